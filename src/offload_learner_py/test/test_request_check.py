"""A request refused for its input, by the planners' own contract: the learner answers it without calling
either planner, and it is never a decision."""
import math

import pytest

from offload_planner_cpp import PlanStatus
from offload_learner_py.online.request_check import MAX_MESSAGE_CHARS, check_request

MAP = dict(width=100, height=80, resolution=0.05, origin_xy=(-1.0, 2.0), orientation=(0.0, 0.0, 0.0, 1.0))


def check(start, goal, tolerance=0.0, start_frame="map", goal_frame="map"):
    return check_request(**MAP, start_frame=start_frame, start_xy=start, goal_frame=goal_frame, goal_xy=goal,
                         tolerance_m=tolerance)


def test_a_request_the_planners_would_plan_is_not_refused():
    assert check((0.0, 3.0), (3.0, 5.0)) is None
    assert check((0.0, 3.0), (3.0, 5.0), goal_frame="") is None    # RViz leaves the frame empty


@pytest.mark.parametrize("start, goal, tolerance, status", [
    ((math.nan, 3.0), (3.0, 5.0), 0.0, PlanStatus.INVALID_REQUEST),
    ((0.0, 3.0), (3.0, math.inf), 0.0, PlanStatus.INVALID_REQUEST),
    ((0.0, 3.0), (3.0, 5.0), -1.0, PlanStatus.INVALID_REQUEST),
    ((-5.0, 3.0), (3.0, 5.0), 0.0, PlanStatus.START_OFF_MAP),
    ((0.0, 3.0), (1e15, 5.0), 0.0, PlanStatus.GOAL_OFF_MAP),     # not an input size of 1e27
])
def test_input_the_planners_refuse_is_refused_with_their_status(start, goal, tolerance, status):
    refused = check(start, goal, tolerance)
    assert refused is not None and refused.status == int(status) and refused.message


def test_frames_are_left_to_the_planners_and_messages_are_bounded():
    assert check((0.0, 3.0), (3.0, 5.0), goal_frame="odom") is None   # the learner does not know the map's frame
    refused = check((0.0, 3.0), (1e15, 5.0), start_frame="m" * 4_000_000, goal_frame="")
    assert refused is not None and len(refused.message) <= MAX_MESSAGE_CHARS
