"""CloudBridge.set_planner_parameters, what the cloud bridge node calls with the local planner's reconfigured
options: the next request carries them to the cloud, a value the core's table refuses changes nothing."""
import numpy as np
import pytest

from offload_planner_cpp import PlanStatus
from offload_cloud.bridge import BridgeConfig, CloudBridge, StampedPose

from cloud_test_helpers import make_keys, start_server

pytestmark = pytest.mark.timeout(60)
RESOLUTION_M = 0.05


def point(cell) -> StampedPose:
    return StampedPose("map", (cell[0] + 0.5) * RESOLUTION_M, (cell[1] + 0.5) * RESOLUTION_M)


def test_reconfigured_options_reach_the_next_cloud_plan_and_refused_ones_change_nothing(tmp_path):
    server = start_server(make_keys(tmp_path, ["robot"]), workers=1)
    bridge = CloudBridge(BridgeConfig(endpoint=server.endpoint, keys_dir=str(tmp_path / "robot")))
    grid = np.zeros((5, 9), np.int8)
    grid[:, 4] = 100   # a wall; cell (3, 2) is one cell (5 cm) from it
    try:
        bridge.set_map(grid.reshape(-1), 9, 5, RESOLUTION_M, 0.0, 0.0, (0.0, 0.0, 0.0, 1.0), "map", "stamp")
        beside_the_wall = lambda: bridge.plan(point((3, 2)), point((0, 2)), 0.0).status   # noqa: E731
        assert beside_the_wall() == PlanStatus.OK
        assert bridge.set_planner_parameters({"robot_radius": 0.06, "algorithm": "auto"}) == {"robot_radius": 0.06}
        assert beside_the_wall() == PlanStatus.START_BLOCKED, "a 6 cm radius (1.2 cells) blocks the start"

        with pytest.raises(ValueError, match=r"^robot_radius must be a finite number >= 0, got -1$"):
            bridge.set_planner_parameters({"robot_radius": -1.0})
        with pytest.raises(ValueError, match="cost_factor must be 0"):   # the core's rule between two options
            bridge.set_planner_parameters({"algorithm": "jps", "cost_factor": 2.0})
        with pytest.raises(TypeError, match="no planner node parameter goal_tolerance_cells"):
            bridge.set_planner_parameters({"goal_tolerance_cells": 1.0})
        assert bridge.config.robot_radius_m == 0.06 and bridge.config.algorithm == "auto"
        assert beside_the_wall() == PlanStatus.START_BLOCKED

        assert bridge.set_planner_parameters({"robot_radius": 0.0}) == {"robot_radius": 0.0}
        assert beside_the_wall() == PlanStatus.OK
    finally:
        bridge.close()
        server.stop()
