"""Versioned `.npz` files: named arrays plus a format tag and JSON metadata, never pickles. Shared by the
transition tables and the planning traces."""
import json
import zipfile
from typing import Dict, Iterable, Mapping, Tuple

import numpy as np


def save_versioned_npz(path: str, file_format: str, metadata: Mapping, arrays: Mapping[str, np.ndarray]) -> None:
    np.savez_compressed(path, format=np.array(file_format), metadata=np.array(json.dumps(dict(metadata))),
                        **arrays)


def load_versioned_npz(path: str, file_format: str, names: Iterable[str], what: str) -> Tuple[Dict, Dict]:
    """(arrays by name, metadata) of a file written by save_versioned_npz with `file_format`. A missing,
    corrupt or foreign file raises ValueError saying which and why."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            found = str(archive["format"]) if "format" in archive.files else None
            if found != file_format:
                raise ValueError(f"{path} is not a {what} ({file_format}), format is {found!r}")
            missing = [name for name in names if name not in archive.files]
            if missing:
                raise ValueError(f"{path} lacks {what} arrays {missing}")
            return {name: archive[name] for name in names}, json.loads(str(archive["metadata"]))
    except (OSError, EOFError, zipfile.BadZipFile, json.JSONDecodeError, KeyError) as error:
        raise ValueError(f"{path}: cannot read {what}: {error}") from error
