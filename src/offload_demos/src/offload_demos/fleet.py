"""Fleet load on the cloud planner: N simulated robots, each with its own map, goals and CURVE key,
against one server or several behind HAProxy (TCP mode, health checks), optionally killing one server
mid-run. Bounded in requests and time; loopback only. A demo and test tool, not shipped to a host.

    python -m offload_demos.fleet --robots 50 --servers 3 --haproxy --kill-at-s 5

Every answer is checked against the robot's own planner on the same map, so a plan from a stale or wrong
map counts as an error. A request is lost when the robot gave up on it (no reply within its deadline,
retries included); the run fails (exit 1) on any lost request or wrong answer. At the end it prints the
STATS of every server still alive (asked directly, not through HAProxy).
"""
import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
import zmq

from offload_planner_cpp import PlanStatus, plan_raw
from offload_cloud import keys
from offload_cloud.client import CloudClient, CloudTimeout
from offload_cloud.protocol import ProtocolError, Status, is_planner_status
from offload_cloud.server import CloudServer
from offload_demos.loopback import LOOPBACK, free_port, wait_for_port

def haproxy_config(frontend_port: int, server_ports: List[int], stats_port: Optional[int] = None) -> str:
    """TCP load balancing of ZeroMQ connections. A connection stays on its server; when that server dies
    its sessions are shut (on-marked-down), the robot's socket reconnects and HAProxy sends it to a live
    server, where a cache miss makes the robot upload its map again."""
    servers = "\n".join(f"    server cloud{k} {LOOPBACK}:{port} check" for k, port in enumerate(server_ports))
    stats = (f"\nlisten stats\n    mode http\n    bind {LOOPBACK}:{stats_port}\n    stats enable\n"
             f"    stats uri /\n" if stats_port else "")
    return f"""global
    # Headroom over the frontend's limit (each connection needs two file descriptors: 9000 fits a 20000
    # descriptor limit); the per-source limit keeps one host from using up the slots new robots need.
    maxconn 9000

defaults
    mode tcp
    timeout connect 1s
    # ZeroMQ connections are long-lived and may idle between plans (the bridge pings every second).
    timeout client 1h
    timeout server 1h
    retries 2
    option redispatch

frontend robots
    bind {LOOPBACK}:{frontend_port}
    maxconn 8000
    # At most 64 connections from one address (a robot uses a few): one host cannot fill the table.
    stick-table type ip size 100k expire 60s store conn_cur
    tcp-request connection track-sc0 src
    tcp-request connection reject if {{ sc0_conn_cur gt 64 }}
    # A ZeroMQ peer sends its greeting (0xFF, 8 bytes, 0x7F) at once: a connection that sends nothing for
    # 10 s is closed instead of holding a slot for the hour of the client timeout.
    tcp-request inspect-delay 10s
    tcp-request content accept if {{ req.len ge 10 }} {{ req.payload(0,1) -m bin ff }}
    tcp-request content reject
    default_backend planners

backend planners
    balance leastconn
    # Beyond a TCP connect (a stopped server's kernel still accepts): send a ZMTP greeting signature and
    # expect the server's, which only a running libzmq I/O thread sends.
    option tcp-check
    tcp-check connect
    tcp-check send-binary ff00000000000000017f
    tcp-check expect binary ff
    default-server inter 250ms fall 2 rise 2 on-marked-down shutdown-sessions
{servers}
{stats}"""


@dataclass
class RobotLog:
    latencies_s: List[float] = field(default_factory=list)
    statuses: List[int] = field(default_factory=list)
    lost: int = 0
    wrong: int = 0
    uploads: int = 0


@dataclass
class FleetResult:
    robots: int
    servers: int
    requests: int
    answered: int
    planned: int
    busy: int
    errors: int
    lost: int
    wrong: int
    uploads: int
    seconds: float
    latencies_s: np.ndarray
    server_stats: List[Tuple[int, dict]] = field(default_factory=list)   # (port, STATS) of live servers

    @property
    def plans_per_s(self) -> float:
        return self.answered / self.seconds if self.seconds > 0 else 0.0

    def lines(self) -> List[str]:
        p50, p99 = (np.percentile(self.latencies_s, [50, 99]) * 1e3) if len(self.latencies_s) else (np.nan, np.nan)
        return [f"robots {self.robots}, servers {self.servers}: {self.requests} requests in {self.seconds:.1f} s",
                f"answered {self.answered} ({self.plans_per_s:.0f}/s), planned {self.planned}, BUSY {self.busy}, "
                f"errors {self.errors}, wrong answers {self.wrong}, lost {self.lost}",
                f"latency p50 {p50:.2f} ms, p99 {p99:.2f} ms; map uploads {self.uploads}"] + \
            [line for port, stats in self.server_stats for line in server_stats_lines(port, stats)]


def server_stats_lines(port: int, stats: dict) -> List[str]:
    """A server's STATS as the server logs them, plus its busiest clients."""
    clients = sorted(stats["clients"].items(), key=lambda item: -item[1]["requests"])
    busiest = ", ".join(f"{name} {counts['requests']}" for name, counts in clients[:5])
    limited = sum(counts["rate_limited"] for _, counts in clients)
    return [f"server {LOOPBACK}:{port} {CloudServer.stats_line(stats)}",
            f"  requests by client (busiest 5 of {len(clients)}): {busiest or 'none'}; rate limited {limited}"]


def robot_map(seed: int, size: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    grid = np.where(rng.random((size, size)) < 0.2, 100, 0).astype(np.int8)
    return grid


def run_robot(index: int, endpoint: str, keys_dir: Path, map_size: int, requests: int, deadline: float,
              timeout_s: float, retries: int, think_s: float, context: zmq.Context, log: RobotLog) -> None:
    grid = robot_map(1000 + index, map_size)
    rng = np.random.default_rng(index)
    free = np.argwhere(grid == 0)[:, ::-1]
    client = CloudClient(endpoint, keys_dir=str(keys_dir / f"robot{index:02d}"), timeout_s=timeout_s,
                         retries=retries, context=context)
    try:
        for _ in range(requests):
            if time.monotonic() >= deadline:
                break
            time.sleep(rng.uniform(0, 2 * think_s))   # robots ask now and then, not in lockstep
            start, goal = (tuple(int(v) for v in free[rng.integers(len(free))]) for _ in range(2))
            began = time.perf_counter()
            try:
                outcome = client.plan(grid, start, goal)
            except CloudTimeout:
                log.lost += 1
                continue
            log.latencies_s.append(time.perf_counter() - began)
            log.statuses.append(int(outcome.reply.status))
            log.uploads += outcome.uploaded
            if is_planner_status(outcome.reply.status):
                expected = plan_raw(grid, start, goal)
                if int(expected["status"]) != int(outcome.reply.status) or (
                        expected["status"] == PlanStatus.OK and abs(expected["cost"] - outcome.reply.cost_cells) > 1e-9):
                    log.wrong += 1
    finally:
        client.close()


class Cloud:
    """Server processes (and HAProxy in front when asked) on loopback ports, stopped on exit."""

    def __init__(self, servers: int, workers: int, keys_dir: Path, use_haproxy: bool, work_dir: Path):
        self.processes: List[subprocess.Popen] = []
        self.server_ports = [free_port() for _ in range(servers)]
        for port in self.server_ports:
            self.processes.append(subprocess.Popen(
                [sys.executable, "-m", "offload_cloud", "--bind", f"tcp://{LOOPBACK}:{port}",
                 "--workers", str(workers), "--keys-dir", str(keys_dir), "--log-level", "ERROR",
                 "--stats-admin", "robot00"],   # the fleet report reads every robot through robot00
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        for port in self.server_ports:
            if not wait_for_port(port, 20.0):
                self.close()
                raise RuntimeError(f"cloud server on port {port} did not start")
        self.haproxy = None
        if use_haproxy:
            binary = shutil.which("haproxy") or "/usr/sbin/haproxy"
            if not os.path.exists(binary):
                self.close()
                raise RuntimeError("haproxy is not installed (apt-get install haproxy)")
            port = free_port()
            config = work_dir / "haproxy.cfg"
            config.write_text(haproxy_config(port, self.server_ports))
            self.haproxy = subprocess.Popen([binary, "-f", str(config), "-db"], stdout=subprocess.DEVNULL,
                                            stderr=subprocess.PIPE, text=True)
            if not wait_for_port(port, 10.0):
                self.close()
                raise RuntimeError("haproxy did not start")
            self.endpoint = f"tcp://{LOOPBACK}:{port}"
        else:
            self.endpoint = f"tcp://{LOOPBACK}:{self.server_ports[0]}"

    def live_stats(self, keys_dir: Path, context: zmq.Context) -> List[Tuple[int, dict]]:
        """STATS of every server process still running, asked directly with one robot's key."""
        found = []
        for port, process in zip(self.server_ports, self.processes):
            if process.poll() is not None:
                continue
            client = CloudClient(f"tcp://{LOOPBACK}:{port}", keys_dir=str(keys_dir), timeout_s=5.0, retries=0,
                                 context=context)
            try:
                found.append((port, client.stats()))
            except (CloudTimeout, ProtocolError) as error:
                print(f"no stats from server {LOOPBACK}:{port}: {error}", file=sys.stderr)
            finally:
                client.close()
        return found

    def kill(self, index: int) -> None:
        self.processes[index].send_signal(signal.SIGKILL)
        self.processes[index].wait()

    def close(self) -> None:
        for process in self.processes + ([self.haproxy] if self.haproxy else []):
            if process.poll() is None:
                process.terminate()
        for process in self.processes + ([self.haproxy] if self.haproxy else []):
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()


def run_fleet(robots: int = 50, servers: int = 3, workers: int = 1, use_haproxy: bool = True,
              requests: int = 40, duration_s: float = 120.0, kill_at_s: Optional[float] = None,
              map_size: int = 128, timeout_s: float = 10.0, retries: int = 4, think_s: float = 0.05) -> FleetResult:
    if robots < 1 or robots > 99 or servers < 1 or requests < 1 or duration_s <= 0:
        raise ValueError("robots must be in 1..99, servers and requests >= 1, duration_s > 0")
    if servers > 1 and not use_haproxy:
        raise ValueError("several servers need HAProxy in front")
    with tempfile.TemporaryDirectory(prefix="offload-fleet-") as tmp:
        work = Path(tmp)
        server_keys = keys.generate(work / "keys", [f"robot{k:02d}" for k in range(robots)])
        cloud = Cloud(servers, workers, server_keys, use_haproxy, work)
        context = zmq.Context()
        logs = [RobotLog() for _ in range(robots)]
        try:
            began = time.monotonic()
            deadline = began + duration_s
            threads = [threading.Thread(target=run_robot, name=f"robot{k:02d}",
                                        args=(k, cloud.endpoint, work / "keys", map_size, requests, deadline,
                                              timeout_s, retries, think_s, context, logs[k]))
                       for k in range(robots)]
            for thread in threads:
                thread.start()
            if kill_at_s is not None:
                while time.monotonic() < began + kill_at_s and any(t.is_alive() for t in threads):
                    time.sleep(0.05)
                cloud.kill(0)
            for thread in threads:
                thread.join(duration_s + timeout_s + 30)
            seconds = time.monotonic() - began
            server_stats = cloud.live_stats(work / "keys" / "robot00", context)
        finally:
            cloud.close()
            context.term()
    statuses = np.array([s for log in logs for s in log.statuses], dtype=np.int64)
    planner = np.array([is_planner_status(s) for s in statuses], dtype=bool)
    return FleetResult(robots=robots, servers=servers, requests=sum(len(l.statuses) + l.lost for l in logs),
                       answered=len(statuses), planned=int(planner.sum()),
                       busy=int((statuses == Status.BUSY).sum()),
                       errors=int((~planner & (statuses != Status.BUSY)).sum()),
                       lost=sum(l.lost for l in logs), wrong=sum(l.wrong for l in logs),
                       uploads=sum(l.uploads for l in logs), seconds=seconds,
                       latencies_s=np.array([x for log in logs for x in log.latencies_s]),
                       server_stats=server_stats)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=50)
    parser.add_argument("--servers", type=int, default=3)
    parser.add_argument("--workers", type=int, default=1, help="planner threads per server")
    parser.add_argument("--no-haproxy", action="store_true", help="one server, robots connect directly")
    parser.add_argument("--requests", type=int, default=40, help="plans per robot")
    parser.add_argument("--duration-s", type=float, default=120.0, help="stop asking after this long")
    parser.add_argument("--kill-at-s", type=float, default=None, help="SIGKILL the first server at this time")
    parser.add_argument("--map-size", type=int, default=128, help="cells a side of each robot's map")
    parser.add_argument("--timeout-s", type=float, default=10.0, help="a robot's deadline per plan")
    parser.add_argument("--think-s", type=float, default=0.05, help="mean pause of a robot between plans")
    parser.add_argument("--baseline", action="store_true",
                        help="first run the same robots against one server directly, no HAProxy and no kill, "
                             "and print the run's figures against it")
    args = parser.parse_args(argv)
    try:
        baseline = None
        if args.baseline:
            baseline = run_fleet(args.robots, 1, args.workers, False, args.requests, args.duration_s, None,
                                 args.map_size, args.timeout_s, think_s=args.think_s)
            print("baseline, one server, robots connected directly:\n  " + "\n  ".join(baseline.lines()))
        result = run_fleet(args.robots, args.servers, args.workers, not args.no_haproxy, args.requests,
                           args.duration_s, args.kill_at_s, args.map_size, args.timeout_s, think_s=args.think_s)
    except (ValueError, RuntimeError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print("\n".join(result.lines()))
    if baseline is not None and len(baseline.latencies_s) and len(result.latencies_s):
        ratio = [np.percentile(result.latencies_s, q) / np.percentile(baseline.latencies_s, q) for q in (50, 99)]
        print(f"against the baseline: throughput x{result.plans_per_s / baseline.plans_per_s:.2f}, "
              f"p50 x{ratio[0]:.2f}, p99 x{ratio[1]:.2f} (same robots, maps and goals)")
    return 1 if result.lost or result.wrong or (baseline is not None and (baseline.lost or baseline.wrong)) else 0


if __name__ == "__main__":
    sys.exit(main())
