"""One robot's pings while another client key floods the same cloud server with 64 MiB plans (#31 Medium 8).

    python -m offload_demos.bench_flood [--connections 12] [--seconds 8] [--cases frames,one-frame,control]

The other key sends plans on a new 8000 x 8000 map each (64 MiB, never cached) back to back on `--connections`
connections, in its own process, within the server's limits (the plans it got BUSY for are counted). The robot,
another key, pings every 10 ms: first with the server idle, then during the flood. Each case has its own server
process (defaults, 2 I/O threads, 2 workers) and prints ping p50 / p99 / max idle and loaded:

- frames: this release, the maps in frames of 1 MiB (map_frames.py);
- one-frame: each map in one 64 MiB frame, as robots from before the frames sent them, to a server run with
  --max-frame-mib 64 that accepts them: libzmq decrypts such a frame whole on an I/O thread;
- control: the sender floods a second server process while the robot pings its own, idle one: the two share
  nothing but the machine's cores, which is what the robot's pings cannot be spared on a shared host.

Every figure printed is measured in this run.
"""
import argparse
import os
import pathlib
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

from offload_cloud import keys, protocol
from offload_cloud.client import CloudClient
from offload_demos.bench_link import spawn
from offload_demos.loopback import LOOPBACK, free_port

MAP_SIDE = 8000   # 64 MB of cells
CASES = ("frames", "one-frame", "control")


def one_frame_plan(grid: np.ndarray, map_hash: bytes):
    """Frames of a plan carrying `grid` in one frame, as clients from before map_frames.py sent it."""
    def build(request_id):
        frames = protocol.encode_plan(request_id, map_hash, (0, 1), (1, 1))
        return frames + [protocol.map_metadata(grid), memoryview(grid).cast("B")]
    return build


def flood(endpoint: str, keys_dir: str, connections: int, one_frame: bool) -> None:
    """Sends 64 MiB plans on new maps on `connections` connections until SIGTERM, then prints the counts of
    the replies by status as `name=count` words."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    counts, lock = {}, threading.Lock()

    def sender(seed: int) -> None:
        rng = np.random.default_rng(seed)
        with CloudClient(endpoint, keys_dir=keys_dir, timeout_s=60, retries=0) as client:
            while not stop.is_set():
                grid = np.zeros((MAP_SIDE, MAP_SIDE), np.int8)
                grid[0, rng.integers(2, MAP_SIDE)] = 100   # a new map each time: never cached
                try:
                    if one_frame:
                        status = client.request(one_frame_plan(grid, protocol.grid_hash(grid))).status.name
                    else:
                        status = client.plan(grid, (0, 1), (1, 1)).reply.status.name
                except Exception as error:   # a timeout or a dropped connection counts as what it is
                    status = type(error).__name__
                with lock:
                    counts[status] = counts.get(status, 0) + 1
    for seed in range(connections):
        threading.Thread(target=sender, args=(seed,), daemon=True).start()
    print("sending", flush=True)
    stop.wait()
    with lock:
        print(" ".join(f"{name}={count}" for name, count in sorted(counts.items())), flush=True)
    os._exit(0)   # the senders may be mid-plan


def start_flood(endpoint: str, keys_dir, connections: int, one_frame: bool = False) -> subprocess.Popen:
    """The flood as its own process (as on its own machine: no GIL or allocator shared with the pings), once it
    sends."""
    process = subprocess.Popen([sys.executable, "-m", "offload_demos.bench_flood", "--flood", endpoint, str(keys_dir),
                                str(connections)] + (["--one-frame"] if one_frame else []),
                               stdout=subprocess.PIPE, text=True)
    process.stdout.readline()
    return process


def stop_flood(process: subprocess.Popen) -> dict:
    """Stops the flood; its reply counts by status."""
    process.terminate()
    out, _ = process.communicate(timeout=120)
    words = out.split()
    return {name: int(count) for name, count in (word.split("=") for word in words if "=" in word)}


def ping_for(client: CloudClient, seconds: float) -> np.ndarray:
    """Ping round trips (ms), one every 10 ms for `seconds`."""
    samples, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        samples.append(client.ping() * 1e3)
        time.sleep(0.01)
    return np.array(samples)


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) process `pid` has used."""
    fields = pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def summary(samples: np.ndarray) -> str:
    return (f"p50 {np.median(samples):.2f} ms, p99 {np.percentile(samples, 99):.2f} ms, max {samples.max():.1f} ms "
            f"({len(samples)} pings)")


def run_case(case: str, server_keys, robot_keys, other_keys, connections: int, seconds: float) -> None:
    ports = [free_port()] + ([free_port()] if case == "control" else [])
    extra = ["--max-frame-mib", "64"] if case == "one-frame" else []
    servers = [spawn(["-m", "offload_cloud", "--bind", f"tcp://{LOOPBACK}:{port}", "--log-level", "ERROR",
                      "--keys-dir", str(server_keys), *extra]) for port in ports]
    try:
        with CloudClient(f"tcp://{LOOPBACK}:{ports[0]}", keys_dir=str(robot_keys), timeout_s=30) as robot:
            idle = ping_for(robot, min(3.0, seconds / 3))
            flooded = servers[-1].pid
            sender = start_flood(f"tcp://{LOOPBACK}:{ports[-1]}", other_keys, connections, case == "one-frame")
            try:
                time.sleep(2.0)   # every connection mid-plan
                cpu_before = cpu_s(flooded)
                loaded = ping_for(robot, seconds)
                cpu_used_s = cpu_s(flooded) - cpu_before
            finally:
                counts = stop_flood(sender)
        print(f"[{case}] idle: {summary(idle)}", flush=True)
        print(f"[{case}] while another key sent 64 MiB plans on {connections} connections: {summary(loaded)}; "
              f"its replies: {' '.join(f'{k} {v}' for k, v in sorted(counts.items())) or 'none'}; the flooded server "
              f"used {cpu_used_s / seconds:.2f} cores meanwhile", flush=True)
    finally:
        for server in servers:
            server.kill()
            server.wait()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--connections", type=int, default=12, help="the flooding key's connections (default 12)")
    parser.add_argument("--seconds", type=float, default=8.0, help="pinging time during each flood (default 8)")
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    parser.add_argument("--flood", nargs=3, help=argparse.SUPPRESS)   # ENDPOINT KEYS CONNECTIONS
    parser.add_argument("--one-frame", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.flood:
        flood(args.flood[0], args.flood[1], int(args.flood[2]), args.one_frame)
        return 0
    cases = args.cases.split(",")
    if set(cases) - set(CASES):
        parser.error(f"unknown case(s) {', '.join(sorted(set(cases) - set(CASES)))}")
    print(f"{os.cpu_count()} cores; one robot pings every 10 ms, another key sends 64 MiB plans on "
          f"{args.connections} connections for {args.seconds:g} s", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        server_keys = keys.generate(pathlib.Path(tmp), ["robot", "other"])
        for case in cases:
            run_case(case, server_keys, pathlib.Path(tmp) / "robot", pathlib.Path(tmp) / "other", args.connections,
                     args.seconds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
