"""The cloud server and client under hostile input: memory bounded by the cache cap and the connection
guard, replies bounded and checked by the client, absurd flags refused before any work, warnings rate
limited. Each test reproduces an attack at a scale that runs in seconds; OFFLOAD_ATTACK_SCALE=full runs the
larger versions (200,000 uploads)."""
import collections
import logging
import pathlib
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zmq

import offload_planner_cpp
from offload_cloud import protocol
from offload_cloud.client import CloudClient, CloudTimeout
from offload_cloud.protocol import Kind, PlanOptions, Reply, Status
from offload_cloud.server_cli import parse_args

from cloud_test_helpers import (FULL, MIB, LOOPBACK, PeakRss, curve_dealer, free_port, rss_bytes, spawn_server,
                                start_server, stop_process)

pytestmark = pytest.mark.timeout(180)


def test_many_tiny_maps_keep_server_rss_within_twice_the_cache_cap(key_root):
    uploads = 200_000 if FULL else 6000
    port = free_port()
    # No rate limit: every upload must reach the cache (the flood would otherwise get BUSY, as it should:
    # test_cloud_fair_share.py).
    process = spawn_server(port, key_root / "server", extra_args=["--cache-mib", "1", "--rate-per-client", "0"])
    context = zmq.Context()
    socket = curve_dealer(context, key_root / "robot", f"{LOOPBACK}:{port}")

    def upload(first, last, window=32):
        sent = answered = 0
        while answered < last - first:
            while first + sent < last and sent - answered < window:
                grid = np.frombuffer((first + sent).to_bytes(8, "little"), np.int8).reshape(1, 8)
                socket.send_multipart(protocol.encode_upload(first + sent, grid))
                sent += 1
            assert socket.poll(20000), "server stopped answering"
            assert protocol.decode_reply(socket.recv_multipart()).status == Status.OK
            answered += 1

    try:
        upload(0, 300)     # code paths warm, a few maps cached
        idle = rss_bytes(process.pid)
        upload(300, uploads)
        grown = rss_bytes(process.pid) - idle
    finally:
        socket.close(0)
        context.term()
        stop_process(process)
    print(f"{uploads} distinct 1 x 8 maps, --cache-mib 1: RSS {idle / MIB:.1f} MiB -> +{grown / MIB:.2f} MiB")
    assert grown <= 2 * MIB   # the bar: within twice the cap above the idle size (landed code: +27 MiB)


def test_message_of_many_frames_is_cut_at_the_connection_bound(key_root, tmp_path):
    frames, frame_bytes = (1200, MIB) if FULL else (200, MIB - 4096)   # frames up to the frame bound (1 MiB)
    max_message_mib = 64 if FULL else 1
    port = free_port()
    process = spawn_server(port, key_root / "server", log_path=tmp_path / "server.log",
                           extra_args=["--max-message-mib", str(max_message_mib),
                                       "--max-queued-mib", str(2 * max_message_mib if not FULL else 256)])
    endpoint = f"{LOOPBACK}:{port}"
    context = zmq.Context()
    rss = PeakRss(process.pid)
    try:
        with CloudClient(endpoint, keys_dir=str(key_root / "robot"), timeout_s=5.0) as client:
            client.ping()
            rss.start()
            attacker = curve_dealer(context, key_root / "robot2", endpoint)
            attacker.send_multipart(protocol.encode_ping(0))   # says whose it is: the per-connection bound holds it
            assert attacker.poll(5000) and attacker.recv_multipart()
            big = bytes(frame_bytes)   # each frame within the frame bound, together far over the max message
            attacker.send_multipart([protocol.envelope(Kind.UPLOAD, 1)] + [big] * frames, copy=False)
            answered = attacker.poll(30000 if FULL else 4000)
            grown = rss.stop()
            attacker.close(0)
            assert client.ping() > 0     # the server lives and serves
    finally:
        rss.stop()
        context.term()
        stop_process(process)
    log = (tmp_path / "server.log").read_text()
    print(f"{frames} frames x {frame_bytes} B: RSS {rss.idle / MIB:.1f} MiB, peak +{grown / MIB:.1f} MiB")
    assert not answered and "cut the connection" in log
    # The per-connection bound is (receive HWM + 1) x max message + 1 MiB: 4 MiB here (landed code: +143 MiB).
    # The guard samples every 25 ms: what arrives in between is beyond it. With the system's libsodium CURVE takes
    # in about 1 GB/s here (the cut came at 17-18 MB held), so the allowance is 32 MiB, far under the 200 MiB sent.
    assert grown <= (32 if not FULL else 400) * MIB


def test_a_first_message_over_the_first_message_bound_is_cut_and_the_client_pings_ahead_of_one(key_root, tmp_path):
    port = free_port()
    process = spawn_server(port, key_root / "server", log_path=tmp_path / "server.log")
    endpoint = f"{LOOPBACK}:{port}"
    context = zmq.Context()
    rss = PeakRss(process.pid)
    try:
        with CloudClient(endpoint, keys_dir=str(key_root / "robot"), timeout_s=5.0) as client:
            client.ping()
            rss.start()
            # A connection that has not said whose it is sends 256 MiB as its first message (256 frames, each
            # within the frame bound): under the per-connection bound (321 MiB), far over a first message.
            attacker = curve_dealer(context, key_root / "robot2", endpoint)
            attacker.send_multipart([protocol.envelope(Kind.UPLOAD, 1)] + [bytes(MIB)] * 256, copy=False)
            answered = attacker.poll(4000)
            grown = rss.stop()
            attacker.close(0)
        # The package's client on a fresh connection, a 48 MiB map first: it pings ahead, so it is served.
        grid = np.zeros((7000, 7000), np.int8)
        with CloudClient(endpoint, keys_dir=str(key_root / "robot2"), timeout_s=20.0, retries=0) as uploader:
            reply = uploader.upload(grid)
    finally:
        rss.stop()
        context.term()
        stop_process(process)
    log = (tmp_path / "server.log").read_text()
    print(f"256 MiB first message: RSS {rss.idle / MIB:.1f} MiB, peak +{grown / MIB:.1f} MiB")
    assert not answered and "before its first message" in log
    # 1 MiB + 1 MiB of slack, plus what arrives within one 25 ms check (about 1 GB/s here) and the frames
    # libzmq allocated: without the rule it holds the whole 256 MiB.
    assert grown <= 96 * MIB
    assert reply.status == Status.OK


def test_a_key_over_its_connections_loses_its_idlest_and_other_keys_are_served(key_root, tmp_path):
    port = free_port()
    process = spawn_server(port, key_root / "server", log_path=tmp_path / "server.log",
                           extra_args=["--max-connections-per-key", "2"])
    endpoint = f"{LOOPBACK}:{port}"
    robots = [CloudClient(endpoint, keys_dir=str(key_root / "robot"), timeout_s=5.0, retries=0) for _ in range(3)]
    try:
        robots[0].ping()
        robots[1].ping()           # both then idle, as connections whose peers vanished without a word would be
        assert robots[2].ping() > 0                # the newest goes on: the key is never locked out
        with CloudClient(endpoint, keys_dir=str(key_root / "robot2"), timeout_s=5.0) as other:
            assert other.ping() > 0                # another key is served
    finally:
        for robot in robots:
            robot.close()
        stop_process(process)
    assert "its least recently active one goes" in (tmp_path / "server.log").read_text()


_FLOODER = """
import sys, zmq
from offload_cloud import protocol
sys.path.insert(0, sys.argv[3])
from cloud_test_helpers import curve_dealer
context = zmq.Context()
dealers = [curve_dealer(context, sys.argv[2], sys.argv[1]) for _ in range(2)]
print("flooding", flush=True)
while True:
    for dealer in dealers:
        for k in range(64):
            dealer.send_multipart(protocol.encode_ping(k))
    for dealer in dealers:
        for k in range(64):
            dealer.recv_multipart()
"""


def test_a_first_message_over_the_bound_is_cut_while_another_key_floods_the_broker(key_root, tmp_path):
    """With pings always waiting for the broker, the first-message rule is still judged, once every connection
    had its turn."""
    port = free_port()
    process = spawn_server(port, key_root / "server", log_path=tmp_path / "server.log",
                           extra_args=["--rate-per-client", "0"])
    endpoint = f"{LOOPBACK}:{port}"
    flooder = subprocess.Popen([sys.executable, "-c", _FLOODER, endpoint, str(key_root / "robot"),
                                str(pathlib.Path(__file__).parent)], stdout=subprocess.PIPE, text=True)
    context = zmq.Context()
    rss = PeakRss(process.pid)
    try:
        assert flooder.stdout.readline().strip() == "flooding"
        time.sleep(1.0)
        rss.start()
        attacker = curve_dealer(context, key_root / "robot2", endpoint)
        attacker.send_multipart([protocol.envelope(Kind.UPLOAD, 1)] + [bytes(MIB)] * 256, copy=False)
        attacker.poll(4000)
        grown = rss.stop()
        attacker.close(0)
        assert flooder.poll() is None, "the flooder stopped: nothing kept the broker busy"
    finally:
        rss.stop()
        flooder.kill()
        flooder.wait()
        context.term()
        stop_process(process)
    print(f"256 MiB first message under a ping flood: peak +{grown / MIB:.1f} MiB")
    assert "before its first message" in (tmp_path / "server.log").read_text()
    assert grown <= 96 * MIB      # without the turns counted, the flood kept the rule from being judged: +256 MiB


class CappingProxy:
    """TCP proxy to `port` that forwards at most `cap_bytes` of each connection upstream, then holds it open:
    a first message that stalls part way."""

    def __init__(self, port: int, cap_bytes: int):
        self.upstream, self.cap_bytes = ("127.0.0.1", port), cap_bytes
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.sockets = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.upstream)
            self.sockets += [client, server]
            for source, sink, cap in ((client, server, self.cap_bytes), (server, client, None)):
                threading.Thread(target=self._pump, args=(source, sink, cap), daemon=True).start()

    def _pump(self, source, sink, cap):
        sent = 0
        try:
            while True:
                data = source.recv(1 << 16)
                while cap is not None and sent >= cap:
                    time.sleep(0.05)
                if not data:
                    return
                if cap is not None:
                    data = data[:cap - sent]
                sink.sendall(data)
                sent += len(data)
        except OSError:
            return

    def close(self):
        self.listener.close()
        for sock in self.sockets:
            sock.close()


def test_connections_yet_to_say_whose_they_are_are_bounded_together(key_root):
    """Many connections each stalled within its first-message bound (1.5 MiB of a larger first message, under
    the 2 MiB each may have read) hold no more than the unidentified budget together, and a robot of another key
    uploads a large map meanwhile."""
    server = start_server(key_root / "server", max_pending_unidentified_bytes=8 * MIB)
    proxy = CappingProxy(int(server.endpoint.rsplit(":", 1)[1]), cap_bytes=3 * MIB // 2)
    context = zmq.Context()
    stalled = [curve_dealer(context, key_root / "robot2", f"{LOOPBACK}:{proxy.port}") for _ in range(10)]
    try:
        for dealer in stalled:
            dealer.send_multipart([protocol.envelope(Kind.UPLOAD, 1)] + [bytes(MIB)] * 4, copy=False)
        deadline = time.monotonic() + 10.0
        while len(server.guard.connections) < 6 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(1.0)
        unidentified = [c for c in server.guard.connections.values() if not c.identified]
        assert 1 <= len(unidentified) <= 5        # 8 MiB / 1.5 MiB: the oldest were cut (10 otherwise)
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot"), timeout_s=20.0, retries=0) as robot:
            assert robot.upload(np.zeros((3000, 3000), np.int8)).status == Status.OK
    finally:
        for dealer in stalled:
            dealer.close(0)
        context.term()
        proxy.close()
        server.stop()


def test_the_server_has_the_kernel_probe_idle_peers(key_root):
    """A peer gone without a FIN (power loss, a NAT that forgot it) must not hold memory or its key's places for
    ever: every accepted connection has TCP keepalive on, with the configured idle time."""
    server = start_server(key_root / "server", keepalive_s=7.0)
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot"), timeout_s=5.0) as robot:
            robot.ping()
            (fd,) = list(server.guard.connections)
            with socket.fromfd(fd, socket.AF_INET, socket.SOCK_STREAM) as sock:
                assert sock.getsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE) == 1
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPIDLE) == 7
                assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_KEEPCNT) == 3
    finally:
        server.stop()


def test_the_client_pings_ahead_of_a_message_over_the_first_message_bound():
    frames_of = collections.defaultdict(list)   # connection (routing id) -> kinds of its messages, in order

    def record(request_id):
        return protocol.encode_reply(Reply(request_id, Status.OK, "ok"))
    server = FakeServer(record, on_message=lambda identity, frames: frames_of[identity].append(
        (protocol.decode_envelope(frames[0])[0], sum(len(frame) for frame in frames))))
    try:
        with CloudClient(server.endpoint, insecure=True, timeout_s=5.0) as client:
            client.upload(np.zeros((8, 8), np.int8))
            client.upload(np.zeros((300, 300), np.int8))
            client.upload(np.zeros((1100, 1000), np.int8))
        with CloudClient(server.endpoint, insecure=True, timeout_s=5.0) as client:
            client.upload(np.zeros((300, 300), np.int8))
    finally:
        server.close()
    first, second = frames_of.values()
    kinds = [kind for kind, _ in first]
    # A tiny first message needs no ping ahead, nor a later one up to the bound; a larger one does.
    assert kinds == [Kind.UPLOAD, Kind.UPLOAD, Kind.PING, Kind.UPLOAD]
    assert first[1][1] <= protocol.FIRST_MESSAGE_MAX_BYTES < first[3][1]
    # A new socket's first message that is not tiny (a map) goes after a ping.
    assert [kind for kind, _ in second] == [Kind.PING, Kind.UPLOAD]


class FakeServer:
    """A ROUTER that answers every request with reply_for(request_id)."""

    def __init__(self, reply_for, on_message=lambda identity, frames: None):
        self.on_message = on_message
        self.context = zmq.Context()
        self.socket = self.context.socket(zmq.ROUTER)
        self.socket.linger = 0
        port = self.socket.bind_to_random_port(LOOPBACK)
        self.endpoint = f"{LOOPBACK}:{port}"
        self.reply_for = reply_for
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self):
        while not self.stop.is_set():
            if self.socket.poll(50):
                frames = self.socket.recv_multipart()
                self.on_message(frames[0], frames[1:])
                _, request_id = protocol.decode_envelope(frames[1])
                self.socket.send_multipart([frames[0], *self.reply_for(request_id)], copy=False)

    def close(self):
        self.stop.set()
        self.thread.join(5)
        self.socket.close(0)
        self.context.term()


def _lying_reply(path, goal=(9, 9), cost=None, status=Status.OK, planning_time_s=0.0):
    path = np.asarray(path, np.int32).reshape(-1, 2)
    if cost is None:
        steps = np.abs(np.diff(path, axis=0))
        cost = float(np.sum(np.where(steps.sum(axis=1) == 2, np.sqrt(2.0), 1.0))) if len(path) > 1 else 0.0
    return lambda request_id: protocol.encode_reply(Reply(request_id, status, "", path, goal, 10, planning_time_s,
                                                          cost))


def test_the_reply_check_costs_the_path_not_the_map():
    """#30: the bridge checked each cloud reply with a free-cell mask of the whole grid (16 MB and 8 ms on a
    4 M-cell map per cloud plan). The check reads only the path's cells now: what it allocates does not grow
    with the map."""
    import tracemalloc
    from offload_cloud.client import reply_problem
    grid = np.zeros((4000, 4000), np.int8)
    path = np.array([(x, 100) for x in range(100, 141)], np.int32)
    reply = Reply(1, Status.OK, "", path, (140, 100), 41, 0.001, 40.0)
    tracemalloc.start()
    try:
        assert reply_problem(reply, grid, (100, 100), (140, 100), protocol.PlanOptions(), 1.0) == ""
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20, f"the check allocated {peak} bytes on a {grid.size}-cell map"


def test_client_bounds_reply_size_and_checks_the_path_against_the_map_it_sent():
    grid = np.zeros((10, 10), np.int8)
    grid[5, 1:9] = 100
    diagonal = [(k, k) for k in range(10)]
    honest = [(0, 0), (1, 1), (2, 2), (3, 3), (4, 4), (5, 4), (6, 4), (7, 4), (8, 4), (9, 4), (9, 5), (9, 6),
              (9, 7), (9, 8), (9, 9)]
    lies = {
        "huge path": (_lying_reply(np.zeros((300_000, 2)), cost=0.0), "timeout"),   # 2.4 MB over a 1 MiB bound
        "off the map": (_lying_reply([(0, 0), (-1, 1)], goal=(-1, 1)), "leaves the map"),
        "through a wall": (_lying_reply(diagonal), "obstacle"),
        "cuts a corner": (_lying_reply([(0, 0), (0, 1), (0, 2), (0, 3), (0, 4), (1, 4), (2, 4), (3, 4), (4, 4),
                                        (5, 4), (6, 4), (7, 4), (8, 4), (9, 5), (9, 6), (9, 7), (9, 8), (9, 9)]),
                          "corner"),
        "absurd cost": (_lying_reply(honest, cost=5e306), "cost"),
        "jumps": (_lying_reply([(0, 0), (9, 9)]), "8-connected"),
        "wrong start": (_lying_reply(honest[1:]), "starts at"),
        "planning time": (_lying_reply(honest, planning_time_s=1e300), "planning time"),
        "failure with a path": (_lying_reply(honest, status=Status.NO_PATH), "with a path"),
    }
    for name, (reply_for, expected) in lies.items():
        fake = FakeServer(reply_for)
        try:
            with CloudClient(fake.endpoint, insecure=True, timeout_s=1.0, retries=0, max_reply_bytes=MIB) as client:
                client.known_maps.add(protocol.grid_hash(grid))
                if expected == "timeout":
                    with pytest.raises(CloudTimeout):
                        client.plan(grid, (0, 0), (9, 9))
                    continue
                reply = client.plan(grid, (0, 0), (9, 9)).reply
                assert reply.status == Status.SERVER_ERROR and expected in reply.message, (name, reply)
        finally:
            fake.close()
    fake = FakeServer(_lying_reply(honest))
    try:
        with CloudClient(fake.endpoint, insecure=True, timeout_s=1.0, retries=0) as client:
            assert client.plan(grid, (0, 0), (9, 9)).reply.status == Status.OK   # the truth still passes
    finally:
        fake.close()


def test_a_path_through_the_inflated_band_is_refused_when_the_request_inflates():
    """#31 Medium 6: the client checked a cloud path against the raw grid, so with a robot radius a path
    hugging an obstacle was accepted (40/40 lying replies, 26 within 3 cells of obstacles). It is checked
    against the grid the request was planned on: the map inflated by the planner's own rule."""
    grid = np.zeros((20, 20), np.int8)
    grid[10, 0:15] = 100                                         # a wall with a gap at x >= 15
    hugging = [(16, y) for y in range(0, 20)]                    # through the gap, one cell from the wall's end
    inflating = protocol.PlanOptions(robot_radius_cells=2.0)
    for options, expected in ((protocol.PlanOptions(), Status.OK), (inflating, Status.SERVER_ERROR)):
        fake = FakeServer(_lying_reply(hugging, goal=(16, 19)))
        try:
            with CloudClient(fake.endpoint, insecure=True, timeout_s=1.0, retries=0) as client:
                client.known_maps.add(protocol.grid_hash(grid))
                reply = client.plan(grid, (16, 0), (16, 19), options).reply
                assert reply.status == expected, (options, reply)
                if expected == Status.SERVER_ERROR:
                    assert "obstacle" in reply.message
        finally:
            fake.close()
    honest = offload_planner_cpp.plan(grid, (17, 0), (17, 19), robot_radius_cells=2.0)
    fake = FakeServer(_lying_reply(honest.path, goal=(17, 19), cost=honest.cost))
    try:
        with CloudClient(fake.endpoint, insecure=True, timeout_s=1.0, retries=0) as client:
            client.known_maps.add(protocol.grid_hash(grid))
            assert client.plan(grid, (17, 0), (17, 19), inflating).reply.status == Status.OK   # the truth passes
    finally:
        fake.close()


@pytest.mark.parametrize("argv, expected", [
    (["--bind", "tcp://127.0.0.1:99999", "--insecure"], "port in 0..65535"),
    (["--bind", "tcp://127.0.0.1", "--insecure"], "tcp://HOST:PORT"),
    (["--max-message-mib", "0", "--insecure"], "--max-message-mib must be in"),
    (["--cache-mib", "-5", "--insecure"], "--cache-mib must be in"),
    (["--workers", "0", "--insecure"], "--workers must be in"),
    (["--max-queued-mib", "8", "--insecure"], "must be >= --max-message-mib"),
    (["--max-frame-mib", "0", "--insecure"], "--max-frame-mib must be in"),
    (["--max-frame-mib", "65", "--insecure"], "--max-frame-mib (65) must be <= --max-message-mib (64)"),
    (["--max-wait-s", "nan", "--insecure"], "--max-wait-s must be in"),
    (["--max-wait-s", "0", "--insecure"], "--max-wait-s must be in"),
])
def test_server_refuses_absurd_flags_before_any_work(argv, expected, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(argv)
    assert exit_info.value.code == 2 and expected in capsys.readouterr().err


def test_busy_warnings_are_rate_limited(caplog):
    server = start_server(None, workers=1, max_queued=1, max_message_bytes=4 * MIB, max_queued_bytes=4 * MIB)
    grid = np.zeros((1500, 1500), np.int8)
    context = zmq.Context()
    socket = context.socket(zmq.DEALER)
    socket.linger = 0
    socket.connect(server.endpoint)
    try:
        with caplog.at_level(logging.WARNING, logger="offload_cloud.server"):
            with CloudClient(server.endpoint, insecure=True, timeout_s=30.0) as client:
                client.upload(grid)
                digest = protocol.grid_hash(grid)
                for request_id in range(300):
                    socket.send_multipart(protocol.encode_plan(request_id, digest, (0, 0), (1499, 1499),
                                                               PlanOptions(stop_at_goal=False)))
                replies = []
                while len(replies) < 300 and socket.poll(30000):
                    replies.append(protocol.decode_reply(socket.recv_multipart()).status)
        busy_lines = [r for r in caplog.records if "BUSY" in r.getMessage()]
        assert replies.count(Status.BUSY) >= 250 and len(replies) == 300
        assert 1 <= len(busy_lines) <= 10, len(busy_lines)
    finally:
        socket.close(0)
        context.term()
        server.stop()
