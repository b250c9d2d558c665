"""Loopback ports for the demo, tests and benchmarks that start servers of their own, and stopping those servers."""
import contextlib
import socket
import subprocess
import time
from typing import Optional

LOOPBACK = "127.0.0.1"


def free_port() -> int:
    """A TCP port on the loopback interface that is free now (the OS picks it)."""
    with socket.socket() as probe:
        probe.bind((LOOPBACK, 0))
        return probe.getsockname()[1]


def wait_for_port(port: int, timeout_s: float) -> bool:
    """True once something accepts connections on the loopback port, False after timeout_s."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection((LOOPBACK, port), timeout=0.2):
            return True
        time.sleep(0.05)
    return False


def stop_process(process: Optional[subprocess.Popen], grace_s: float = 20.0) -> None:
    """SIGTERM, then SIGKILL after grace_s: a node or server gets the chance to close its bag or sockets, and a
    hung one still goes. None or an exited process: nothing to do."""
    if process is None or process.poll() is not None:
        return
    process.terminate()
    try:
        process.wait(grace_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
