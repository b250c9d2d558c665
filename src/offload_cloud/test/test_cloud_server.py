"""The cloud server on a random loopback port: correct plans, CURVE allowlist, hostile input, size cap,
cache misses, concurrency, and the health-check command."""
import collections
import os
import random
import signal
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
from offload_cloud.keys import load_client_keys
from offload_cloud.protocol import Kind, PlanOptions, Status

from cloud_test_helpers import LOOPBACK, free_port, make_keys, random_map, spawn_server, start_server, stop_process

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def key_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("keys")
    server_keys = make_keys(root, ["robot", "robot2"])
    intruder = make_keys(tmp_path_factory.mktemp("other"), ["intruder"]).parent / "intruder"
    return server_keys, root / "robot", intruder


@pytest.fixture(scope="module")
def server(key_dirs):
    server = start_server(key_dirs[0], workers=2, max_message_bytes=1 << 20, cache_bytes=1 << 22)
    yield server
    server.stop()


@pytest.fixture
def client(server, key_dirs):
    with CloudClient(server.endpoint, keys_dir=str(key_dirs[1]), timeout_s=5.0) as client:
        yield client


def curve_socket(context, key_dir, endpoint, kind=zmq.DEALER):
    socket = context.socket(kind)
    socket.linger = 0
    public, secret, server_public = load_client_keys(key_dir)
    socket.curve_publickey, socket.curve_secretkey, socket.curve_serverkey = public, secret, server_public
    socket.connect(endpoint)
    return socket


def test_ping_and_plan_match_local_planning(client):
    assert client.ping() > 0
    grid = random_map(60, 40, 0.2, seed=1)
    outcome = client.plan(grid, (0, 0), (59, 39))
    local = offload_planner_cpp.plan_raw(grid, (0, 0), (59, 39))
    assert outcome.uploaded and outcome.reply.status == Status.OK and local["status"] == offload_planner_cpp.PlanStatus.OK
    np.testing.assert_array_equal(outcome.reply.path, local["path"])
    assert outcome.reply.cost_cells == local["cost"] and outcome.reply.expansions == local["expansions"]
    again = client.plan(grid, (0, 0), (59, 39))
    assert not again.uploaded and again.reply.status == Status.OK


def test_planner_failures_come_back_as_statuses(client):
    grid = np.zeros((10, 10), np.int8)
    grid[5, :] = 100
    assert client.plan(grid, (0, 0), (9, 9)).reply.status == Status.NO_PATH
    blocked = client.plan(grid, (0, 0), (5, 5)).reply
    assert blocked.status == Status.GOAL_BLOCKED and "obstacle" in blocked.message
    assert client.plan(grid, (0, 0), (50, 5)).reply.status == Status.GOAL_OFF_MAP
    tolerant = client.plan(grid, (0, 0), (5, 5), PlanOptions(goal_tolerance_cells=1.5)).reply
    assert tolerant.status == Status.OK and tolerant.goal != (5, 5)


def test_old_client_gets_unsupported_version(server, key_dirs):
    context = zmq.Context()
    socket = curve_socket(context, key_dirs[1], server.endpoint)
    try:
        socket.send_multipart([protocol.ENVELOPE.pack(protocol.MAGIC, 0, Kind.PING, 12)])
        assert socket.poll(5000)
        reply = protocol.decode_reply(socket.recv_multipart())
        assert reply.status == Status.UNSUPPORTED_VERSION and reply.request_id == 12
        assert f"speaks version {protocol.VERSION}" in reply.message
    finally:
        socket.close(0)
        context.term()


def test_req_socket_clients_are_served_too(server, key_dirs):
    context = zmq.Context()
    socket = curve_socket(context, key_dirs[1], server.endpoint, zmq.REQ)
    try:
        socket.send_multipart(protocol.encode_ping(5))
        assert socket.poll(5000)
        assert protocol.decode_reply(socket.recv_multipart()).status == Status.OK
    finally:
        socket.close(0)
        context.term()


def test_unknown_client_key_gets_no_service(server, key_dirs):
    with CloudClient(server.endpoint, keys_dir=str(key_dirs[2]), timeout_s=1.0, retries=0) as intruder:
        with pytest.raises(CloudTimeout):
            intruder.ping()
        with pytest.raises(CloudTimeout):
            intruder.plan(np.zeros((4, 4), np.int8), (0, 0), (3, 3))
    with CloudClient(server.endpoint, insecure=True, timeout_s=1.0, retries=0) as plaintext:
        with pytest.raises(CloudTimeout):
            plaintext.ping()
    with CloudClient(server.endpoint, keys_dir=str(key_dirs[1].parent / "robot2"), timeout_s=5.0) as allowed:
        assert allowed.ping() > 0


HOSTILE_METADATA = [
    b"[" * 1000, b"{" * 1000, b'{"a":' * 300 + b"1" + b"}" * 300, b'{"a":[' * 150,   # deep nesting
    b"[]", b'"int8"', b"null", b"1e999", b"\xff\xfe{", b" " * 1025,                  # not an object, too long
    b'{"dtype":"int16","height":30,"width":30}', b'{"dtype":["int8"],"height":30,"width":30}',   # wrong dtype
    b'{"dtype":"int8","height":-30,"width":30}', b'{"dtype":"int8","height":30,"width":0}',      # sizes
    b'{"dtype":"int8","height":30,"width":1' + b"0" * 40 + b"}", b'{"dtype":"int8","height":100001,"width":1}',
    b'{"dtype":"int8","height":2000,"width":2000}', b'{"dtype":"int8","height":30.0,"width":30}',
    b'{"dtype":"int8","height":true,"width":30}', b'{"dtype":"int8","height":30}',
]
HOSTILE_TOLERANCES = [float("nan"), float("inf"), -float("inf"), -1.0, -0.0, 0.0, 5e-324, 1.5, 1e300, 1e308,
                      1.7976931348623157e308]
INT32_EDGES = [0, 1, 29, 30, -1, 2**31 - 1, -2**31]


def expected_reply_id(message, max_frames):
    """The request id the server's reply to `message` (sent by a DEALER) carries, or None when the protocol
    drops it unanswered (more frames than any valid message: `max_frames`, and a REQ-style delimiter)."""
    if len(message) > max_frames + 1:               # identity + more than max_frames + 1 frames: dropped
        return None
    payload = message[1:] if len(message) >= 2 and message[0] == b"" else message   # REQ-style delimiter
    return protocol.request_id_of(payload[0])


def test_fuzz_every_answerable_message_gets_exactly_one_reply(server, key_dirs, client):
    rng = random.Random(1234)
    grid = random_map(30, 30, 0.1, seed=2)
    digest = protocol.grid_hash(grid)
    assert client.upload(grid).status == Status.OK   # cached, so hash-only plans reach the planner
    valid = [bytes(f) for f in protocol.encode_plan(7, digest, (0, 0), (29, 29), grid=grid)]
    ping = protocol.encode_ping(8)[0]

    def garbage():
        choice = rng.randrange(8)
        if choice == 0:   # random frames
            return [rng.randbytes(rng.randrange(0, 64)) for _ in range(rng.randrange(1, 6))]
        if choice == 1:   # a valid message truncated at a random frame and byte
            frames = valid[:rng.randrange(1, len(valid) + 1)]
            cut = rng.randrange(len(frames))
            return frames[:cut] + [frames[cut][:rng.randrange(len(frames[cut]) + 1)]]
        if choice == 2:   # a valid message with random bytes flipped
            frames = [bytearray(f) for f in valid[:2]]
            for _ in range(rng.randrange(1, 4)):
                frame = frames[rng.randrange(len(frames))]
                if frame:
                    frame[rng.randrange(len(frame))] = rng.randrange(256)
            return [bytes(f) for f in frames]
        if choice == 3:   # right envelope, hostile body
            kind = rng.choice([Kind.PLAN, Kind.UPLOAD, Kind.REPLY, Kind.PING])
            return [protocol.envelope(kind, rng.getrandbits(64))] + [rng.randbytes(rng.randrange(80))
                                                                      for _ in range(rng.randrange(0, 4))]
        if choice == 4:   # many frames
            return [ping] * rng.randrange(5, 40)
        if choice == 5:
            return [b""] * rng.randrange(1, 4) + [ping]
        if choice == 6:   # hostile map metadata, in an upload or with a plan
            metadata = rng.choice(HOSTILE_METADATA)
            cells = valid[3] if rng.random() < 0.7 else rng.randbytes(rng.randrange(2000))
            if rng.random() < 0.5:   # an upload's cells in one to three frames, split anywhere
                cuts = sorted(rng.randrange(len(cells) + 1) for _ in range(rng.randrange(3)))
                pieces = [cells[a:b] for a, b in zip([0] + cuts, cuts + [len(cells)])]
                return [protocol.envelope(Kind.UPLOAD, rng.getrandbits(64)), metadata, *pieces]
            return [protocol.envelope(Kind.PLAN, rng.getrandbits(64)), valid[1], metadata, cells]
        # hostile plan body on the cached map: tolerance, cells, lethal threshold, flags
        body = protocol.PLAN_BODY.pack(digest if rng.random() < 0.8 else rng.randbytes(16),
                                       *(rng.choice(INT32_EDGES) if rng.random() < 0.3 else rng.randrange(30)
                                         for _ in range(4)),
                                       rng.choice(HOSTILE_TOLERANCES), rng.choice([50, 0, 100, -1, 32767, -32768]),
                                       rng.randrange(256))
        return [protocol.envelope(Kind.PLAN, rng.getrandbits(64)), body]

    expected = [collections.Counter() for _ in range(4)]
    received = [collections.Counter() for _ in range(4)]
    statuses = collections.Counter()

    def drain(k, wait_ms=0):
        while sockets[k].poll(wait_ms):
            frames = sockets[k].recv_multipart()
            if len(frames) == 5 and frames[0] == b"":   # answer to a message sent with an empty first frame
                frames = frames[1:]
            reply = protocol.decode_reply(frames)
            received[k][reply.request_id] += 1
            statuses[reply.status] += 1
            assert reply.status != Status.SERVER_ERROR, reply.message
            wait_ms = 0

    context = zmq.Context()
    sockets = [curve_socket(context, key_dirs[1], server.endpoint) for _ in range(4)]
    started = time.monotonic()
    try:
        for k in range(3000):
            message = garbage()
            sockets[k % 4].send_multipart(message)
            request_id = expected_reply_id(message, server.config.max_frames)
            if request_id is not None:
                expected[k % 4][request_id] += 1
            if k % 200 == 199:   # drain so the server's replies never pile up
                for j in range(4):
                    drain(j)
        deadline = time.monotonic() + 15
        for j in range(4):
            while received[j] != expected[j] and time.monotonic() < deadline:
                drain(j, 100)
        for j in range(4):
            drain(j, 300)   # nothing more may come: exactly one reply each
        for j in range(4):
            assert received[j] == expected[j], (expected[j] - received[j], received[j] - expected[j])
    finally:
        for socket in sockets:
            socket.close(0)
        context.term()
    assert sum(sum(c.values()) for c in expected) > 2500
    assert {Status.OK, Status.BAD_REQUEST, Status.TOO_LARGE, Status.MAP_UNKNOWN, Status.START_OFF_MAP} <= set(statuses)
    assert time.monotonic() - started < 30
    outcome = client.plan(grid, (0, 0), (29, 29))
    assert outcome.reply.status == Status.OK
    np.testing.assert_array_equal(outcome.reply.path, offload_planner_cpp.plan_raw(grid, (0, 0), (29, 29))["path"])


def test_huge_goal_tolerance_is_answered_in_time(client):
    grid = np.zeros((300, 300), np.int8)
    grid[200:, 200:] = 100   # the goal (299, 299) is blocked: the tolerance decides
    for goal, tolerance in (((10, 10), 1e300), ((299, 299), 1e300), ((299, 299), 1.7976931348623157e308)):
        started = time.monotonic()
        reply = client.plan(grid, (0, 0), goal, PlanOptions(goal_tolerance_cells=tolerance)).reply
        assert time.monotonic() - started < 10.0
        assert reply.status == Status.OK, reply.message
    assert reply.goal != (299, 299) and grid[reply.goal[1], reply.goal[0]] == 0


def test_oversized_message_is_refused_and_server_survives(server, key_dirs, client):
    big = np.zeros((1100, 1000), np.int8)   # 1.1 MB over the 1 MiB cap, sent in frames of at most 1 MiB
    with CloudClient(server.endpoint, keys_dir=str(key_dirs[1]), timeout_s=5.0, retries=0) as sender:
        reply = sender.plan(big, (0, 0), (5, 5)).reply
        assert reply.status == Status.TOO_LARGE and "--max-message-mib" in reply.message, reply
    # A frame over the cap makes libzmq drop the connection: no reply at all (test_cloud_frames.py).
    with pytest.raises(CloudTimeout):
        with CloudClient(server.endpoint, keys_dir=str(key_dirs[1]), timeout_s=1.0, retries=0) as sender:
            sender.request(lambda request_id: [protocol.envelope(Kind.UPLOAD, request_id), protocol.map_metadata(big),
                                               big.tobytes()])
    # Frames each under the cap but together over it are refused with a reply.
    context = zmq.Context()
    socket = curve_socket(context, key_dirs[1], server.endpoint)
    try:
        half = bytes(700_000)
        socket.send_multipart([protocol.envelope(Kind.UPLOAD, 3), half, half])
        assert socket.poll(5000)
        assert protocol.decode_reply(socket.recv_multipart()).status == Status.TOO_LARGE
    finally:
        socket.close(0)
        context.term()
    assert client.ping() > 0


def test_sigterm_stops_the_server_cleanly(tmp_path):
    """SIGTERM mid-service: exit status 0 and the orderly stop line (the handler, not the default action)."""
    port = free_port()
    log_path = tmp_path / "server.log"
    process = spawn_server(port, None, log_path=log_path, extra_args=["--log-level", "INFO"])
    try:
        with CloudClient(f"{LOOPBACK}:{port}", insecure=True, timeout_s=5.0) as client:
            assert client.plan(random_map(50, 50, 0.1, seed=9), (0, 0), (49, 49)).reply.status == Status.OK
        started = time.monotonic()
        process.send_signal(signal.SIGTERM)
        returncode = process.wait(20)
        print(f"exit {time.monotonic() - started:.2f} s after SIGTERM")
    finally:
        stop_process(process)
    assert returncode == 0
    assert "stopped; cache hits" in log_path.read_text()


def test_cache_miss_makes_the_client_upload_again(key_dirs):
    server = start_server(key_dirs[0], workers=1, cache_bytes=150_000)   # room for one 100 kB map
    try:
        with CloudClient(server.endpoint, keys_dir=str(key_dirs[1]), timeout_s=5.0) as client:
            first, second = random_map(400, 250, 0.1, seed=3), random_map(400, 250, 0.1, seed=4)
            assert client.plan(first, (0, 0), (399, 249)).uploaded
            assert not client.plan(first, (0, 0), (10, 10)).uploaded
            assert client.plan(second, (0, 0), (399, 249)).uploaded   # evicts the first map
            outcome = client.plan(first, (0, 0), (399, 249))
            assert outcome.uploaded and outcome.reply.status == Status.OK
            assert server.cache.evictions >= 1
            assert not client.plan(first, (0, 0), (399, 249)).uploaded
    finally:
        server.stop()


def test_many_concurrent_clients_get_correct_paths(server, key_dirs):
    grid = random_map(120, 90, 0.25, seed=5)
    rng = np.random.default_rng(6)
    free = np.argwhere(grid == 0)
    jobs = [(tuple(free[a][::-1]), tuple(free[b][::-1])) for a, b in rng.integers(0, len(free), (48, 2))]
    results = {}

    def robot(index):
        with CloudClient(server.endpoint, keys_dir=str(key_dirs[1]), timeout_s=20.0) as client:
            for job in range(index, len(jobs), 8):
                results[job] = client.plan(grid, *jobs[job]).reply

    threads = [threading.Thread(target=robot, args=(k,)) for k in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert len(results) == len(jobs)
    for job, (start, goal) in enumerate(jobs):
        local = offload_planner_cpp.plan_raw(grid, start, goal)
        reply = results[job]
        assert reply.status == int(local["status"])
        np.testing.assert_array_equal(reply.path, local["path"])
        assert reply.cost_cells == local["cost"]


def test_health_check_command(server, key_dirs):
    command = [sys.executable, "-m", "offload_cloud.client"]
    ok = subprocess.run(command + [server.endpoint, "--ping", "--keys-dir", str(key_dirs[1])],
                        capture_output=True, text=True, timeout=60, env=os.environ)
    assert ok.returncode == 0, ok.stderr
    assert "round trip" in ok.stdout
    denied = subprocess.run(command + [server.endpoint, "--ping", "--keys-dir", str(key_dirs[2]), "--timeout",
                                       "0.5"], capture_output=True, text=True, timeout=60, env=os.environ)
    assert denied.returncode == 1 and "no answer" in denied.stderr
