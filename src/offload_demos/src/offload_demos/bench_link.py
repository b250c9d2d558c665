"""Cloud link benchmark (make bench-link). Every figure printed is measured in this run, on loopback.

1. Link overhead: a cloud plan on a cached map, round trip minus the server-reported planning time,
   against a raw pyzmq REQ/REP round trip carrying the same request and reply sizes, each server in its
   own process, both with CURVE and both in plaintext. Median and p99; --runs N repeats it (each run
   followed by its own raw baseline).
2. Bytes on the wire per request after the upload: TCP payload counted by the WAN emulator (no delay); and the
   robot bridge's CPU per cloud plan without ROS (2048 x 2048 map, 1000-pose paths). --only-link stops here.
3. Throughput with 1 and 2 workers: plans/s from concurrent clients on a 2000 x 2000 map.
4. One robot's ping round trip, idle and while another client key sends 64 MiB plans (a new 8000 x 8000
   map each), with 1 libzmq I/O thread (the baseline) and with the server's default of 2; and the control:
   the same sender loading another server process, so what the robot's server adds is told apart from
   what the machine's two cores cost.
"""
import argparse
import os
import pathlib
import select
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
import zmq

from offload_cloud import keys, protocol
from offload_cloud.client import CloudClient
from offload_cloud.keys import load_client_keys, load_server_keys
from offload_demos.loopback import LOOPBACK, free_port
from offload_demos.wan_emulator import LinkModel, WanEmulator


def wait_listening(process: subprocess.Popen) -> None:
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        ready, _, _ = select.select([process.stdout], [], [], 0.2)
        if ready and "listening on" in process.stdout.readline():
            return
        if process.poll() is not None:
            break
    raise RuntimeError("server did not start")


def spawn(args) -> subprocess.Popen:
    process = subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                               text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    wait_listening(process)
    return process


def spawn_cloud(port: int, server_keys, workers: int, io_threads: int = 2) -> subprocess.Popen:
    # The benchmark's clients wait up to 60 s, so the server may let requests wait as long: throughput is
    # measured at saturation, where the default --max-wait-s would answer part of the queue BUSY.
    args = ["-m", "offload_cloud", "--bind", f"tcp://{LOOPBACK}:{port}", "--workers",
            str(workers), "--io-threads", str(io_threads), "--log-level", "WARNING", "--max-wait-s", "60"]
    return spawn(args + (["--keys-dir", str(server_keys)] if server_keys else ["--insecure"]))


def echo_server(port: int, reply_bytes: int, server_keys) -> None:
    """Raw REP server: answers every request with `reply_bytes` bytes, nothing else."""
    context = zmq.Context()
    socket = context.socket(zmq.REP)
    socket.linger = 0
    if server_keys:
        public, secret, _ = load_server_keys(server_keys)
        socket.curve_publickey, socket.curve_secretkey, socket.curve_server = public, secret, True
    socket.bind(f"tcp://{LOOPBACK}:{port}")
    print("listening on", port, flush=True)
    reply = bytes(reply_bytes)
    while socket.poll(60_000):
        socket.recv()
        socket.send(reply)


def raw_round_trips(port: int, request_bytes: int, count: int, client_keys) -> np.ndarray:
    context = zmq.Context()
    socket = context.socket(zmq.REQ)
    socket.linger = 0
    if client_keys:
        socket.curve_publickey, socket.curve_secretkey, socket.curve_serverkey = load_client_keys(client_keys)
    socket.connect(f"tcp://{LOOPBACK}:{port}")
    request = bytes(request_bytes)
    samples = np.empty(count)
    for k in range(-50, count):   # 50 warm-up round trips
        started = time.perf_counter()
        socket.send(request)
        if not socket.poll(5000):
            raise RuntimeError("raw echo server did not answer")
        socket.recv()
        if k >= 0:
            samples[k] = time.perf_counter() - started
    socket.close(0)
    context.term()
    return samples


def cloud_overheads(endpoint: str, grid, start, goal, count: int, client_keys):
    """(round trip minus server planning time per request, request bytes, reply bytes)."""
    with CloudClient(endpoint, keys_dir=client_keys, insecure=client_keys is None, timeout_s=30) as client:
        client.plan(grid, start, goal)   # uploads the map
        map_hash = protocol.grid_hash(grid)
        samples = np.empty(count)
        for k in range(-50, count):
            outcome = client.plan(grid, start, goal, map_hash=map_hash)
            assert outcome.reply.status == protocol.Status.OK and not outcome.uploaded
            if k >= 0:
                samples[k] = outcome.round_trip_s - outcome.reply.planning_time_s
        request = sum(len(f) for f in protocol.encode_plan(1, map_hash, start, goal))
        reply = sum(len(f) for f in protocol.encode_reply(outcome.reply))
    print(f"cached plan: {len(outcome.reply.path)} path cells, server planning time "
          f"{outcome.reply.planning_time_s * 1e3:.3f} ms")
    return samples, request, reply


def wire_bytes(endpoint: str, grid, start, goal, count: int, client_keys):
    emulator = WanEmulator(f"tcp://{LOOPBACK}:0", endpoint, LinkModel())
    proxied = emulator.start()
    try:
        with CloudClient(proxied, keys_dir=client_keys, insecure=client_keys is None, timeout_s=30) as client:
            client.plan(grid, start, goal)
            time.sleep(0.2)
            up, down = emulator.bytes_up, emulator.bytes_down
            map_hash = protocol.grid_hash(grid)
            for _ in range(count):
                client.plan(grid, start, goal, map_hash=map_hash)
            time.sleep(0.2)
            return (emulator.bytes_up - up) / count, (emulator.bytes_down - down) / count
    finally:
        emulator.stop()


def throughput(endpoint: str, grid, jobs, clients: int, client_keys) -> float:
    done = []
    map_hash = protocol.grid_hash(grid)

    def robot(index):
        with CloudClient(endpoint, keys_dir=client_keys, insecure=client_keys is None, timeout_s=60) as client:
            client.plan(grid, *jobs[0], map_hash=map_hash)
            for start, goal in jobs[index::clients]:
                # a no-path answer is a served plan too
                assert protocol.is_planner_status(client.plan(grid, start, goal, map_hash=map_hash).reply.status)
                done.append(1)

    started = time.perf_counter()
    threads = [threading.Thread(target=robot, args=(k,)) for k in range(clients)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return len(done) / (time.perf_counter() - started)


def large_plans(endpoint: str, keys_dir: str) -> None:
    """Another robot (its own process, as on its own machine: no GIL or allocator shared with the one measured)
    sending 64 MiB plans back to back until SIGTERM; prints how many it sent."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    sent = 0
    with CloudClient(endpoint, keys_dir=keys_dir, timeout_s=120) as other:
        rng = np.random.default_rng(1)
        print("sending", flush=True)
        while not stop.is_set():
            grid = np.zeros((8000, 8000), np.int8)
            grid[0, rng.integers(2, 8000)] = 100     # a new map each time: 64 MiB up, hashed and cached
            other.plan(grid, (0, 1), (1, 1))
            sent += 1
    print(sent, flush=True)


def pings_under_large_plans(endpoint: str, robot_keys, other_keys, seconds: float = 15.0,
                            sender_endpoint: str = None):
    """One robot's ping round trips (s) idle for `seconds` / 3, then for `seconds` while another key sends 64 MiB
    plans (to `sender_endpoint`, default the same server); how many it sent and for how long (s)."""
    def ping_for(client, duration_s):
        samples, end = [], time.monotonic() + duration_s
        while time.monotonic() < end:
            samples.append(client.ping())
            time.sleep(0.01)
        return np.array(samples)
    with CloudClient(endpoint, keys_dir=robot_keys, timeout_s=30) as robot:
        idle = ping_for(robot, seconds / 3)
        sender = subprocess.Popen([sys.executable, __file__, "--large-plans", sender_endpoint or endpoint,
                                   str(other_keys)],
                                  stdout=subprocess.PIPE, text=True)
        began = time.monotonic()
        try:
            sender.stdout.readline()       # connected and sending
            began = time.monotonic()
            time.sleep(2.0)
            loaded = ping_for(robot, seconds)
        finally:
            sender.terminate()
            out, _ = sender.communicate(timeout=120)
            sending_s = time.monotonic() - began
    last = out.split()[-1] if out.split() else ""
    return idle, loaded, int(last) if last.isdigit() else 0, sending_s


def bridge_cpu(endpoint: str, client_keys: str, count: int, gap_s: float = 0.0):
    """The robot bridge's request path without ROS (CloudBridge.plan, its reply check and the path's poses written
    as the node writes them, then the node's PlanPath response) on a 2048 x 2048 map, 1000-pose paths: per
    request, the calling thread's CPU (what the node's cpu_s accounts) and the whole process's (the client's
    libzmq I/O thread too), in seconds; and the poses of one path. With gap_s, a pause before each request, as a
    robot asks a few times a second: each request then meets caches its last one no longer warms."""
    from genpy import Time
    from offload_cloud.bridge import BridgeConfig, CloudBridge, StampedPose
    from offload_learner_py.nodes.cloud_bridge import plan_response
    from offload_learner_py.nodes.path_wire import pose_count, pose_row_prefix
    side, resolution = 2048, 0.05
    grid = np.full((side, side), 100, np.int8)
    grid[1024, 24:1024] = 0           # a corridor: a 1000-cell path that the planner finds in a fraction of a ms
    bridge = CloudBridge(BridgeConfig(endpoint=endpoint, keys_dir=client_keys))
    try:
        assert bridge.set_map(grid.reshape(-1), side, side, resolution, 0.0, 0.0, (0, 0, 0, 1), "map", None) == ""
        bridge.heartbeat()            # uploads the map, as the node's heartbeat does
        bridge.wait_for_upload(60)
        start, goal = (StampedPose("map", (x + 0.5) * resolution, 1024.5 * resolution) for x in (24, 1023))
        thread_s, process_s = np.empty(count), np.empty(count)
        for k in range(-50, count):
            if gap_s:
                time.sleep(gap_s)
            began_thread, began_process = time.thread_time(), time.process_time()
            result = bridge.plan(start, goal, 0.0, lambda frame_id: pose_row_prefix(Time(1, 0), frame_id))
            path = plan_response(result).path   # the node stamps with rospy's clock
            if k >= 0:
                thread_s[k], process_s[k] = time.thread_time() - began_thread, time.process_time() - began_process
            assert result.status.name == "OK", result.message
    finally:
        bridge.close()
    return thread_s, process_s, pose_count(path)


def summary(samples: np.ndarray) -> str:
    return f"median {np.median(samples) * 1e3:.3f} ms, p99 {np.percentile(samples, 99) * 1e3:.3f} ms"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=2000, help="round trips per latency measurement")
    parser.add_argument("--throughput-plans", type=int, default=120, help="plans per throughput measurement")
    parser.add_argument("--runs", type=int, default=1, help="link overhead measurements per mode (medians of each)")
    parser.add_argument("--only-link", action="store_true",
                        help="the link overhead and the bridge's CPU only (no throughput, no fairness)")
    parser.add_argument("--echo", nargs=3, help=argparse.SUPPRESS)   # PORT REPLY_BYTES KEYS|-
    parser.add_argument("--large-plans", nargs=2, help=argparse.SUPPRESS)   # ENDPOINT KEYS
    args = parser.parse_args(argv)
    if args.large_plans:
        large_plans(*args.large_plans)
        return 0
    if args.echo:
        echo_server(int(args.echo[0]), int(args.echo[1]), None if args.echo[2] == "-" else args.echo[2])
        return 0

    rng = np.random.default_rng(0)
    grid = np.where(rng.random((2000, 2000)) < 0.2, 100, 0).astype(np.int8)
    start, goal = (1000, 1000), (1040, 1030)
    grid[start[1], start[0]] = grid[goal[1], goal[0]] = 0
    print(f"map 2000 x 2000 ({grid.nbytes / 2**20:.1f} MiB), cached plan {start} -> {goal}; "
          f"{args.requests} round trips each; {os.cpu_count()} cores")
    processes = []
    with tempfile.TemporaryDirectory() as tmp:
        server_keys = keys.generate(pathlib.Path(tmp), ["bench", "other"])
        client_keys = str(pathlib.Path(tmp) / "bench")
        try:
            for label, skeys, ckeys in (("CURVE", server_keys, client_keys), ("plaintext", None, None)):
                port = free_port()
                processes.append(spawn_cloud(port, skeys, workers=2))
                endpoint = f"tcp://{LOOPBACK}:{port}"
                echo_port, added = free_port(), []
                for run in range(args.runs):   # each run: the link, then the raw baseline right after it
                    overheads, request_bytes, reply_bytes = cloud_overheads(endpoint, grid, start, goal,
                                                                           args.requests, ckeys)
                    if run == 0:
                        processes.append(spawn([__file__, "--echo", str(echo_port), str(reply_bytes),
                                                str(skeys or "-")]))
                    raw = raw_round_trips(echo_port, request_bytes, args.requests, ckeys)
                    added.append((np.median(overheads) - np.median(raw)) * 1e3)
                    print(f"[{label}] cloud plan minus server planning time: {summary(overheads)}")
                    print(f"[{label}] raw pyzmq REQ/REP, {request_bytes} B out / {reply_bytes} B back: "
                          f"{summary(raw)}")
                    print(f"[{label}] link adds {added[-1]:.3f} ms median over raw pyzmq (bar: <= 0.25 ms)")
                if args.runs > 1:
                    print(f"[{label}] added over {args.runs} runs: median {np.median(added):.3f} ms, "
                          f"{min(added):.3f}-{max(added):.3f} ms (bar: <= 0.25 ms)")
                if label == "CURVE":
                    up, down = wire_bytes(endpoint, grid, start, goal, 200, ckeys)
                    print(f"[{label}] after the upload: request payload {request_bytes} B, on the wire "
                          f"{up:.0f} B up / {down:.0f} B down per plan (TCP payload; bar: <= 512 B up)")
                    thread_s, process_s, poses = bridge_cpu(endpoint, client_keys, args.requests // 2)
                    print(f"[bridge] CPU per cloud plan on a 2048 x 2048 map, {poses}-pose paths, without ROS: "
                          f"calling thread median {np.median(thread_s) * 1e3:.3f} ms (mean "
                          f"{np.mean(thread_s) * 1e3:.3f}), whole process median {np.median(process_s) * 1e3:.3f} ms "
                          f"(mean {np.mean(process_s) * 1e3:.3f}; bar: <= 0.5 ms)")
                    thread_s, process_s, _ = bridge_cpu(endpoint, client_keys, 120, gap_s=0.25)
                    print(f"[bridge] the same paced at 4 Hz, as a robot asks (120 requests): calling thread median "
                          f"{np.median(thread_s) * 1e3:.3f} ms (mean {np.mean(thread_s) * 1e3:.3f}), whole process "
                          f"median {np.median(process_s) * 1e3:.3f} ms (mean {np.mean(process_s) * 1e3:.3f})")
            if args.only_link:
                return 0
            free = np.argwhere(grid == 0)
            picks = rng.integers(0, len(free), (args.throughput_plans, 2))
            jobs = [(tuple(free[a][::-1]), tuple(free[b][::-1])) for a, b in picks]
            # The ceiling for 2 workers: the same plans in 1 and 2 threads in this process, no link.
            from offload_planner_cpp import plan_raw
            for threads in (1, 2):
                began = time.perf_counter()
                pool = [threading.Thread(target=lambda part: [plan_raw(grid, *job) for job in part],
                                         args=(jobs[k::threads],)) for k in range(threads)]
                for thread in pool:
                    thread.start()
                for thread in pool:
                    thread.join()
                print(f"[throughput] planner alone, {threads} thread(s), no link: "
                      f"{len(jobs) / (time.perf_counter() - began):.1f} plans/s")
            for workers in (1, 2):
                port = free_port()
                processes.append(spawn_cloud(port, server_keys, workers))
                rate = throughput(f"tcp://{LOOPBACK}:{port}", grid, jobs, clients=4, client_keys=client_keys)
                print(f"[throughput] {workers} worker(s), 4 clients, random start/goal on the 2000 x 2000 map: "
                      f"{rate:.1f} plans/s")
            for io_threads in (1, 2):
                port = free_port()
                processes.append(spawn_cloud(port, server_keys, 1, io_threads))
                idle, loaded, sent, sending_s = pings_under_large_plans(f"tcp://{LOOPBACK}:{port}", client_keys,
                                                                        str(pathlib.Path(tmp) / "other"))
                print(f"[fairness] {io_threads} I/O thread(s): one robot's ping idle {summary(idle)}; while another "
                      f"key sent {sent} plans of 64 MiB ({sent * 64 / sending_s:.0f} MiB/s over CURVE) "
                      f"{summary(loaded)}, max {loaded.max() * 1e3:.1f} ms "
                      f"(p99 {np.percentile(loaded, 99) / np.percentile(idle, 99):.1f}x idle; bar: 3x)")
                shared = np.percentile(loaded, 99)
            # The control: the same sender loads another server process on this machine, so the robot's server
            # shares nothing with it but the cores. What is left is the machine's part, not the server's.
            ports = free_port(), free_port()
            for port in ports:
                processes.append(spawn_cloud(port, server_keys, 1))
            idle, loaded, sent, sending_s = pings_under_large_plans(
                f"tcp://{LOOPBACK}:{ports[0]}", client_keys, str(pathlib.Path(tmp) / "other"),
                sender_endpoint=f"tcp://{LOOPBACK}:{ports[1]}")
            print(f"[fairness] control, the sender on another server process (2 I/O threads): ping idle "
                  f"{summary(idle)}; loaded {summary(loaded)}, max {loaded.max() * 1e3:.1f} ms "
                  f"({np.percentile(loaded, 99) / np.percentile(idle, 99):.1f}x idle, {sent} plans sent); sharing the "
                  f"server: p99 {shared / np.percentile(loaded, 99):.2f}x the control's")
        finally:
            for process in processes:
                process.kill()
                process.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
