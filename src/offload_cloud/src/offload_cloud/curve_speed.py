"""Which libzmq and libsodium encrypt this process's CURVE traffic. pyzmq's binary wheels bundle a libsodium
built without its optimised code: crypto_box ran at 57 MiB/s on the development machine, against 1.3-1.5 GiB/s
for Debian's libsodium23. At 57 MiB/s one client's 64 MiB message holds a libzmq I/O thread (and the robot's
CPU that sends it) for over a second. The workspace builds pyzmq on the system libzmq (requirements.txt,
`--no-binary pyzmq`); a cloud host should do the same (src/offload_cloud/README.md).

Run as a script (`python curve_speed.py`, which needs only pyzmq: the Makefile runs it before the workspace
is built) it exits 1 when the bundled libsodium is in use."""
import pathlib
from typing import List

import zmq

WHEEL_LIBS_DIR = "pyzmq.libs"   # where auditwheel puts the libraries a pyzmq wheel bundles
REMEDY = ("apt-get install libzmq3-dev && pip install --force-reinstall --no-deps --no-binary pyzmq "
          f"pyzmq=={zmq.__version__}")


def loaded_libraries(maps_path: str = "/proc/self/maps") -> List[str]:
    """Paths of the libzmq and libsodium shared objects mapped into this process (Linux)."""
    try:
        text = pathlib.Path(maps_path).read_text()
    except OSError:
        return []
    fields = (line.split(None, 5) for line in text.splitlines())
    paths = {parts[5] for parts in fields if len(parts) == 6}
    return sorted(path for path in paths if "libzmq" in path or "libsodium" in path)


def bundled_libsodium(maps_path: str = "/proc/self/maps") -> bool:
    """True when CURVE runs through the libsodium a pyzmq wheel bundles (the slow one)."""
    import zmq.backend   # noqa: F401  (loads libzmq and its libsodium)
    return any(WHEEL_LIBS_DIR in path and "libsodium" in path for path in loaded_libraries(maps_path))


if __name__ == "__main__":
    import sys
    sys.exit(int(bundled_libsodium()))
