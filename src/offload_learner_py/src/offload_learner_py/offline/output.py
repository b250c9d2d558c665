"""Writing results safely: text from bags (topic names, messages, paths) is untrusted, and an output
directory may hold earlier results or be a planted symlink."""
import os
import re

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
