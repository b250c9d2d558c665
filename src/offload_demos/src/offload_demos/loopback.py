"""Loopback ports for the demo, tests and benchmarks that start servers of their own, and stopping those servers."""
import contextlib
import random
import socket
import subprocess
import time
from typing import Optional, Tuple

LOOPBACK = "127.0.0.1"
PORT_RANGE_FILE = "/proc/sys/net/ipv4/ip_local_port_range"
LOWEST_PORT = 10000


def ephemeral_ports(path: str = PORT_RANGE_FILE) -> Tuple[int, int]:
    """The kernel's range for the local ports of outgoing connections (Linux's default when it cannot be read)."""
    try:
        with open(path) as stream:
            low, high = (int(field) for field in stream.read().split()[:2])
        return low, high
    except (OSError, ValueError):
        return 32768, 60999


def free_port(attempts: int = 200) -> int:
    """A TCP port on the loopback interface that is free now, below the kernel's ephemeral range. A port the OS
    picks (bind to 0) comes from that range, which every outgoing connection draws from too: between the pick and a
    server's bind, one of a launch's own connections (the master's, a node's) took it, and the server died with
    "Address already in use" (a bench run, 2026-11-28)."""
    high = ephemeral_ports()[0]
    low = LOWEST_PORT if high > LOWEST_PORT + 1000 else 1024
    for _ in range(attempts):
        port = random.randrange(low, high)
        with socket.socket() as probe:
            try:
                probe.bind((LOOPBACK, port))
            except OSError:
                continue
        return port
    raise OSError(f"no free loopback port in [{low}, {high}) after {attempts} tries")


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
