"""Shared pieces of the cloud link tests: keys, a server on a random loopback port, a server subprocess
that can be killed, and maps."""
import os
import pathlib
import select
import subprocess
import sys
import threading
import time

import numpy as np
import zmq

from offload_cloud import keys
from offload_cloud.keys import load_client_keys
from offload_demos.loopback import free_port  # noqa: F401  (re-exported for the tests)
from offload_cloud.server import CloudServer, ServerConfig

LOOPBACK = "tcp://127.0.0.1"
MIB = 1 << 20
# The attack tests at full scale (200,000 uploads, a 20-robot storm on a 2000 x 2000 map): OFFLOAD_ATTACK_SCALE=full
FULL = os.environ.get("OFFLOAD_ATTACK_SCALE") == "full"


def make_keys(directory: pathlib.Path, clients=("robot",)) -> pathlib.Path:
    """Server keys dir; client dirs are directory / name."""
    return keys.generate(directory, list(clients))


def start_server(server_keys=None, **overrides) -> CloudServer:
    config = ServerConfig(bind=f"{LOOPBACK}:0", keys_dir=str(server_keys) if server_keys else None,
                          insecure=server_keys is None, **overrides)
    server = CloudServer(config)
    server.start()
    return server


def curve_dealer(context, key_dir, endpoint):
    """A raw DEALER socket with a robot's CURVE keys, for tests that speak the wire protocol by hand."""
    dealer = context.socket(zmq.DEALER)
    dealer.linger = 0
    dealer.curve_publickey, dealer.curve_secretkey, dealer.curve_serverkey = load_client_keys(key_dir)
    dealer.connect(endpoint)
    return dealer


def spawn_server(port: int, server_keys, workers: int = 2, timeout_s: float = 20.0, extra_args=(),
                 log_path=None, preexec_fn=None) -> subprocess.Popen:
    """The server as its own process (so a test can SIGKILL it or measure its memory); returns once it
    listens. server_keys None: --insecure. Its log goes to `log_path` when given; `preexec_fn` runs in the
    child before it starts (e.g. to set its descriptor limit)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    keys_args = ["--keys-dir", str(server_keys)] if server_keys is not None else ["--insecure"]
    log = open(log_path, "w") if log_path else subprocess.DEVNULL
    process = subprocess.Popen(
        [sys.executable, "-m", "offload_cloud", "--bind", f"{LOOPBACK}:{port}",
         "--workers", str(workers), *keys_args, "--log-level", "WARNING", *extra_args],
        stdout=subprocess.PIPE, stderr=log, env=env, text=True, preexec_fn=preexec_fn)
    if log_path:
        log.close()
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        ready, _, _ = select.select([process.stdout], [], [], 0.2)
        if ready and "listening on" in process.stdout.readline():
            return process
        if process.poll() is not None:
            break
    process.kill()
    process.wait()
    raise RuntimeError("cloud server subprocess did not start")


def stop_process(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.kill()
    process.wait(10)
    if process.stdout:
        process.stdout.close()


def rss_bytes(pid: int) -> int:
    """Resident set size of a process, from /proc."""
    with open(f"/proc/{pid}/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for process {pid}")


class PeakRss:
    """A process's peak RSS above its size at start(), sampled every 2 ms in a thread until stop()."""

    def __init__(self, pid: int):
        self.pid, self.idle, self.peak = pid, 0, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    def start(self) -> None:
        self.idle = self.peak = rss_bytes(self.pid)
        self._thread.start()

    def _watch(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_bytes(self.pid))
            time.sleep(0.002)

    def stop(self) -> int:
        """Bytes the peak was above the start."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        return self.peak - self.idle


def random_map(width: int, height: int, obstacle_share: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    grid = np.where(rng.random((height, width)) < obstacle_share, 100, 0).astype(np.int8)
    grid[0, 0] = grid[-1, -1] = 0
    return grid
