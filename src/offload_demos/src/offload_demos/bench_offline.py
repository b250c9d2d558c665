"""`make bench-offline`: how fast bags become transitions and how fast the DQN trains offline.

Writes bags of decision/outcome pairs (lz4 chunks, as `rosbag record --lz4` writes, with a link
latency topic the reader must skip), then measures, on this machine and this run:
  - transitions ingested per second: one bag in one process, then all bags in parallel processes;
  - offline training steps per second at batch 64 (torch, one thread).
The bar: >= 20,000 transitions/s and >= 300 steps/s. Exit status 2 when a figure is below it.
"""
import argparse
import os
import shutil
import sys
import tempfile
import time

import numpy as np
import torch

from offload_demos.bag_writer import installed_definitions, probe_request, typestore_for, write_requests
from offload_learner_py.data.bags import read_bag, read_bags
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.offline.retrain import train_offline
from offload_learner_py.core.reward import reward

INGEST_BAR = 20_000
TRAIN_BAR = 300

LATENCY_MSG = "Header header\nuint8 source\nbool reachable\nfloat64 round_trip_s\n"


def synthetic_requests(n: int, seed: int, first_id: int):
    rng = np.random.default_rng(seed)
    d = 10 ** rng.uniform(-2, 0.7, n)
    u = rng.uniform(0.2, 1.0, n)
    b = rng.uniform(0.02, 0.06, n)
    local_s = 0.005 + 0.04 * d / u
    cloud_s = b + 0.01 * d
    action = rng.integers(0, 2, n)
    for i in range(n):
        a = int(action[i])
        yield probe_request(first_id + i, float(d[i]), float(u[i]), float(b[i]), float(local_s[i]),
                            float(cloud_s[i]), a, 0.5, reward(a, float(local_s[i]), float(cloud_s[i])),
                            probe=i % 4 != 3, loss=0.01)


def write_bench_bags(directory: str, bags: int, requests: int) -> list:
    store = typestore_for(*installed_definitions(), {"offload_msgs/msg/LinkLatency": LATENCY_MSG})

    def latency(bag, index, time_ns):
        bag.write("/cloud_bridge/latency", "offload_msgs/msg/LinkLatency", {"round_trip_s": 0.03, "reachable": True},
                  time_ns)

    paths = []
    for k in range(bags):
        path = os.path.join(directory, f"bench_{k}.bag")
        write_requests(path, synthetic_requests(requests, k, 1_000_000 * (k + 1)), store=store, compression="lz4",
                       extra=latency)
        paths.append(path)
    return paths


def measure_ingest(paths: list, workers: int) -> dict:
    began = time.perf_counter()
    _, report = read_bag(paths[0])
    single_s = time.perf_counter() - began
    began = time.perf_counter()
    data = read_bags(paths, workers=workers)
    parallel_s = time.perf_counter() - began
    return {"single_bag_transitions": report.requests, "single_bag_per_s": report.requests / single_s,
            "parallel_transitions": len(data.log), "parallel_per_s": len(data.log) / parallel_s,
            "workers": workers, "table_rows": int(data.log["outcome_reward_valid"].sum())}


def measure_training(paths: list, steps: int) -> dict:
    table = read_bags(paths[:1], workers=1).transition_table()
    config = DQNConfig(seed=1, batch_size=64)
    train_offline(table.slice(0, 2000), config, 50)   # warm-up: allocator, kernels
    began = time.perf_counter()
    result = train_offline(table, config, steps)
    seconds = time.perf_counter() - began
    return {"steps": steps, "steps_per_s": steps / seconds, "rows": len(table),
            "final_loss": float(result.losses[-100:].mean())}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bags", type=int, default=4)
    parser.add_argument("--requests", type=int, default=25_000, help="requests per bag")
    parser.add_argument("--steps", type=int, default=2000, help="training steps to time")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    directory = tempfile.mkdtemp(prefix="bench_offline_")
    try:
        began = time.perf_counter()
        paths = write_bench_bags(directory, args.bags, args.requests)
        size_mb = sum(os.path.getsize(p) for p in paths) / 1e6
        print(f"wrote {args.bags} bags x {args.requests} requests ({size_mb:.1f} MB, lz4) in "
              f"{time.perf_counter() - began:.1f} s")
        ingest = measure_ingest(paths, args.workers)
        training = measure_training(paths, args.steps)
    finally:
        shutil.rmtree(directory, ignore_errors=True)
    print(f"ingest, one bag, one process:   {ingest['single_bag_per_s']:10,.0f} transitions/s "
          f"({ingest['single_bag_transitions']} transitions)")
    print(f"ingest, {args.bags} bags, {ingest['workers']} processes: {ingest['parallel_per_s']:10,.0f} transitions/s "
          f"({ingest['parallel_transitions']} transitions, {ingest['table_rows']} with both latencies)")
    print(f"offline training, batch 64:     {training['steps_per_s']:10,.0f} steps/s "
          f"({training['steps']} steps on {training['rows']} rows, one torch thread)")
    ok = ingest["single_bag_per_s"] >= INGEST_BAR and training["steps_per_s"] >= TRAIN_BAR
    print(f"bar: >= {INGEST_BAR:,} transitions/s (one process) and >= {TRAIN_BAR} steps/s: "
          f"{'met' if ok else 'NOT met on this run'} (load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)")
    return 0 if ok else 2


if __name__ == "__main__":
    sys.exit(main())
