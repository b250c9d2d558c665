"""Dijkstra path planner on OccupancyGrid-convention grids, the same C++ core as the ROS planner node.

    >>> import numpy, offload_planner_cpp
    >>> grid = numpy.zeros((10, 10), numpy.int8)      # indexed [y, x]; -1 unknown, 0..100 occupancy
    >>> result = offload_planner_cpp.plan(grid, (0, 0), (9, 9))
    >>> result.path[-1].tolist(), round(result.cost, 4)
    ([9, 9], 12.7279)
"""
from dataclasses import dataclass
from typing import Tuple

import numpy as np

from offload_planner_cpp._core import (ALGORITHM_NAMES, PlanStatus, check_path, check_path_rows, free_cells,
                                      inflate, options_in_cells, options_table, path_clear, plan_raw,
                                      validate_options)

__all__ = ["plan", "PlanResult", "PlanError", "NoPathError", "PlanStatus", "free_cells", "inflate", "path_clear",
           "check_path", "check_path_rows", "plan_raw", "ALGORITHM_NAMES", "options_table", "validate_options",
           "options_in_cells", "OPTION_DEFAULTS"]

# The core's defaults by option name (planner_options.h), for keyword defaults that must not be typed twice.
OPTION_DEFAULTS = {row["name"]: row["default"] for row in options_table()}
_D = OPTION_DEFAULTS


class PlanError(ValueError):
    """A request the planner cannot serve: invalid map, start or goal off the map or blocked, bad options.

    `status` is the PlanStatus: INVALID_MAP, START_OFF_MAP, GOAL_OFF_MAP, START_BLOCKED, GOAL_BLOCKED or
    INVALID_REQUEST."""

    def __init__(self, status: PlanStatus, message: str):
        super().__init__(f"{status.name}: {message}")
        self.status = status


class NoPathError(RuntimeError):
    """The goal (and every free cell within the tolerance) is unreachable from the start."""

    status = PlanStatus.NO_PATH


@dataclass(frozen=True)
class PlanResult:
    path: np.ndarray          # N x 2 int32 cells (x, y), start to goal inclusive
    cost: float               # path length in cells (1 straight, sqrt(2) diagonal; any-angle: Euclidean)
    weighted_cost: float      # cost in the model planned with; equals cost when cost_factor is 0
    goal: Tuple[int, int]     # the cell reached: the goal, or the nearest reachable one within tolerance
    expansions: int           # cells settled
    seconds: float            # time inside the C++ planner
    grid_address: int         # address of the buffer planned on: the caller's own array, never a copy


def plan(grid, start, goal, *, lethal_threshold=_D["lethal_threshold"], unknown_is_obstacle=_D["unknown_is_obstacle"],
         goal_tolerance=_D["goal_tolerance_cells"], stop_at_goal=_D["stop_at_goal"], algorithm=_D["algorithm"],
         any_angle=_D["any_angle"], cost_factor=_D["cost_factor"], neutral_cost=_D["neutral_cost"],
         inflation_radius_cells=_D["inflation_radius_cells"], robot_radius_cells=_D["robot_radius_cells"],
         inflation_decay=_D["inflation_decay"]) -> PlanResult:
    """Shortest 8-connected path on `grid` (2-D int8 array [y, x], read in place) from `start` to `goal`,
    both (x, y) cells. `goal_tolerance` is in cells. Raises PlanError (a ValueError) on bad input and
    NoPathError when the goal is unreachable.

    `algorithm` "auto" (the default): jump points or the two waves, picked per plan; "dijkstra", "astar",
    "jps" force one; every one returns the same costs. `cost_factor` > 0: a move costs its length times
    the mean of neutral_cost + cost_factor * occupancy over its two cells (global_planner's model).
    `robot_radius_cells` / `inflation_radius_cells`: inflate a raw map first (see `inflate`). `any_angle`:
    the corners of the optimal path pulled tight along lines of sight, never costlier. Defaults, bounds and
    meanings: options_table()."""
    raw = plan_raw(grid, start, goal, lethal_threshold=lethal_threshold,
                   unknown_is_obstacle=unknown_is_obstacle, goal_tolerance=goal_tolerance,
                   stop_at_goal=stop_at_goal, algorithm=algorithm, any_angle=any_angle, cost_factor=cost_factor,
                   neutral_cost=neutral_cost, inflation_radius_cells=inflation_radius_cells,
                   robot_radius_cells=robot_radius_cells, inflation_decay=inflation_decay)
    status = raw["status"]
    if status == PlanStatus.NO_PATH:
        raise NoPathError(raw["message"])
    if status != PlanStatus.OK:
        raise PlanError(status, raw["message"])
    return PlanResult(path=raw["path"], cost=raw["cost"], weighted_cost=raw["weighted_cost"], goal=raw["goal"],
                      expansions=raw["expansions"],
                      seconds=raw["seconds"], grid_address=raw["grid_address"])
