"""request_queue.py and admission.py under load: one upload of a map for a storm of robots, the waiting
requests of a client that gave up dropped, a request that waited past --max-wait-s answered BUSY, BUSY
under real load with every request answered once, the queued-bytes budget. Larger runs:
OFFLOAD_ATTACK_SCALE=full (a 20-robot storm on a 2000 x 2000 map)."""
import collections
import threading
import time

import numpy as np
import pytest
import zmq

from offload_cloud import keys, protocol
from offload_cloud.client import CloudClient, CloudTimeout
import offload_planner_cpp
from offload_cloud.protocol import PlanOptions, Status
from offload_cloud.server import CloudServer, ServerConfig
from offload_cloud.server_cli import parse_args

from cloud_test_helpers import (FULL, curve_dealer, random_map, start_server)

pytestmark = pytest.mark.timeout(180)


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
    # STATS and the metrics count them as BUSY for having waited; the upload and the three waited in the queue.
    assert server.admission.busy == {"waited": 3} and sum(server.queue_seconds.counts) == 4
    assert sum(server.plan_seconds.counts) == 0   # an upload is no plan


def _flood(endpoint, messages, wait_s=60.0):
    """Sends every message at once on one DEALER, then collects the replies: {request id: [statuses]}."""
    context = zmq.Context()
    socket = context.socket(zmq.DEALER)
    socket.linger = 0
    socket.connect(endpoint)
    replies = collections.defaultdict(list)
    try:
        for message in messages:
            socket.send_multipart(message)
        deadline = time.monotonic() + wait_s
        while sum(map(len, replies.values())) < len(messages) and time.monotonic() < deadline:
            if socket.poll(200):
                reply = protocol.decode_reply(socket.recv_multipart())
                replies[reply.request_id].append(reply)
        while socket.poll(300):   # nothing more may come
            reply = protocol.decode_reply(socket.recv_multipart())
            replies[reply.request_id].append(reply)
    finally:
        socket.close(0)
        context.term()
    return replies


def test_busy_under_real_load_every_request_answered_once():
    """A real server, one worker, a queue of 2: a burst of 60 long plans gets BUSY for all but the few the
    worker and the queue hold, at once, and each of the others a correct plan."""
    server = start_server(None, workers=1, max_queued=2, max_message_bytes=4 << 20, max_queued_bytes=4 << 20)
    grid = np.zeros((1200, 1200), np.int8)
    grid[600, 1:] = 100
    digest = protocol.grid_hash(grid)
    try:
        with CloudClient(server.endpoint, insecure=True, timeout_s=10.0) as client:
            assert client.upload(grid).status == Status.OK
        options = PlanOptions(stop_at_goal=False)
        plans = [protocol.encode_plan(k, digest, (0, 0), (1199, 1199), options) for k in range(60)]
        replies = _flood(server.endpoint, plans)
    finally:
        server.stop()
    assert sorted(replies) == list(range(60)) and all(len(r) == 1 for r in replies.values())
    statuses = collections.Counter(r[0].status for r in replies.values())
    assert set(statuses) == {Status.OK, Status.BUSY} and 3 <= statuses[Status.OK] <= 30, statuses
    expected = offload_planner_cpp.plan_raw(grid, (0, 0), (1199, 1199), stop_at_goal=False)
    for (reply,) in replies.values():
        if reply.status == Status.BUSY:
            assert "queued" in reply.message and len(reply.path) == 0
        else:
            assert reply.cost_cells == pytest.approx(1199 * np.sqrt(2.0) + 2 * 1.0, abs=1e-6) or \
                reply.cost_cells == expected["cost"]
            np.testing.assert_array_equal(reply.path, expected["path"])


def test_queued_bytes_budget_gives_busy_under_real_load():
    """Beyond the queued bytes budget an upload gets BUSY while the worker plans; pings never queue."""
    server = start_server(None, workers=1, max_queued=64, max_message_bytes=2 << 20, max_queued_bytes=4 << 20)
    assert server.config.receive_hwm == 2
    grid = np.zeros((1400, 1400), np.int8)
    digest = protocol.grid_hash(grid)
    try:
        with CloudClient(server.endpoint, insecure=True, timeout_s=10.0) as client:
            assert client.upload(grid).status == Status.OK
        long_plans = [protocol.encode_plan(k, digest, (0, 0), (1399, 1399), PlanOptions(stop_at_goal=False))
                      for k in range(4)]
        uploads = [protocol.encode_upload(100 + k, random_map(1200, 1200, 0.1, seed=k)) for k in range(5)]
        replies = _flood(server.endpoint, long_plans + uploads + [protocol.encode_ping(200)])
    finally:
        server.stop()
    assert all(len(replies[k]) == 1 for k in [0, 1, 2, 3, 100, 101, 102, 103, 104, 200])
    assert all(replies[k][0].status == Status.OK for k in range(4)) and replies[200][0].message == "pong"
    upload_statuses = [replies[100 + k][0].status for k in range(5)]
    # 1.44 MB each: two fit the 4 MiB budget beside the queued plans, the rest are refused at once.
    assert upload_statuses.count(Status.OK) == 2 and upload_statuses.count(Status.BUSY) == 3, upload_statuses
    assert "bytes) queued" in next(r[0].message for k, r in replies.items() if r[0].status == Status.BUSY)
    with pytest.raises(ValueError):
        CloudServer(ServerConfig(insecure=True, max_message_bytes=64 << 20, max_queued_bytes=32 << 20))
    assert parse_args(["--max-queued-mib", "32", "--max-message-mib", "16"]).max_queued_mib == 32
    assert parse_args([]).max_queued_mib == 256
