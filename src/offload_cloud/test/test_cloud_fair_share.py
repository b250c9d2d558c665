"""Server observability and fair share: STATS counts a known sequence of requests
from two robots, per robot by key name; the health check prints them; a greedy robot is rate limited and
held to its share of the queue while a polite robot's plans are all planned; a robot uploading many maps
evicts its own, never another robot's map. Servers on random loopback ports; no timed assertions."""
import json
import logging
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zmq

import offload_planner_cpp
from offload_cloud import protocol
from offload_cloud.client import CloudClient
from offload_cloud.map_cache import ENTRY_OVERHEAD_BYTES, MapCache
from offload_cloud.protocol import Kind, PlanOptions, ProtocolError, Reply, Status
from offload_cloud.server_cli import parse_args

from cloud_test_helpers import curve_dealer, make_keys, random_map, start_server

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def key_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("keys")
    make_keys(root, ["robot1", "robot2"])
    return root


# -- protocol --------------------------------------------------------------------------------------------

def test_stats_request_and_reply_round_trip():
    frames = protocol.encode_stats(42)
    assert protocol.decode_envelope(frames[0]) == (Kind.STATS, 42) and len(frames) == 1
    stats = {"requests": 3, "clients": {"robot1": {"requests": 3}}}
    reply = protocol.decode_reply(protocol.encode_stats_reply(42, stats))
    assert reply.request_id == 42 and reply.status == Status.OK
    assert protocol.decode_stats(reply) == stats
    for bad in (Reply(1, Status.OK, "[1, 2]"), Reply(1, Status.OK, "not json"), Reply(1, Status.OK, "[" * 5000),
                Reply(1, Status.BAD_REQUEST, "unknown message kind 5")):
        with pytest.raises(ProtocolError):
            protocol.decode_stats(bad)


def test_absurd_fair_share_flags_are_refused():
    for flags in (["--rate-per-client", "-1"], ["--rate-per-client", "nan"], ["--burst-per-client", "0"],
                  ["--stats-log-s", "-5"], ["--stats-log-s", "inf"]):
        with pytest.raises(SystemExit) as exit_info:
            parse_args(["--insecure", *flags])
        assert exit_info.value.code == 2
    args = parse_args(["--insecure"])
    assert (args.rate_per_client, args.burst_per_client, args.stats_log_s) == (50.0, 100, 60.0)


# -- STATS -----------------------------------------------------------------------------------------------

def test_stats_show_a_key_its_own_figures_and_are_rate_limited(key_root):
    """Any key could read every robot's name, counts and maps, and ask 3,000 times a second: a key sees
    only itself unless it is a --stats-admin, and STATS draw on the client's token bucket."""
    server = start_server(key_root / "server", workers=1, rate_per_client=5.0, burst_per_client=3,
                          stats_admins=("robot2",))
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot1")) as robot1, \
                CloudClient(server.endpoint, keys_dir=str(key_root / "robot2")) as robot2:
            robot2.ping()
            robot1.ping()
            own = robot1.stats()
            assert set(own["clients"]) == {"robot1"} and own["requests"] == 0
            statuses = [robot1.request(protocol.encode_stats).status for _ in range(10)]
            assert statuses.count(Status.BUSY) >= 5 and Status.OK in statuses
            everyone = robot2.stats()                   # the admin key sees every robot
        assert set(everyone["clients"]) == {"robot1", "robot2"}
        assert everyone["clients"]["robot1"]["rate_limited"] == statuses.count(Status.BUSY)
    finally:
        server.stop()


def test_stats_count_a_known_sequence_from_two_robots(key_root, caplog):
    caplog.set_level(logging.INFO, logger="offload_cloud.server")
    server = start_server(key_root / "server", workers=1, stats_log_s=0.05, stats_admins=("robot2",))
    grid_a, grid_b = random_map(40, 30, 0.1, seed=1), random_map(20, 20, 0.1, seed=2)
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot1")) as robot1, \
                CloudClient(server.endpoint, keys_dir=str(key_root / "robot2")) as robot2:
            assert robot1.plan(grid_a, (0, 0), (39, 29)).reply.status == Status.OK        # uploads map A
            assert robot1.plan(grid_a, (0, 0), (10, 10)).reply.status == Status.OK        # cache hit
            assert robot1.upload(grid_b).status == Status.OK                              # uploads map B
            unknown = protocol.grid_hash(random_map(10, 10, 0.1, seed=3))
            reply = robot2.request(lambda rid: protocol.encode_plan(rid, unknown, (0, 0), (9, 9)))
            assert reply.status == Status.MAP_UNKNOWN                                     # cache miss
            reply = robot2.request(lambda rid: [protocol.envelope(Kind.REPLY, rid)])
            assert reply.status == Status.BAD_REQUEST                                     # not a request
            robot2.ping()
            robot2.ping()
            stats = robot2.stats()
        # robot1's new socket pinged ahead of its first message, a map (protocol.FIRST_MESSAGE_MAX_BYTES)
        assert stats["requests"] == 4 and stats["pings"] == 3 and stats["stats"] == 1
        assert stats["replies"] == {"OK": 3, "MAP_UNKNOWN": 1, "BAD_REQUEST": 1}
        cache = stats["cache"]
        assert (cache["hits"], cache["misses"], cache["uploads"], cache["maps"], cache["evictions"]) == (1, 1, 2, 2, 0)
        assert cache["bytes"] == grid_a.nbytes + grid_b.nbytes + 2 * ENTRY_OVERHEAD_BYTES
        assert stats["queue"]["depth"] == 0 and stats["queue"]["in_flight"] == 0
        assert stats["uptime_s"] > 0 and stats["workers"] == 1
        clients = stats["clients"]
        assert set(clients) == {"robot1", "robot2"}
        assert clients["robot1"]["requests"] == 3 and clients["robot1"]["replies"] == {"OK": 3}
        assert clients["robot1"]["cache_bytes"] == cache["bytes"]   # both maps are robot1's uploads
        assert clients["robot2"]["requests"] == 1
        assert clients["robot2"]["replies"] == {"MAP_UNKNOWN": 1, "BAD_REQUEST": 1}
        assert clients["robot2"]["cache_bytes"] == 0
        assert [clients["robot1"][k] for k in ("cache_hits", "cache_misses", "uploads")] == [1, 0, 2]
        assert [clients["robot2"][k] for k in ("cache_hits", "cache_misses", "uploads")] == [0, 1, 0]
        assert all(c["rate_limited"] == 0 and c["fair_share_refused"] == 0 for c in clients.values())

        # The health check prints the same counters (plus its own STATS request).
        command = [sys.executable, "-m", "offload_cloud.client", server.endpoint, "--stats",
                   "--keys-dir", str(key_root / "robot1")]
        done = subprocess.run(command, capture_output=True, text=True, timeout=30)
        assert done.returncode == 0, done.stderr
        printed = json.loads(done.stdout)
        assert printed["stats"] == 2 and printed["replies"] == stats["replies"]
        assert printed["clients"]["robot1"]["replies"] == {"OK": 3}
        assert set(printed["clients"]) == {"robot1"}   # not an admin: its own figures, no other robot's

        # The periodic log line (every 0.05 s here) carries the counters.
        def stats_lines():
            return [r.getMessage() for r in caplog.records if r.getMessage().startswith("stats: up")]
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not any("4 requests" in line for line in stats_lines()):
            time.sleep(0.05)
        line = next(line for line in stats_lines() if "4 requests" in line)
        assert "cache hits 1, misses 1, uploads 2" in line and "BAD_REQUEST 1, MAP_UNKNOWN 1, OK 3" in line
    finally:
        server.stop()


def test_stats_is_answered_while_the_only_worker_plans(key_root):
    """STATS is the broker's, as PING: sent right behind a long plan on the same connection, its answer
    comes first and sees that plan in flight."""
    server = start_server(key_root / "server", workers=1, stats_admins=("robot2",))
    grid = random_map(1400, 1400, 0.1, seed=4)
    context = zmq.Context()
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot1"), timeout_s=30) as robot1:
            assert robot1.upload(grid).status == Status.OK
        socket = curve_dealer(context, key_root / "robot1", server.endpoint)
        socket.send_multipart(protocol.encode_plan(1, protocol.grid_hash(grid), (0, 0), (1399, 1399),
                                                   PlanOptions(stop_at_goal=False)))
        socket.send_multipart(protocol.encode_stats(2))
        replies = []
        while len(replies) < 2:
            assert socket.poll(30000), "no reply"
            replies.append(protocol.decode_reply(socket.recv_multipart()))
        socket.close(0)
        assert [reply.request_id for reply in replies] == [2, 1]
        stats = protocol.decode_stats(replies[0])
        assert stats["queue"]["in_flight"] == 1 and stats["clients"]["robot1"]["requests"] == 2
        assert replies[1].status == Status.OK
    finally:
        context.term()
        server.stop()


# -- fair share ------------------------------------------------------------------------------------------

class Flooder(threading.Thread):
    """A greedy robot: keeps `window` plans outstanding on one connection until stopped; counts replies."""

    def __init__(self, context, key_dir, endpoint, grid, window=40):
        super().__init__(daemon=True)
        self.socket = curve_dealer(context, key_dir, endpoint)
        self.digest = protocol.grid_hash(grid)
        self.height, self.width = grid.shape
        self.window = window
        self.stop = threading.Event()
        self.sent = 0
        self.replies = []

    def run(self):
        rng = np.random.default_rng(7)
        try:
            while True:
                while not self.stop.is_set() and self.sent - len(self.replies) < self.window:
                    goal = (int(rng.integers(self.width)), int(rng.integers(self.height)))
                    self.socket.send_multipart(protocol.encode_plan(self.sent, self.digest, (0, 0), goal))
                    self.sent += 1
                if self.stop.is_set() and len(self.replies) == self.sent:
                    return
                if self.socket.poll(20000):
                    self.replies.append(protocol.decode_reply(self.socket.recv_multipart()))
                elif self.stop.is_set():
                    return   # an unanswered request: the test's count check reports it
        finally:
            self.socket.close(0)


def polite_plans(endpoint, key_dir, grid, count):
    """`count` plans one after another; each reply with the locally planned answer."""
    rng = np.random.default_rng(11)
    free = np.argwhere(grid == 0)[:, ::-1]
    outcomes = []
    with CloudClient(endpoint, keys_dir=str(key_dir), timeout_s=30, retries=0) as robot:
        for _ in range(count):
            start, goal = (tuple(int(v) for v in free[rng.integers(len(free))]) for _ in range(2))
            outcomes.append((robot.plan(grid, start, goal).reply, offload_planner_cpp.plan_raw(grid, start, goal)))
    return outcomes


def flood_beside_polite_robot(key_root, polite_count=8, **server_config):
    server = start_server(key_root / "server", workers=1, max_wait_s=60, stats_admins=("robot2",), **server_config)
    greedy_grid, polite_grid = random_map(400, 400, 0.1, seed=5), random_map(300, 300, 0.1, seed=6)
    context = zmq.Context()
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot1")) as uploader:
            assert uploader.upload(greedy_grid).status == Status.OK
        greedy = Flooder(context, key_root / "robot1", server.endpoint, greedy_grid)
        greedy.start()
        while len(greedy.replies) < 50:   # the flood is on before the polite robot asks
            time.sleep(0.01)
        polite = polite_plans(server.endpoint, key_root / "robot2", polite_grid, polite_count)
        greedy.stop.set()
        greedy.join(60)
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot2")) as robot2:
            stats = robot2.stats()
    finally:
        context.term()
        server.stop()
    assert len(greedy.replies) == greedy.sent and len({r.request_id for r in greedy.replies}) == greedy.sent
    return greedy, polite, stats


def assert_all_planned(polite):
    for reply, expected in polite:
        assert reply.status == int(expected["status"]), reply.message
        assert abs(reply.cost_cells - expected["cost"]) < 1e-9


def test_greedy_robot_is_rate_limited_while_polite_robot_is_all_planned(key_root):
    greedy, polite, stats = flood_beside_polite_robot(key_root, rate_per_client=20.0, burst_per_client=10)
    assert_all_planned(polite)
    limited = [r for r in greedy.replies if r.status == Status.BUSY and r.message.startswith("rate limit")]
    assert limited, {r.message for r in greedy.replies}
    assert "client robot1" in limited[0].message and "--rate-per-client 20 plans/s" in limited[0].message
    assert any(protocol.is_planner_status(r.status) for r in greedy.replies)   # limited, not shut out
    assert stats["clients"]["robot1"]["rate_limited"] == len(limited)
    assert stats["clients"]["robot2"]["rate_limited"] == 0
    polite_replies = stats["clients"]["robot2"]["replies"]
    assert sum(polite_replies.values()) == len(polite) and "BUSY" not in polite_replies


def test_greedy_robot_is_held_to_its_share_of_the_queue(key_root):
    """No rate limit: the flood fills what the queue lets it, yet the polite robot always finds a place."""
    greedy, polite, stats = flood_beside_polite_robot(key_root, rate_per_client=0.0, max_queued=8)
    assert_all_planned(polite)
    refused = [r for r in greedy.replies if r.status == Status.BUSY and r.message.startswith("fair share")]
    assert refused and "client robot1" in refused[0].message
    assert stats["clients"]["robot1"]["fair_share_refused"] == len(refused)
    assert stats["clients"]["robot2"]["replies"].get("BUSY", 0) == 0


def test_robot_uploading_many_maps_cannot_evict_another_robots_map(key_root):
    maps = [random_map(100, 100, 0.1, seed=20 + k) for k in range(12)]
    charge = maps[0].nbytes + ENTRY_OVERHEAD_BYTES
    server = start_server(key_root / "server", workers=1, cache_bytes=4 * charge, stats_admins=("robot2",))   # room for four maps
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot1")) as robot1, \
                CloudClient(server.endpoint, keys_dir=str(key_root / "robot2")) as robot2:
            assert robot2.plan(maps[0], (0, 0), (99, 99)).reply.status == Status.OK
            for grid in maps[1:]:
                assert robot1.upload(grid).status == Status.OK
            kept = protocol.grid_hash(maps[0])
            reply = robot2.request(lambda rid: protocol.encode_plan(rid, kept, (0, 0), (99, 99)))
            assert reply.status == Status.OK, reply.message     # robot2's map survived, hash only
            newest = protocol.grid_hash(maps[-1])
            assert robot1.request(lambda rid: protocol.encode_plan(rid, newest, (0, 0), (99, 99))).status == Status.OK
            stats = robot2.stats()
        assert stats["cache"]["evictions"] == len(maps) - 4
        assert stats["clients"]["robot2"]["cache_bytes"] == charge
        assert stats["clients"]["robot1"]["cache_bytes"] == 3 * charge
    finally:
        server.stop()


def test_map_cache_evicts_the_heaviest_owners_least_recently_used_map():
    grids = {name: np.full((10, 10), k, np.int8) for k, name in enumerate("abcdef")}
    charge = MapCache.charge(grids["a"])
    cache = MapCache(3 * charge)
    assert cache.put(b"a", grids["a"], "robot2")
    for name in "bcdef":
        assert cache.put(name.encode(), grids[name], "robot1")
    assert b"a" in cache and b"e" in cache and b"f" in cache and b"b" not in cache
    assert cache.bytes_by_owner() == {"robot2": charge, "robot1": 2 * charge}
    assert cache.get(b"e") is not None          # e is now robot1's most recent: f goes first
    assert cache.put(b"g", grids["a"] + 1, "robot3")
    assert b"f" not in cache and b"e" in cache and b"a" in cache
    assert cache.bytes_by_owner() == {"robot1": charge, "robot2": charge, "robot3": charge}
    assert cache.evictions == 4 and cache.inserted == 7 and cache.size_bytes == 3 * charge
