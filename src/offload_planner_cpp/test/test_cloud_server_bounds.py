"""Issue 10 ("Hold under attack"), the cloud link's findings: each test reproduces one attack at a scale
that runs in seconds and checks the property the fix must hold. Larger runs: OFFLOAD_ATTACK_SCALE=full
(200,000 uploads, a 20-robot storm on a 2000 x 2000 map)."""
import logging
import os
import pathlib
import signal
import stat
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zmq

from offload_planner_cpp.cloud import keys, protocol
from offload_planner_cpp.cloud.client import CloudClient, CloudTimeout
from offload_planner_cpp.cloud.keys import load_client_keys
from offload_planner_cpp.cloud.protocol import Kind, PlanOptions, Reply, Status
from offload_planner_cpp.cloud.server import CloudServer, ServerConfig
from offload_planner_cpp.cloud.server_cli import parse_args

from cloud_test_helpers import (LOOPBACK, curve_dealer, free_port, make_keys, random_map, rss_bytes, spawn_server,
                                start_server, stop_process)

pytestmark = pytest.mark.timeout(180)
FULL = os.environ.get("OFFLOAD_ATTACK_SCALE") == "full"
MIB = 1 << 20


@pytest.fixture
def key_root(tmp_path):
    make_keys(tmp_path, ["robot", "robot2"])
    return tmp_path


# -- finding 1: the cache cap holds for many tiny maps -------------------------------------------------

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


# -- finding 2: a message of many frames is bounded per connection --------------------------------------

def test_message_of_many_frames_is_cut_at_the_connection_bound(key_root, tmp_path):
    frames, frame_bytes = (24, 50 * MIB - 4096) if FULL else (200, MIB - 4096)
    max_message_mib = 64 if FULL else 1
    port = free_port()
    process = spawn_server(port, key_root / "server", log_path=tmp_path / "server.log",
                           extra_args=["--max-message-mib", str(max_message_mib),
                                       "--max-queued-mib", str(2 * max_message_mib if not FULL else 256)])
    endpoint = f"{LOOPBACK}:{port}"
    context = zmq.Context()
    peak, stop = [0], threading.Event()

    def watch():
        while not stop.is_set():
            peak[0] = max(peak[0], rss_bytes(process.pid))
            time.sleep(0.002)

    try:
        with CloudClient(endpoint, keys_dir=str(key_root / "robot"), timeout_s=5.0) as client:
            client.ping()
            idle = peak[0] = rss_bytes(process.pid)
            watcher = threading.Thread(target=watch)
            watcher.start()
            attacker = curve_dealer(context, key_root / "robot2", endpoint)
            big = bytes(frame_bytes)   # each frame under the max message size, together far over it
            attacker.send_multipart([protocol.envelope(Kind.UPLOAD, 1)] + [big] * frames, copy=False)
            answered = attacker.poll(30000 if FULL else 4000)
            stop.set()
            watcher.join()
            attacker.close(0)
            assert client.ping() > 0     # the server lives and serves
        grown = peak[0] - idle
    finally:
        stop.set()
        context.term()
        stop_process(process)
    log = (tmp_path / "server.log").read_text()
    print(f"{frames} frames x {frame_bytes} B: RSS {idle / MIB:.1f} MiB, peak +{grown / MIB:.1f} MiB")
    assert not answered and "cut the connection" in log
    # The per-connection bound is (receive HWM + 1) x max message + 1 MiB: 4 MiB here (landed code: +143 MiB).
    assert grown <= (8 if not FULL else 400) * MIB


# -- finding 3: SIGHUP reloads the allowlist -------------------------------------------------------------

def _answers(key_dir, endpoint, timeout_s=1.0) -> bool:
    with CloudClient(endpoint, keys_dir=str(key_dir), timeout_s=timeout_s, retries=0) as client:
        try:
            client.ping()
            return True
        except CloudTimeout:
            return False


def test_sighup_reloads_the_allowlist_revoking_and_admitting(key_root, tmp_path):
    server_keys = key_root / "server"
    port = free_port()
    process = spawn_server(port, server_keys, log_path=tmp_path / "server.log")
    endpoint = f"{LOOPBACK}:{port}"
    try:
        revoked = CloudClient(endpoint, keys_dir=str(key_root / "robot2"), timeout_s=1.0, retries=0)
        assert revoked.ping() > 0          # connected and served before the revocation
        (server_keys / "clients" / "robot2.key").unlink()
        keys.generate(key_root, ["robot3"], add_to=server_keys)
        process.send_signal(signal.SIGHUP)
        deadline = time.monotonic() + 10
        while not _answers(key_root / "robot3", endpoint) and time.monotonic() < deadline:
            pass
        assert _answers(key_root / "robot3", endpoint), "an admitted robot is refused after SIGHUP"
        with pytest.raises(CloudTimeout):
            revoked.ping()                 # its open connection was closed, its key is refused
        revoked.close()
        assert not _answers(key_root / "robot2", endpoint)
        assert _answers(key_root / "robot", endpoint)
        # A bad allowlist on reload keeps the previous one and the server running.
        (server_keys / "clients" / "junk.key").write_text("not a key\n")
        process.send_signal(signal.SIGHUP)
        time.sleep(0.5)
        assert process.poll() is None and _answers(key_root / "robot3", endpoint)
    finally:
        stop_process(process)
    log = (tmp_path / "server.log").read_text()
    assert "allowlist reloaded" in log and "allowlist NOT reloaded" in log and "junk.key" in log
    assert "refused a CURVE handshake from 127.0.0.1" in log     # finding 11: refusals at WARNING, with address


# -- finding 4: a key file without its secret line ------------------------------------------------------

def _strip_secret(path: pathlib.Path) -> None:
    path.write_text("".join(line for line in path.read_text().splitlines(True) if "secret-key" not in line))


def test_key_file_without_secret_fails_fast_with_one_line(key_root):
    robot_secret = key_root / "robot" / keys.CLIENT_SECRET
    _strip_secret(robot_secret)
    started = time.monotonic()
    check = subprocess.run([sys.executable, "-m", "offload_planner_cpp.cloud.client", "tcp://127.0.0.1:9", "--ping",
                            "--keys-dir", str(key_root / "robot"), "--timeout", "1"],
                           capture_output=True, text=True, timeout=60)
    assert check.returncode == 2 and time.monotonic() - started < 30
    assert check.stderr.count("\n") == 1 and str(robot_secret) in check.stderr and "Traceback" not in check.stderr
    server_secret = key_root / "server" / keys.SERVER_SECRET
    _strip_secret(server_secret)
    server = subprocess.run([sys.executable, "-m", "offload_planner_cpp.cloud.server", "--bind",
                             f"{LOOPBACK}:{free_port()}", "--keys-dir", str(key_root / "server")],
                            capture_output=True, text=True, timeout=60)
    assert server.returncode == 2 and "Traceback" not in server.stderr
    assert server.stderr.count("\n") == 1 and str(server_secret) in server.stderr
    with pytest.raises(ValueError, match=str(robot_secret)):
        CloudClient("tcp://127.0.0.1:9", keys_dir=str(key_root / "robot"))


# The node's start-up path without a ROS master: rospy's calls replaced by stand-ins, spin() for 3 s.
NODE_START = """
import sys, time, types, rospy
params = {"~endpoint": "tcp://127.0.0.1:9", "~keys_dir": sys.argv[1], "~heartbeat_period_s": 0.2}
rospy.init_node = rospy.on_shutdown = rospy.loginfo = rospy.logwarn = lambda *a, **k: None
rospy.get_param = lambda name, default=None: params.get(name, default)
rospy.logfatal = lambda fmt, *a: print("FATAL " + fmt % a, file=sys.stderr)
rospy.Publisher = lambda *a, **k: types.SimpleNamespace(publish=lambda msg: None)
rospy.Subscriber = lambda *a, **k: types.SimpleNamespace(resolved_name="map")
rospy.Service = lambda *a, **k: None
rospy.spin = lambda: time.sleep(3)
from offload_planner_cpp.nodes import cloud_bridge
cloud_bridge.main()
"""


def test_bridge_node_start_up_fails_fast_naming_the_key_file(key_root):
    robot_secret = key_root / "robot" / keys.CLIENT_SECRET
    _strip_secret(robot_secret)
    node = subprocess.run([sys.executable, "-c", NODE_START, str(key_root / "robot")], capture_output=True,
                          text=True, timeout=60)
    assert node.returncode == 1, node.stderr
    assert node.stderr.startswith("FATAL ") and str(robot_secret) in node.stderr and "Traceback" not in node.stderr


# -- findings 5 and 6: the keys tool ----------------------------------------------------------------------

def test_add_to_refuses_an_admitted_name_and_names_that_are_not_file_names(key_root):
    server_keys = key_root / "server"
    before = (server_keys / "clients" / "robot.key").read_bytes()
    other = key_root / "elsewhere"
    with pytest.raises(FileExistsError, match="already admitted"):
        keys.generate(other, ["robot"], add_to=server_keys)
    assert (server_keys / "clients" / "robot.key").read_bytes() == before and not (other / "robot").exists()
    assert keys.main([str(other), "--clients", "robot", "--add-to", str(server_keys)]) == 1
    keys.generate(other, ["robot"], add_to=server_keys, replace=True)
    assert (server_keys / "clients" / "robot.key").read_bytes() != before
    for name in ("..", ".", "a/b", "", "server", "clients", "-x", "x" * 65):
        with pytest.raises(ValueError, match="bad client name"):
            keys.generate(other, [name], add_to=server_keys)
    assert not (key_root / "client.key").exists() and not (key_root.parent / "client.key_secret").exists()


def test_secret_files_are_600_even_under_umask_000_and_loose_ones_are_refused(tmp_path):
    old_umask = os.umask(0)
    try:
        server_keys = keys.generate(tmp_path, ["robot"])
    finally:
        os.umask(old_umask)
    for secret in (server_keys / keys.SERVER_SECRET, tmp_path / "robot" / keys.CLIENT_SECRET):
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert not stat.S_IMODE((server_keys / "clients").stat().st_mode) & 0o022
    os.chmod(tmp_path / "robot" / keys.CLIENT_SECRET, 0o644)
    with pytest.raises(keys.KeyFileError, match="readable by others"):
        load_client_keys(tmp_path / "robot")
    os.chmod(server_keys / keys.SERVER_SECRET, 0o640)
    with pytest.raises(keys.KeyFileError, match="readable by others"):
        keys.load_server_keys(server_keys)
    os.chmod(server_keys / keys.SERVER_SECRET, 0o600)
    os.chmod(server_keys / "clients", 0o777)
    with pytest.raises(keys.KeyFileError, match="writable by others"):
        keys.load_server_keys(server_keys)
    os.chmod(server_keys / "clients", 0o755)
    os.chmod(server_keys / "clients" / "robot.key", 0o666)
    with pytest.raises(keys.KeyFileError, match="writable by others"):
        keys.load_server_keys(server_keys)


# -- finding 7: a fleet starting together on one large map ---------------------------------------------

def test_upload_storm_uploads_the_map_once_and_every_plan_is_answered(key_root, monkeypatch):
    robots, side, plans_each = (20, 2000, 6) if FULL else (10, 1000, 3)
    names = [f"r{k}" for k in range(robots)]
    keys.generate(key_root, names, add_to=key_root / "server")
    decoded = []
    real_decode_map = protocol.decode_map

    def counting_decode_map(metadata, data, max_cells):
        result = real_decode_map(metadata, data, max_cells)
        decoded.append(result[0])
        return result

    monkeypatch.setattr(protocol, "decode_map", counting_decode_map)
    grid = random_map(side, side, 0.05, seed=11)
    digest = protocol.grid_hash(grid)
    rng = np.random.default_rng(12)
    free = np.argwhere(grid == 0)
    server = start_server(key_root / "server", workers=2)
    statuses, barrier = {name: [] for name in names}, threading.Barrier(robots)
    pairs = [[tuple(tuple(int(v) for v in free[k][::-1]) for k in rng.integers(0, len(free), 2))
              for _ in range(plans_each)] for _ in names]

    def robot(index, name):
        with CloudClient(server.endpoint, keys_dir=str(key_root / name), timeout_s=5.0, retries=1) as client:
            barrier.wait()
            for start, goal in pairs[index]:
                try:
                    statuses[name].append(client.plan(grid, start, goal).reply.status)
                except CloudTimeout:
                    statuses[name].append("timeout")

    try:
        threads = [threading.Thread(target=robot, args=(k, name)) for k, name in enumerate(names)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
    finally:
        server.stop()
    every = [status for name in names for status in statuses[name]]
    print(f"{robots} robots x {plans_each} plans on {side} x {side}: {every.count(Status.OK)} OK, "
          f"{every.count(Status.BUSY)} BUSY, {every.count('timeout')} timeouts, map decoded {decoded.count(digest)} times")
    assert len(every) == robots * plans_each
    assert decoded.count(digest) == 1      # one upload for the whole fleet (landed code: one per robot)
    # Every plan answered: planned, or BUSY at once when the two workers cannot plan it within --max-wait-s
    # (the robot then plans locally); never left to time out. The large run may lose a first plan to the
    # 80 MB of simultaneous first uploads on a loaded machine, never a later one.
    assert all(status in (Status.OK, Status.BUSY) for name in names for status in statuses[name][1 if FULL else 0:])
    assert every.count(Status.OK) >= len(every) // 4, statuses


def test_waiting_requests_of_a_client_that_gave_up_are_dropped(key_root):
    server = start_server(key_root / "server", workers=1)
    grid = np.zeros((30, 30), np.int8)
    digest = protocol.grid_hash(grid)
    release, stuck, planned = threading.Event(), threading.Event(), []
    real_handle = server.handle

    def slow_handle(payload):   # the only worker is stuck on a long plan until released
        stuck.set()
        release.wait(30)
        planned.append(protocol.request_id_of(payload[0].buffer))
        return real_handle(payload)

    server.handle = slow_handle
    context = zmq.Context()
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_root / "robot"), timeout_s=30.0) as busy:
            busy_plan = threading.Thread(target=busy.plan, args=(grid, (0, 0), (29, 29)))
            busy_plan.start()
            assert stuck.wait(10)
            quitter = curve_dealer(context, key_root / "robot2", server.endpoint)
            for request_id in range(5):
                quitter.send_multipart(protocol.encode_plan(request_id, digest, (0, 0), (29, 29)))
            deadline = time.monotonic() + 10
            while server.queued_bytes < 5 * 57 and time.monotonic() < deadline:
                time.sleep(0.02)
            quitter.close(0)          # gave up, as Lazy Pirate does after a timeout
            while server.abandoned_dropped < 5 and time.monotonic() < deadline:
                time.sleep(0.02)
            release.set()
            busy_plan.join(30)
            assert busy.plan(grid, (0, 0), (29, 29)).reply.status == Status.OK
        assert server.abandoned_dropped == 5 and not set(planned) & set(range(5)), planned
    finally:
        release.set()
        context.term()
        server.stop()


def test_requests_that_waited_past_max_wait_get_busy_instead_of_a_late_plan(key_root):
    server = start_server(None, workers=1, max_wait_s=0.5)
    grid = np.zeros((30, 30), np.int8)
    release, stuck = threading.Event(), threading.Event()
    real_handle = server.handle

    def slow_handle(payload):
        stuck.set()
        release.wait(30)
        return real_handle(payload)

    server.handle = slow_handle
    context = zmq.Context()
    socket = context.socket(zmq.DEALER)
    socket.linger = 0
    socket.connect(server.endpoint)
    try:
        with CloudClient(server.endpoint, insecure=True, timeout_s=30.0) as client:
            first = threading.Thread(target=client.upload, args=(grid,))
            first.start()
            assert stuck.wait(10)
            digest = protocol.grid_hash(grid)
            for request_id in range(3):
                socket.send_multipart(protocol.encode_plan(request_id, digest, (0, 0), (29, 29)))
            time.sleep(1.0)          # they wait twice --max-wait-s behind the stuck worker
            release.set()
            first.join(30)
            replies = [protocol.decode_reply(socket.recv_multipart()) for _ in range(3) if socket.poll(10000)]
    finally:
        release.set()
        socket.close(0)
        context.term()
        server.stop()
    assert sorted(reply.request_id for reply in replies) == [0, 1, 2]
    assert all(reply.status == Status.BUSY and "--max-wait-s" in reply.message for reply in replies)


# -- finding 9: the client does not trust the server's reply ----------------------------------------------

class FakeServer:
    """A ROUTER that answers every request with reply_for(request_id)."""

    def __init__(self, reply_for):
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


# -- finding 10: command-line values -------------------------------------------------------------------------

@pytest.mark.parametrize("argv, expected", [
    (["--bind", "tcp://127.0.0.1:99999", "--insecure"], "port in 0..65535"),
    (["--bind", "tcp://127.0.0.1", "--insecure"], "tcp://HOST:PORT"),
    (["--max-message-mib", "0", "--insecure"], "--max-message-mib must be in"),
    (["--cache-mib", "-5", "--insecure"], "--cache-mib must be in"),
    (["--workers", "0", "--insecure"], "--workers must be in"),
    (["--max-queued-mib", "8", "--insecure"], "must be >= --max-message-mib"),
    (["--max-wait-s", "nan", "--insecure"], "--max-wait-s must be in"),
    (["--max-wait-s", "0", "--insecure"], "--max-wait-s must be in"),
])
def test_server_refuses_absurd_flags_before_any_work(argv, expected, capsys):
    with pytest.raises(SystemExit) as exit_info:
        parse_args(argv)
    assert exit_info.value.code == 2 and expected in capsys.readouterr().err


# -- finding 11: smaller things a fleet would see ---------------------------------------------------------

def test_garbage_key_in_the_allowlist_stops_the_server_at_start_up(key_root):
    junk = key_root / "server" / "clients" / "junk.key"
    junk.write_text("garbage\n")
    server = subprocess.run([sys.executable, "-m", "offload_planner_cpp.cloud.server", "--bind",
                             f"{LOOPBACK}:{free_port()}", "--keys-dir", str(key_root / "server")],
                            capture_output=True, text=True, timeout=60)
    assert server.returncode == 2 and str(junk) in server.stderr and "Traceback" not in server.stderr


def test_busy_warnings_are_rate_limited(caplog):
    server = start_server(None, workers=1, max_queued=1, max_message_bytes=4 * MIB, max_queued_bytes=4 * MIB)
    grid = np.zeros((1500, 1500), np.int8)
    context = zmq.Context()
    socket = context.socket(zmq.DEALER)
    socket.linger = 0
    socket.connect(server.endpoint)
    try:
        with caplog.at_level(logging.WARNING, logger="offload_planner_cpp.cloud.server"):
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
