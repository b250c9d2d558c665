"""The heartbeat rests while plans measure the link (#30: what the robot pays per request). A cloud answer to a plan
stands for a ping for one heartbeat period; never when the cloud lacks the current map (the ping uploads it), and
never once the answers stop."""
import time

import pytest

from offload_planner_cpp import PlanStatus
from offload_cloud.bridge import BridgeConfig, CloudBridge, StampedPose

from cloud_test_helpers import random_map, start_server

pytestmark = pytest.mark.timeout(120)
RESOLUTION_M = 0.05


def point(cell) -> StampedPose:
    return StampedPose("map", (cell[0] + 0.5) * RESOLUTION_M, (cell[1] + 0.5) * RESOLUTION_M)


def give_map(bridge, grid):
    height, width = grid.shape
    assert bridge.set_map(grid.reshape(-1), width, height, RESOLUTION_M, 0.0, 0.0, (0.0, 0.0, 0.0, 1.0), "map",
                          "stamp") == ""


def test_a_plans_answer_stands_for_the_ping_for_one_period_and_only_on_a_map_the_cloud_has():
    server = start_server(workers=1)
    bridge = CloudBridge(BridgeConfig(endpoint=server.endpoint, insecure=True, timeout_s=1.0, retries=0))
    try:
        give_map(bridge, random_map(80, 60, 0.1, seed=3))
        assert bridge.recent_round_trip(10.0) is None           # nothing measured yet: ping
        result = bridge.plan(point((0, 0)), point((79, 59)), 0.0)
        assert result.status == PlanStatus.OK, result.message
        assert bridge.recent_round_trip(10.0) == result.link_round_trip_s   # the plan's own measurement
        time.sleep(0.3)
        assert bridge.recent_round_trip(0.2) is None            # older than the period: ping
        assert bridge.recent_round_trip(10.0) == result.link_round_trip_s

        give_map(bridge, random_map(80, 60, 0.1, seed=4))      # a new map the cloud has not acknowledged
        assert bridge.recent_round_trip(10.0) is None           # the ping uploads it
        assert bridge.heartbeat()[0]
        bridge.wait_for_upload()
        assert bridge.recent_round_trip(10.0) == result.link_round_trip_s

        server.stop()                                           # plans that time out measure nothing
        assert bridge.plan(point((0, 0)), point((79, 59)), 0.0).status == PlanStatus.CLOUD_TIMEOUT
        assert bridge.recent_round_trip(10.0) == result.link_round_trip_s
        assert bridge.recent_round_trip(0.5) is None
    finally:
        bridge.close()
        server.stop()
