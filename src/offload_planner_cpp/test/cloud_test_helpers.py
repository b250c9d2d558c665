"""Shared pieces of the cloud link tests: keys, a server on a random loopback port, a server subprocess
that can be killed, and maps."""
import os
import pathlib
import select
import socket
import subprocess
import sys
import time

import numpy as np

from offload_planner_cpp.cloud import keys
from offload_planner_cpp.cloud.server import CloudServer, ServerConfig

LOOPBACK = "tcp://127.0.0.1"


def make_keys(directory: pathlib.Path, clients=("robot",)) -> pathlib.Path:
    """Server keys dir; client dirs are directory / name."""
    return keys.generate(directory, list(clients))


def start_server(server_keys=None, **overrides) -> CloudServer:
    config = ServerConfig(bind=f"{LOOPBACK}:0", keys_dir=str(server_keys) if server_keys else None,
                          insecure=server_keys is None, **overrides)
    server = CloudServer(config)
    server.start()
    return server


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def spawn_server(port: int, server_keys, workers: int = 2, timeout_s: float = 20.0) -> subprocess.Popen:
    """The server as its own process (so a test can SIGKILL it); returns once it listens."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    process = subprocess.Popen(
        [sys.executable, "-m", "offload_planner_cpp.cloud.server", "--bind", f"{LOOPBACK}:{port}",
         "--workers", str(workers), "--keys-dir", str(server_keys), "--log-level", "WARNING"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env, text=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready, _, _ = select.select([process.stdout], [], [], 0.2)
        if ready and "listening on" in process.stdout.readline():
            return process
        if process.poll() is not None:
            break
    process.kill()
    raise RuntimeError("cloud server subprocess did not start")


def random_map(width: int, height: int, obstacle_share: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    grid = np.where(rng.random((height, width)) < obstacle_share, 100, 0).astype(np.int8)
    grid[0, 0] = grid[-1, -1] = 0
    return grid
