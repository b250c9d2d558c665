"""The client's reply check (reply_check.reply_problem) branch by branch, on the arrays decode_reply hands it: each lie
is named, each truth passes, and the cost it recomputes is the path's octile or Euclidean length. Every case runs
both ways the check calls the core: check_path alone, and check_path_rows writing the path's poses (the bridge's)."""
import math

import numpy as np
import pytest

from offload_cloud.reply_check import PathRows, reply_problem
from offload_cloud.protocol import PlanOptions, Reply, Status
from offload_planner_cpp._core import check_map, path_poses

GRID = np.zeros((6, 8), np.int8)          # 8 wide, 6 high
GEOMETRY = check_map(8, 6, 48, 0.05, 1.0, 2.0, (0.0, 0.0, 0.0, 1.0))[1]
ANY_ANGLE = PlanOptions(any_angle=True)
START_POSE, GOAL_POSE = (1.01, 2.02, 0.0, 0.0, 0.0, 0.0, 1.0), (1.3, 2.2, 0.0, 0.0, 0.0, 0.6, 0.8)


def path_rows() -> PathRows:
    return PathRows(GEOMETRY, START_POSE, GOAL_POSE, "map", lambda frame_id: frame_id.encode() + b"|")


@pytest.fixture(params=[False, True], ids=["check_path", "check_path_rows"])
def check(request):
    def check(path, goal=None, cost=None, options=PlanOptions(), start=None):
        path = np.asarray(path, np.int32).reshape(-1, 2)
        start = tuple(path[0]) if start is None else start
        goal = tuple(path[-1]) if goal is None else goal
        if cost is None:
            steps = np.abs(np.diff(path.astype(float), axis=0))
            cost = float(np.hypot(steps[:, 0], steps[:, 1]).sum())
        rows = path_rows() if request.param else None
        why = reply_problem(Reply(1, Status.OK, "", path, goal, 5, 0.0, cost), GRID, start, goal, options, 1.0, rows)
        if rows is not None and why == "":   # a true path's poses, as path_poses writes them for the same request
            assert rows.prefix == b"map|" and rows.rows == path_poses(GEOMETRY, path, START_POSE, GOAL_POSE, True,
                                                                       b"map|")
        return why
    return check


@pytest.mark.parametrize("path, options", [
    ([(0, 0)], PlanOptions()),                                        # start is the goal
    ([(0, 0), (1, 1), (2, 1), (3, 2), (3, 3)], PlanOptions()),         # straight and diagonal steps
    ([(7, 5), (6, 4), (6, 3)], PlanOptions()),                         # the far corner of the map
    ([(0, 0), (3, 1), (7, 5)], ANY_ANGLE),
])
def test_true_paths_pass(path, options, check):
    assert check(path, options=options) == ""


@pytest.mark.parametrize("path, options, goal, start, expected", [
    ([(0, 0), (8, 0)], ANY_ANGLE, None, None, "leaves the map"),       # x = width
    ([(0, 0), (0, 6)], ANY_ANGLE, None, None, "leaves the map"),       # y = height
    ([(0, 0), (0, -1)], PlanOptions(), None, None, "leaves the map"),
    ([(0, 0), (1, 1)], PlanOptions(), None, (1, 0), "starts at"),
    ([(0, 0), (1, 1)], PlanOptions(), (2, 2), None, "ends at"),
    ([(0, 0), (1, 1), (1, 1), (2, 2)], PlanOptions(), None, None, "8-connected"),   # a step of no length
    ([(0, 0), (2, 1)], PlanOptions(), None, None, "8-connected"),                   # a knight's move
    ([(0, 0), (3, 1), (3, 1), (7, 5)], ANY_ANGLE, None, None, "repeats a corner"),
])
def test_each_lie_is_named(path, options, goal, start, expected, check):
    assert expected in check(path, goal=goal, start=start, options=options)


def test_the_cost_must_be_the_paths_length(check):
    path = [(0, 0), (1, 1), (2, 1), (3, 2)]                            # 2 diagonal steps and 1 straight one
    assert check(path, cost=1 + 2 * math.sqrt(2)) == ""
    assert "cost" in check(path, cost=3.0)                            # as if every step were straight
    assert "cost" in check(path, cost=3 * math.sqrt(2))               # as if every step were diagonal
    assert check([(0, 0), (3, 1)], options=ANY_ANGLE, cost=math.sqrt(10)) == ""
    assert "cost" in check([(0, 0), (3, 1)], options=ANY_ANGLE, cost=4.0)


def test_no_rows_for_a_path_through_a_wall():
    grid = GRID.copy()
    grid[1, 1] = 100
    path = np.array([(0, 0), (1, 1), (2, 2)], np.int32)
    rows = path_rows()
    why = reply_problem(Reply(1, Status.OK, "", path, (2, 2), 5, 0.0, 2 * math.sqrt(2)), grid, (0, 0), (2, 2),
                        PlanOptions(), 1.0, rows)
    assert "crosses an obstacle" in why and rows.rows == b""


def test_the_rows_end_at_the_goal_pose_only_when_the_requested_goal_was_reached():
    path = np.array([(0, 0), (1, 0), (2, 0)], np.int32)
    for requested, reached in (((2, 0), True), ((3, 0), False)):   # (3, 0): reached within the tolerance
        rows = path_rows()
        assert reply_problem(Reply(1, Status.OK, "", path, (2, 0), 5, 0.0, 2.0), GRID, (0, 0), requested,
                             PlanOptions(goal_tolerance_cells=1.5), 1.0, rows) == ""
        assert rows.rows == path_poses(GEOMETRY, path, START_POSE, GOAL_POSE, reached, b"map|")
