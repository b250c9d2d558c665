"""A request refused for its input is not a decision: before routing, the learner checks it with the
planners' own request contract (the C++ core, through its binding) against the map's metadata, so a
non-finite pose, a pose off the map or a negative tolerance gets the planner's status without either
planner being called, and teaches nothing. Blocked and unreachable goals need the grid and are left to the
planners. Frames are left to the planners too: the learner does not see the map's frame."""
from dataclasses import dataclass
from typing import Optional, Sequence

from offload_planner_cpp import PlanStatus
from offload_planner_cpp._core import check_map, resolve_request

MAX_MESSAGE_CHARS = 200   # a hostile frame id must not flood logs and bags


@dataclass(frozen=True)
class Rejection:
    status: int
    message: str


def check_request(width: int, height: int, resolution: float, origin_xy: Sequence[float],
                  orientation: Sequence[float], start_frame: str, start_xy: Sequence[float], goal_frame: str,
                  goal_xy: Sequence[float], tolerance_m: float) -> Optional[Rejection]:
    """The planners' verdict on the request's input, or None when they would plan it (or the map metadata is
    itself unusable, which the planners report)."""
    checked, geometry = check_map(int(width), int(height), int(width) * int(height), float(resolution),
                                  float(origin_xy[0]), float(origin_xy[1]), [float(q) for q in orientation])
    if geometry is None:
        return None
    # The start's frame stands for the map frame: the goal must be in the same one (or empty, as RViz leaves it).
    outcome = resolve_request(geometry, start_frame, start_frame, float(start_xy[0]), float(start_xy[1]),
                              goal_frame, float(goal_xy[0]), float(goal_xy[1]), float(tolerance_m))[0]
    if outcome is None:
        return None
    if int(outcome.status) == int(PlanStatus.BAD_FRAME):
        return None   # the map's own frame decides: left to the planners
    return Rejection(int(outcome.status), outcome.message[:MAX_MESSAGE_CHARS])
