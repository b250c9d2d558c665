"""The client's reply check (client.reply_problem) branch by branch, on the arrays decode_reply hands it: each lie
is named, each truth passes, and the cost it recomputes is the path's octile or Euclidean length."""
import math

import numpy as np
import pytest

from offload_cloud.client import reply_problem
from offload_cloud.protocol import PlanOptions, Reply, Status

GRID = np.zeros((6, 8), np.int8)          # 8 wide, 6 high
ANY_ANGLE = PlanOptions(any_angle=True)


def check(path, goal=None, cost=None, options=PlanOptions(), start=None):
    path = np.asarray(path, np.int32).reshape(-1, 2)
    start = tuple(path[0]) if start is None else start
    goal = tuple(path[-1]) if goal is None else goal
    if cost is None:
        steps = np.abs(np.diff(path.astype(float), axis=0))
        cost = float(np.hypot(steps[:, 0], steps[:, 1]).sum())
    return reply_problem(Reply(1, Status.OK, "", path, goal, 5, 0.0, cost), GRID, start, goal, options, 1.0)


@pytest.mark.parametrize("path, options", [
    ([(0, 0)], PlanOptions()),                                        # start is the goal
    ([(0, 0), (1, 1), (2, 1), (3, 2), (3, 3)], PlanOptions()),         # straight and diagonal steps
    ([(7, 5), (6, 4), (6, 3)], PlanOptions()),                         # the far corner of the map
    ([(0, 0), (3, 1), (7, 5)], ANY_ANGLE),
])
def test_true_paths_pass(path, options):
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
def test_each_lie_is_named(path, options, goal, start, expected):
    assert expected in check(path, goal=goal, start=start, options=options)


def test_the_cost_must_be_the_paths_length():
    path = [(0, 0), (1, 1), (2, 1), (3, 2)]                            # 2 diagonal steps and 1 straight one
    assert check(path, cost=1 + 2 * math.sqrt(2)) == ""
    assert "cost" in check(path, cost=3.0)                            # as if every step were straight
    assert "cost" in check(path, cost=3 * math.sqrt(2))               # as if every step were diagonal
    assert check([(0, 0), (3, 1)], options=ANY_ANGLE, cost=math.sqrt(10)) == ""
    assert "cost" in check([(0, 0), (3, 1)], options=ANY_ANGLE, cost=4.0)
