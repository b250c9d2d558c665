"""Versioned `.npz` files: named arrays plus a format tag and JSON metadata, never pickles. Shared by the
transition tables and the planning traces."""
import json
import zipfile
import zlib
from typing import Callable, Dict, Iterable, Mapping, Tuple

import numpy as np

# What reading a missing, truncated, corrupt or foreign file can raise. The members of an .npz are
# read lazily, so a damaged compressed member only fails inside archive[name] (zlib.error), and a
# damaged array header fails in numpy's parser (ValueError).
_READ_ERRORS = (OSError, EOFError, zipfile.BadZipFile, zlib.error, json.JSONDecodeError, KeyError, ValueError,
                UnicodeDecodeError)


def save_versioned_npz(path: str, file_format: str, metadata: Mapping, arrays: Mapping[str, np.ndarray]) -> None:
    np.savez_compressed(path, format=np.array(file_format), metadata=np.array(json.dumps(dict(metadata))),
                        **arrays)


def load_versioned_npz(path: str, file_format: str, names: Iterable[str], what: str) -> Tuple[Dict, Dict]:
    """(arrays by name, metadata) of a file written by save_versioned_npz with `file_format`. A missing,
    corrupt or foreign file raises ValueError naming the file and saying why."""
    names = tuple(names)
    try:
        with open(path, "rb") as source:
            magic = source.read(4)
    except OSError as error:
        raise ValueError(f"{path}: cannot read {what}: {error}") from error
    if magic != b"PK\x03\x04":  # every .npz is a zip archive
        raise ValueError(f"{path} is not a {what} ({file_format}): not an .npz (zip) archive")
    try:
        archive = np.load(path, allow_pickle=False)
    except _READ_ERRORS as error:
        raise ValueError(f"{path}: cannot read {what}: {error}") from error
    if not isinstance(archive, np.lib.npyio.NpzFile):  # a bare .npy array
        raise ValueError(f"{path} is not a {what} ({file_format}): it holds one bare array, not an .npz archive")
    with archive:
        try:
            found = str(archive["format"]) if "format" in archive.files else None
        except _READ_ERRORS as error:
            raise ValueError(f"{path}: cannot read {what}: its format tag is unreadable: {error}") from error
        if found != file_format:
            raise ValueError(f"{path} is not a {what} ({file_format}), format is {found!r}")
        missing = [name for name in names + ("metadata",) if name not in archive.files]
        if missing:
            raise ValueError(f"{path} lacks {what} arrays {missing}")
        arrays = {}
        for name in names + ("metadata",):
            try:
                arrays[name] = archive[name]
            except _READ_ERRORS as error:
                raise ValueError(f"{path}: cannot read {what}: array {name!r} is corrupt: {error}") from error
    try:
        metadata = json.loads(str(arrays.pop("metadata")))
    except (json.JSONDecodeError, ValueError) as error:
        raise ValueError(f"{path}: cannot read {what}: its metadata is not JSON: {error}") from error
    if not isinstance(metadata, dict):
        raise ValueError(f"{path}: cannot read {what}: its metadata is a {type(metadata).__name__}, not an object")
    return arrays, metadata


def load_versioned(build: Callable, path: str, file_format: str, names: Iterable[str], what: str):
    """`build(**arrays, metadata=metadata)` from the file; its ValueError on invalid content is raised
    again naming the file."""
    arrays, metadata = load_versioned_npz(path, file_format, names, what)
    try:
        return build(**arrays, metadata=metadata)
    except ValueError as error:
        raise ValueError(f"{path}: invalid {what}: {error}") from error
