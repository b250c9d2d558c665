"""The robot-side bridge without ROS: local-node-identical answers, timeout and reconnect against a server
process that is killed mid-request, and the WAN emulator in between."""
import math
import signal
import threading
import time

import numpy as np
import pytest

import offload_planner_cpp
from offload_planner_cpp import PlanStatus
from offload_cloud.bridge import BridgeConfig, CloudBridge, StampedPose
from offload_cloud.client import CloudClient, CloudTimeout
from offload_demos.wan_emulator import LinkModel, WanEmulator, read_trace

from cloud_test_helpers import LOOPBACK, free_port, make_keys, random_map, spawn_server, start_server

pytestmark = pytest.mark.timeout(120)
RESOLUTION_M = 0.05
ORIGIN_M = (-1.0, 2.0)
IDENTITY = (0.0, 0.0, 0.0, 1.0)


@pytest.fixture(scope="module")
def key_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("keys")
    return make_keys(root, ["robot"]), root / "robot"


def make_bridge(endpoint, client_keys, **overrides) -> CloudBridge:
    return CloudBridge(BridgeConfig(endpoint=endpoint, keys_dir=str(client_keys), **overrides))


def give_map(bridge, grid, frame_id="map"):
    height, width = grid.shape
    return bridge.set_map(grid.reshape(-1), width, height, RESOLUTION_M, *ORIGIN_M, IDENTITY, frame_id, "stamp")


def world(cell):
    return ORIGIN_M[0] + (cell[0] + 0.5) * RESOLUTION_M, ORIGIN_M[1] + (cell[1] + 0.5) * RESOLUTION_M


def point(cell, frame_id="map") -> StampedPose:
    return StampedPose(frame_id, *world(cell))


def test_bridge_answers_like_the_local_node(key_dirs):
    """Statuses and numbers as the request contract and the core give them on the robot; the cost is
    also checked against the independent scipy oracle."""
    from scipy.sparse import csgraph
    from offload_demos.grid_graph import grid_graph
    server = start_server(key_dirs[0], workers=1)
    bridge = make_bridge(server.endpoint, key_dirs[1])
    try:
        assert bridge.plan(point((0, 0)), point((1, 1)), 0.0).status == PlanStatus.NO_MAP
        why = bridge.set_map(np.zeros(5, np.int8), 2, 2, 0.05, 0, 0, IDENTITY, "map", None)
        assert why and why in bridge.plan(point((0, 0)), point((1, 1)), 0.0).message   # NO_MAP says why
        assert bridge.set_map(np.zeros(4, np.int8), 2, 2, 0.05, 0, 0, (0.0, 0.0, math.nan, 1.0), "map", None)
        assert bridge.set_map(np.zeros(4, np.int8), 2, 2, 0.05, 0, 0, (0.0, 0.0, 0.0, 0.0), "map", None)
        assert bridge.set_map(np.zeros(4, np.uint8), 2, 2, 0.05, 0, 0, IDENTITY, "map", None)
        assert bridge.plan(point((0, 0)), point((1, 1)), 0.0).status == PlanStatus.NO_MAP

        grid = random_map(80, 60, 0.2, seed=7)
        assert give_map(bridge, grid) == ""
        start = StampedPose("map", *world((0, 0)), 0.0, (0.0, 0.0, 0.0, 0.0))   # a zero quaternion stays as given
        result = bridge.plan(start, point((79, 59)), 0.0)
        local = offload_planner_cpp.plan_raw(grid, (0, 0), (79, 59))
        assert result.status == PlanStatus.OK and result.reached_goal and result.map_stamp == "stamp"
        oracle = csgraph.dijkstra(grid_graph(grid), indices=0)[59 * 80 + 79]
        assert result.cost_m == pytest.approx(oracle * RESOLUTION_M, abs=1e-9)
        assert result.expansions == local["expansions"] and result.poses.shape == (len(local["path"]), 7)
        np.testing.assert_array_equal(result.poses[1:-1, 0], ORIGIN_M[0] + (local["path"][1:-1, 0] + 0.5) * RESOLUTION_M)
        np.testing.assert_array_equal(result.poses[1:-1, 1], ORIGIN_M[1] + (local["path"][1:-1, 1] + 0.5) * RESOLUTION_M)
        assert tuple(result.poses[0]) == start.pose() and tuple(result.poses[-1]) == point((79, 59)).pose()
        assert np.allclose(np.linalg.norm(result.poses[1:-1, 3:], axis=1), 1.0)
        assert result.link_round_trip_s > 0 and result.reachable

        assert bridge.plan(point((0, 0), "odom"), point((1, 1)), 0.0).status == PlanStatus.BAD_FRAME
        assert bridge.plan(point((0, 0)), point((1, 1), "/map"), 0.0).status == PlanStatus.OK
        assert bridge.plan(point((0, 0)), point((1, 1)), -1.0).status == PlanStatus.INVALID_REQUEST
        assert bridge.plan(StampedPose("", math.nan, 0), point((1, 1)), 0.0).status == PlanStatus.INVALID_REQUEST
        assert bridge.plan(StampedPose("map", -1.5, 2.0), point((1, 1)), 0.0).status == PlanStatus.START_OFF_MAP
        assert bridge.plan(point((0, 0)), StampedPose("map", 3.0, 100.0), 0.0).status == PlanStatus.GOAL_OFF_MAP
        assert bridge.plan(StampedPose("map", 1e308, 2.0), point((1, 1)), 0.0).status == PlanStatus.START_OFF_MAP
        assert bridge.plan(point((0, 0)), StampedPose("map", 0.0, -1e308), 0.0).status == PlanStatus.GOAL_OFF_MAP
        # The tolerance is float32 in the service: 1e308 is inf there, 3e38 m a huge but valid tolerance.
        assert bridge.plan(point((0, 0)), point((1, 1)), 1e308).status == PlanStatus.INVALID_REQUEST
        assert bridge.plan(point((0, 0)), point((1, 1)), 3e38).status == PlanStatus.OK

        walled = np.zeros((20, 20), np.int8)
        walled[10, :] = 100
        give_map(bridge, walled)
        assert bridge.plan(point((0, 0)), point((5, 19)), 0.0).status == PlanStatus.NO_PATH
        assert bridge.plan(point((0, 0)), point((5, 10)), 0.0).status == PlanStatus.GOAL_BLOCKED
        tolerant = bridge.plan(point((0, 0)), point((5, 10)), 0.06)   # 1.2 cells: (5, 9) is the nearest
        assert tolerant.status == PlanStatus.OK and not tolerant.reached_goal
        assert tuple(tolerant.poses[-1, :2]) == pytest.approx(world((5, 9)))   # not the blocked goal
        assert tolerant.cost_m == pytest.approx((4 + 5 * math.sqrt(2)) * RESOLUTION_M)
        assert bridge.plan(point((5, 10)), point((0, 0)), 0.0).status == PlanStatus.START_BLOCKED
    finally:
        bridge.close()
        server.stop()


def test_bridge_options_reach_the_cloud(key_dirs):
    """The bridge's lethal threshold and unknown-cell rule travel to the cloud planner."""
    server = start_server(key_dirs[0], workers=1)
    grid = np.zeros((5, 9), np.int8)
    grid[:, 4] = 100
    grid[2, 4] = 60    # passable only with lethal_threshold > 60
    grid[4, 4] = -1    # passable only when unknown cells are free
    bridges = {name: make_bridge(server.endpoint, key_dirs[1], **options) for name, options in {
        "default": {}, "lenient": {"lethal_threshold": 61}, "explorer": {"unknown_is_obstacle": False}}.items()}
    try:
        for bridge in bridges.values():
            give_map(bridge, grid)
        through_60 = lambda b: b.plan(point((0, 2)), point((8, 2)), 0.0)            # noqa: E731
        through_unknown = lambda b: b.plan(point((0, 4)), point((8, 4)), 0.0)      # noqa: E731
        assert through_60(bridges["default"]).status == PlanStatus.NO_PATH
        assert through_60(bridges["lenient"]).cost_m == pytest.approx(8 * RESOLUTION_M)
        assert through_unknown(bridges["default"]).status == PlanStatus.NO_PATH
        assert through_unknown(bridges["explorer"]).cost_m == pytest.approx(8 * RESOLUTION_M)
    finally:
        for bridge in bridges.values():
            bridge.close()
        server.stop()


def test_bridge_converts_its_metres_to_cells_as_the_local_node(key_dirs):
    """Radii in metres become cells at the map's resolution by the core's conversion: a cell one cell (5 cm)
    from a wall is inside a 6 cm robot radius (1.2 cells) and outside 4 cm, as for the local planner node."""
    server = start_server(key_dirs[0], workers=1)
    grid = np.zeros((5, 9), np.int8)
    grid[:, 4] = 100
    bridges = {radius: make_bridge(server.endpoint, key_dirs[1], robot_radius_m=radius) for radius in (0.06, 0.04)}
    try:
        for bridge in bridges.values():
            give_map(bridge, grid)
        assert bridges[0.06].plan(point((3, 2)), point((0, 2)), 0.0).status == PlanStatus.START_BLOCKED
        assert bridges[0.04].plan(point((3, 2)), point((0, 2)), 0.0).status == PlanStatus.OK
    finally:
        for bridge in bridges.values():
            bridge.close()
        server.stop()


def test_bridge_config_defaults_and_names_are_the_cores():
    config = BridgeConfig(endpoint="tcp://127.0.0.1:9")
    parameters = config.planner_parameters()
    assert parameters == {row["name"]: row["default"] for row in offload_planner_cpp.options_table()
                          if row["node_parameter"]}
    changed = dict(parameters, robot_radius=0.3, algorithm="astar")
    assert BridgeConfig(endpoint="x", **BridgeConfig.planner_fields(changed)).planner_parameters() == changed


def test_killed_server_gives_timeout_in_time_then_reconnects(key_dirs):
    port = free_port()
    endpoint = f"{LOOPBACK}:{port}"
    process = spawn_server(port, key_dirs[0])
    timeout_s = 2.0
    # Dijkstra's waves: a plan long enough to be killed in the middle (jump points cross open ground at once)
    bridge = make_bridge(endpoint, key_dirs[1], timeout_s=timeout_s, retries=1, algorithm="dijkstra")
    try:
        grid = np.zeros((2500, 2500), np.int8)
        give_map(bridge, grid)
        assert bridge.heartbeat()[0]              # starts the map upload
        bridge.wait_for_upload()
        assert bridge.plan(point((0, 0)), point((5, 5)), 0.0).status == PlanStatus.OK
        answers = []

        def ask():
            started = time.monotonic()
            answers.append((bridge.plan(point((0, 0)), point((2499, 2499)), 0.0), time.monotonic() - started))

        asking = threading.Thread(target=ask)
        asking.start()
        time.sleep(0.05)
        process.send_signal(signal.SIGKILL)
        process.wait(10)
        asking.join(30)
        result, elapsed_s = answers[0]
        assert result.status == PlanStatus.CLOUD_TIMEOUT and not result.reachable
        assert "did not answer within 2 s" in result.message
        assert elapsed_s < timeout_s + 1.0
        assert bridge.heartbeat() == (False, 1.0)

        process = spawn_server(port, key_dirs[0])   # restarted, with an empty cache
        result = bridge.plan(point((0, 0)), point((2499, 2499)), 0.0)
        assert result.status == PlanStatus.OK, result.message
        assert bridge.heartbeat()[0]
    finally:
        bridge.close()
        process.kill()
        process.wait(10)


def test_heartbeat_measures_the_link_when_the_map_is_too_large_for_the_server(key_dirs, caplog):
    """A map over the server's max message size: libzmq drops the connection and never answers the upload.
    The heartbeat must still report a reachable cloud with a measured round trip, and retry the upload
    with backoff, not at every heartbeat."""
    server = start_server(key_dirs[0], workers=1, max_message_bytes=1 << 20)
    bridge = make_bridge(server.endpoint, key_dirs[1], timeout_s=0.5, heartbeat_timeout_s=1.0)
    try:
        assert give_map(bridge, np.zeros((1100, 1000), np.int8)) == ""   # 1.1 MB > 1 MiB
        beats = []
        with caplog.at_level("WARNING"):
            for _ in range(20):   # 3 s of 0.15 s heartbeats
                beats.append(bridge.heartbeat())
                time.sleep(0.15)
            bridge.wait_for_upload()
        assert all(reachable for reachable, _ in beats), beats
        assert all(0 < round_trip_s < 0.5 for _, round_trip_s in beats), beats
        # Attempts at about 0 s, then after each 0.5 s timeout + 0.15, 0.3, 0.6 s of backoff: 4 or so, not 20.
        assert 2 <= bridge.upload_attempts <= 5, bridge.upload_attempts
        warnings = [r.getMessage() for r in caplog.records if "upload of map" in r.getMessage()]
        assert len(warnings) == 1 and "(1100000 bytes)" in warnings[0] and "max-message-mib" in warnings[0]
        assert server.cache.misses == 0 and len(server.cache) == 0
        # A map that fits is uploaded at the next heartbeat and then never again.
        give_map(bridge, random_map(100, 100, 0.1, seed=9))
        attempts = bridge.upload_attempts
        for _ in range(5):
            assert bridge.heartbeat()[0]
            bridge.wait_for_upload()
        assert bridge.upload_attempts == attempts + 1 and len(server.cache) == 1
        assert bridge.plan(point((0, 0)), point((99, 99)), 0.0).status == PlanStatus.OK
    finally:
        bridge.close()
        server.stop()


def test_heartbeat_reports_a_non_pong_answer_as_reachable_with_its_round_trip(key_dirs, monkeypatch):
    from offload_cloud.protocol import Reply, Status
    server = start_server(key_dirs[0], workers=1)
    bridge = make_bridge(server.endpoint, key_dirs[1], heartbeat_timeout_s=1.0)
    try:
        client = bridge._heartbeat_client
        real = client.ping_reply

        def busy_pong(timeout_s=None):
            reply, round_trip_s = real(timeout_s)
            return Reply(reply.request_id, Status.BUSY, "busy"), round_trip_s

        monkeypatch.setattr(client, "ping_reply", busy_pong)
        reachable, round_trip_s = bridge.heartbeat()
        assert reachable and 0 < round_trip_s < 0.5   # measured, not the 1 s timeout
    finally:
        bridge.close()
        server.stop()


def test_client_timeout_is_fast_when_nothing_listens():
    with CloudClient(f"{LOOPBACK}:{free_port()}", insecure=True, timeout_s=0.5, retries=2) as client:
        started = time.monotonic()
        with pytest.raises(CloudTimeout):
            client.ping()
        assert time.monotonic() - started < 0.5 + 1.0


def test_wan_emulator_adds_delay_and_stalls(key_dirs):
    server = start_server(key_dirs[0], workers=1)
    link = LinkModel(rtt_s=0.08, jitter_s=0.01, bandwidth_bps=50e6, outages=[(1.5, 1.0)], seed=1)
    emulator = WanEmulator(f"{LOOPBACK}:0", server.endpoint, link)
    endpoint = emulator.start()
    try:
        with CloudClient(endpoint, keys_dir=str(key_dirs[1]), timeout_s=5.0, retries=0) as client:
            client.ping()   # connects (the CURVE handshake crosses the link too)
            round_trips = [client.ping() for _ in range(3)]
            assert min(round_trips) >= 0.08 - 0.01
            outcome = client.plan(random_map(200, 200, 0.1, seed=8), (0, 0), (199, 199))
            assert outcome.reply.status == 0
            while emulator._now() < 1.6:
                time.sleep(0.05)
            with pytest.raises(CloudTimeout):   # stalled for the rest of the outage
                client.ping(timeout_s=0.3)
            assert client.ping() > 0          # the link comes back and so does the client
    finally:
        emulator.stop()
        server.stop()


def test_link_model_trace_and_outages(tmp_path):
    trace_file = tmp_path / "rtt.txt"
    trace_file.write_text("# time_s rtt_ms\n0 20\n1.5, 100\n3 40\n")
    link = LinkModel(trace=read_trace(str(trace_file)), loop_trace=True, outages=[(10, 2)])
    assert [link.round_trip_s(t) for t in (0.5, 2.0, 2.9, 3.5)] == [0.02, 0.1, 0.1, 0.02]
    assert link.outage_end(11.0) == 12 and link.outage_end(12.0) is None
    assert LinkModel(rtt_s=0.05).one_way_s(0.0) == 0.025
    bad = tmp_path / "bad.txt"
    bad.write_text("zero twenty\n")
    with pytest.raises(ValueError):
        read_trace(str(bad))


def test_link_bytes_are_counted_per_request(key_dirs):
    """What a request cost the link: an upload carries the grid, a plan on a cached map only the
    request, and the reply carries the path."""
    server = start_server(key_dirs[0], workers=1)
    bridge = make_bridge(server.endpoint, key_dirs[1])
    client = CloudClient(server.endpoint, keys_dir=str(key_dirs[1]))
    try:
        grid = random_map(200, 150, 0.1, seed=3)
        client.upload(grid)
        assert client.bytes_sent >= grid.nbytes and client.bytes_received > 0
        assert give_map(bridge, grid) == ""
        first = bridge.plan(point((0, 0)), point((199, 149)), 0.0)
        assert first.status == PlanStatus.OK and first.bytes_sent >= grid.nbytes   # no heartbeat yet: it carries the map
        result = bridge.plan(point((0, 0)), point((199, 149)), 0.0)
        assert result.status == PlanStatus.OK
        assert 0 < result.bytes_sent < 1024              # the map is cached: start, goal and hash only
        assert result.bytes_received >= 8 * len(result.poses)   # the path's cells came back
        refused = bridge.plan(point((0, 0)), point((5, 5)), -1.0)
        assert refused.bytes_sent == refused.bytes_received == 0   # refused on the robot: the link is untouched
    finally:
        client.close()
        bridge.close()
        server.stop()
