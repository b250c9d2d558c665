"""CURVE keys for the one-machine demo, generated on first run into one directory (server/ and robot/
beside each other, as offload_cloud.keys writes them), atomically, so the server and the
bridge starting at the same moment never see half a key set."""
import os
import pathlib
import shutil
import tempfile

from offload_cloud import keys

ROBOT = "robot"


def ensure_demo_keys(keys_root) -> pathlib.Path:
    """keys_root with server/ and robot/ in it, generated unless already there."""
    keys_root = pathlib.Path(keys_root)
    if (keys_root / "server" / keys.SERVER_SECRET).is_file() and (keys_root / ROBOT / keys.CLIENT_SECRET).is_file():
        return keys_root
    keys_root.parent.mkdir(parents=True, exist_ok=True)
    staging = pathlib.Path(tempfile.mkdtemp(prefix=".keys-", dir=keys_root.parent))
    try:
        keys.generate(staging, [ROBOT])
        try:
            os.rename(staging, keys_root)
        except OSError:
            if not (keys_root / "server" / keys.SERVER_SECRET).is_file():
                raise   # not a lost race with another starter: a real failure
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    return keys_root


def ensure_demo_robots(keys_root, names) -> pathlib.Path:
    """The demo's keys (ensure_demo_keys) with a client key for each of `names` too (robots that differ, each
    with its own name to the cloud server and the fleet learner), added unless already there."""
    keys_root = ensure_demo_keys(keys_root)
    missing = [name for name in names if not (keys_root / name / keys.CLIENT_SECRET).is_file()]
    if missing:
        keys.generate(keys_root, missing, add_to=keys_root / "server")
    return keys_root
