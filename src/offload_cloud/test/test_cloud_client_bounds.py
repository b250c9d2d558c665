"""The cloud client against a server that lies or is hostile: it pings ahead of a message over the first-message
bound, bounds a reply's size, and checks every reply's path against the map it sent (on the map's cells, inflated
as the request was planned, at the cost of the path and not of the map)."""
import collections
import threading

import numpy as np
import pytest
import zmq

import offload_planner_cpp
from offload_cloud import protocol
from offload_cloud.client import CloudClient, CloudTimeout
from offload_cloud.protocol import Kind, Reply, Status

from cloud_test_helpers import LOOPBACK, MIB

pytestmark = pytest.mark.timeout(180)


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
    from offload_cloud.reply_check import reply_problem
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
