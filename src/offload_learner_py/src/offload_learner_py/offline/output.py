"""Writing results safely: text from bags (topic names, messages, paths) is untrusted, and an output
directory may hold earlier results or be a planted symlink; JSON is strict (no NaN), and an output path is
checked before a long run, not after."""
import json
import os
import re
import tempfile

import numpy as np

_CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")   # keeps tab and newline


def terminal_text(text: str) -> str:
    """Control characters (escape sequences that would drive a terminal) shown as \\xNN."""
    return _CONTROL.sub(lambda m: f"\\x{ord(m.group()):02x}", str(text))


def code_block(text: str) -> str:
    """Text that cannot close the Markdown code fence it is put in, nor drive a terminal."""
    return terminal_text(text).replace("```", "'''")


class OutputDirError(ValueError):
    """An --out directory the command must not write into; the message is one line."""


def prepare_out_dir(path: str, force: bool = False) -> str:
    """Create `path` for results. Refuses a symlink (never followed), a file, an unwritable place, and a
    directory that already holds something unless `force` (then its files are overwritten)."""
    if os.path.islink(path):
        raise OutputDirError(f"--out {path} is a symbolic link: refusing to follow it")
    if os.path.exists(path):
        if not os.path.isdir(path):
            raise OutputDirError(f"--out {path} is a file, not a directory")
        if os.listdir(path) and not force:
            raise OutputDirError(f"--out {path} already holds results: pass --force to overwrite them, or choose "
                                 "another directory")
    else:
        try:
            os.makedirs(path)
        except OSError as error:
            raise OutputDirError(f"--out {path}: cannot create it ({error.strerror})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise OutputDirError(f"--out {path} is not writable")
    return path


def write_json(path: str, values: dict) -> None:
    """Strict JSON (RFC 8259 has no NaN or Infinity): a number that is not finite, such as the threshold
    of a policy that never switches, is written as null."""
    temp_path = path + ".tmp"
    with open(temp_path, "w") as out:
        json.dump(finite_or_null(values), out, indent=2, allow_nan=False)
        out.write("\n")
    os.replace(temp_path, path)


def finite_or_null(value):
    if isinstance(value, dict):
        return {key: finite_or_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [finite_or_null(item) for item in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if value is None or isinstance(value, str):
        return value
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def require_writable_dir(path: str) -> None:
    """Create the output directory and write a probe file in it, so a bad --out fails before the run."""
    try:
        os.makedirs(path, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as error:
        raise OSError(f"{path}: cannot write the output directory: {error}") from error


def require_writable_file(path: str) -> None:
    if os.path.isdir(path):
        raise OSError(f"{path}: cannot write the output file: it is a directory")
    directory = os.path.dirname(os.path.abspath(path))
    try:
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as error:
        raise OSError(f"{path}: cannot write the output file: {error}") from error
