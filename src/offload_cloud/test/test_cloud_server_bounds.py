"""The cloud server under hostile input: memory bounded by the cache cap and the connection guard, absurd
flags refused before any work, warnings rate limited (the client's checks of replies: test_cloud_client_bounds).
Each test reproduces an attack at a scale that runs in seconds; OFFLOAD_ATTACK_SCALE=full runs the larger versions
(200,000 uploads)."""
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

from offload_cloud import protocol
from offload_cloud.client import CloudClient
from offload_cloud.protocol import Kind, PlanOptions, Status
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
