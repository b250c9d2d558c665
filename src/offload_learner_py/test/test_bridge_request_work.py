"""What the cloud bridge does for one cloud plan (#30's bar: at most 0.5 ms of the robot's CPU per cloud request on a
4 M-cell map). Live, most of that CPU is the cold cache met by every call the request makes, so the work is held
here by its count, not by a timer: the Python and C calls of the service thread from the request to the PlanPath
response (CloudBridge.plan, then the node's plan_response), counted by sys.setprofile, and none of them growing
with the map or the path."""
import sys
from collections import Counter
from io import BytesIO

import numpy as np
import pytest
from genpy import Time
from nav_msgs.msg import Path
from offload_msgs.srv import PlanPathResponse

from offload_cloud.bridge import BridgeConfig, BridgeResult, CloudBridge, StampedPose
from offload_learner_py.nodes.cloud_bridge import plan_response
from offload_learner_py.nodes.path_wire import WirePath, WirePlanPathResponse, pose_count, pose_row_prefix
from offload_planner_cpp import PlanStatus

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[2] / "offload_cloud" / "test"))
from cloud_test_helpers import make_keys, start_server  # noqa: E402

pytestmark = pytest.mark.timeout(120)
RESOLUTION_M = 0.05
# Calls of one cloud plan on a cached map as the node makes it (its row prefix and the test's lambda included): 197
# before the cuts of #30's bridge bar (a dozen numpy passes in the reply check and as many writing the path, IntEnum
# look-ups, the options encoded per request, genpy's default messages), 123 after; 106 once the request's cells come
# back from the core as a tuple, the reply is decoded from its Frames and the path's header is set slot by slot.
MAX_CALLS = 110


def poses(count: int) -> np.ndarray:
    rows = np.zeros((count, 7))
    rows[:, 0], rows[:, 6] = np.arange(count) * RESOLUTION_M, 1.0
    return rows


def test_plan_response_carries_the_path_and_every_field():
    result = BridgeResult(PlanStatus.OK, "ok", poses(5), True, 0.002, 17, 0.2, Time(3, 4), "map", 0.01, True, 90, 80)
    res = plan_response(result, Time(5, 6))
    assert isinstance(res.path, WirePath) and pose_count(res.path) == 5
    assert (res.status, res.message, res.planning_time_s, res.expansions, res.cost_m, res.map_stamp, res.bytes_sent,
            res.bytes_received) == (PlanPathResponse.OK, "ok", 0.002, 17, 0.2, Time(3, 4), 90, 80)
    assert res.path.header.frame_id == "map" and res.path.header.stamp == Time(5, 6)
    back = WirePlanPathResponse().deserialize(serialized(res))
    assert [p.pose.position.x for p in back.path.poses] == pytest.approx(list(poses(5)[:, 0]))
    assert all(p.header.frame_id == "map" and p.header.stamp == Time(5, 6) for p in back.path.poses)

    failed = plan_response(BridgeResult(PlanStatus.CLOUD_TIMEOUT, "late"), Time(5, 6))
    assert failed.status == PlanPathResponse.CLOUD_TIMEOUT and failed.message == "late"
    assert type(failed.path) is Path and failed.path.poses == [] and failed.map_stamp == Time()


def serialized(message) -> bytes:
    buffer = BytesIO()
    message.serialize(buffer)
    return buffer.getvalue()


def count_calls(call) -> Counter:
    counted = Counter()

    def profile(frame, event, arg):
        if event == "call":
            counted[f"{frame.f_code.co_filename.rsplit('/', 1)[-1]}:{frame.f_code.co_name}"] += 1
        elif event == "c_call":
            counted[f"C {getattr(arg, '__qualname__', arg)}"] += 1

    sys.setprofile(profile)
    try:
        call()
    finally:
        sys.setprofile(None)
    return counted


@pytest.mark.parametrize("side, length", [(64, 40), (1024, 1000)])
def test_a_cloud_plan_makes_a_bounded_count_of_calls(tmp_path, side, length):
    server_keys = make_keys(tmp_path, ["robot"])
    server = start_server(server_keys, workers=1)
    bridge = CloudBridge(BridgeConfig(endpoint=server.endpoint, keys_dir=str(tmp_path / "robot")))
    try:
        grid = np.full((side, side), 100, np.int8)
        grid[side // 2, 4:4 + length] = 0   # a corridor: a path of `length` cells
        assert bridge.set_map(grid.reshape(-1), side, side, RESOLUTION_M, 0.0, 0.0, (0, 0, 0, 1), "map", None) == ""
        start, goal = (StampedPose("map", (x + 0.5) * RESOLUTION_M, (side // 2 + 0.5) * RESOLUTION_M)
                       for x in (4, 3 + length))

        answers = []

        def prefix(frame_id):   # the node's row_prefix_now, without a ROS clock
            return pose_row_prefix(Time(1, 0), frame_id)

        for _ in range(3):   # the map's upload, then the request as it repeats
            answers.append(plan_response(bridge.plan(start, goal, 0.0, prefix)))
        calls = count_calls(lambda: answers.append(plan_response(bridge.plan(start, goal, 0.0, prefix))))
        assert all(res.status == PlanPathResponse.OK and pose_count(res.path) == length for res in answers)
        assert answers[-1].path.header.frame_id == "map" and answers[-1].path.header.stamp == Time(1, 0)
        as_poses = plan_response(bridge.plan(start, goal, 0.0), Time(1, 0))   # the same path the other way
        assert serialized(as_poses.path) == serialized(answers[-1].path)
    finally:
        bridge.close()
        server.stop()
    total = sum(calls.values())
    assert total <= MAX_CALLS, f"{total} calls per cloud plan: {calls.most_common()}"
    assert not [name for name in calls if name.startswith("enum.py")], calls   # no IntEnum call on the way
    # the reply check and the path's poses in one call into the core (each costs tens of microseconds cold)
    assert calls["C PyCapsule.check_path_rows"] == 1 and calls["reply_check.py:reply_problem"] == 1
    assert calls["C PyCapsule.check_path"] == 0 and calls["C PyCapsule.path_poses"] == 0
    # the options of a repeated request are encoded once, not per request
    assert calls["plan_options.py:encode_options"] == 0
