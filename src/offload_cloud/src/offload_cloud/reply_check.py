"""Why a plan reply cannot be true for the map and request a client sent: the cloud client's check of every answer
(client.CloudClient.plan), so a confused or hostile server never hands the robot a path through a wall."""
import math
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence, Tuple

import numpy as np

from offload_planner_cpp import check_path, check_path_rows
from offload_cloud.protocol import PlanOptions, Reply, Status


@dataclass
class PathRows:
    """Asks plan() for a good path's poses as path_poses' rows, written by the reply check's own call into the core
    (check_path_rows): one trip through pybind11 instead of two, on the cold cache a robot's bridge meets per plan."""
    geometry: Any                       # the map's MapGeometry
    start_pose: Tuple[float, ...]       # x, y, z, qx, qy, qz, qw of the request's start and goal
    goal_pose: Tuple[float, ...]
    frame_id: str
    row_prefix: Callable[[str], bytes]  # frame id -> each row's prefix, called once the reply is back
    prefix: bytes = b""                 # then filled by the check: the prefix it wrote
    rows: bytes = b""                   # and the rows (b"" when the path has a problem)


def reply_problem(reply: Reply, grid: np.ndarray, start: Sequence[int], goal: Sequence[int], options: PlanOptions,
                  round_trip_s: float, rows: Optional[PathRows] = None) -> str:
    """Why a plan reply cannot be true for the map and request this client sent (`grid`: the grid planned on,
    inflated when the options inflate; see PlannedGrids), or "" when it can: the
    path must run from the start to the reached goal (within the tolerance of the goal) through
    traversable cells in 8-connected steps without cutting corners (any-angle: segments that cross no
    blocked cell or corner, by the core's own rule), and its cost must be its length."""
    if not (math.isfinite(reply.planning_time_s) and 0.0 <= reply.planning_time_s <= round_trip_s):
        return f"planning time {reply.planning_time_s!r} s is not within the measured round trip"
    if reply.expansions > 8 * grid.size + 8:
        return f"{reply.expansions} expansions on a map of {grid.size} cells"
    path = reply.path
    if reply.status != Status.OK:
        return "" if len(path) == 0 else f"{reply.status.name} with a path of {len(path)} cells"
    if not 1 <= len(path) <= grid.size:
        return f"path of {len(path)} cells on a map of {grid.size} cells"
    if math.hypot(reply.goal[0] - goal[0], reply.goal[1] - goal[1]) > options.goal_tolerance_cells + 1e-9:
        why = f"reached goal {reply.goal} is farther than the tolerance from the goal {tuple(goal)}"
    else:
        why = ""
    # The rest in one pass over the path's cells in C++ (the planner's own rule for blocked cells and corners):
    # O(path), never a pass over the map (a free-cell mask of a 4 M-cell map cost the robot 8 ms per cloud plan),
    # and one call rather than a dozen numpy passes (0.1-0.2 ms of the bridge's CPU per cloud plan, live).
    checked = (grid, path, (int(start[0]), int(start[1])), reply.goal, options.any_angle, options.lethal_threshold,
               options.unknown_is_obstacle)
    if rows is None:
        problem, segment, length = check_path(*checked)
    else:
        rows.prefix = rows.row_prefix(rows.frame_id)
        problem, segment, length, rows.rows = check_path_rows(
            *checked, rows.geometry, rows.start_pose, rows.goal_pose, tuple(reply.goal) == tuple(goal), rows.prefix)
    if problem == "leaves_map":
        return "path leaves the map"
    if problem == "wrong_start":
        first = path[0].tolist()
        return f"path starts at ({first[0]}, {first[1]}), not at the start {tuple(start)}"
    if problem == "wrong_end":
        last = path[-1].tolist()
        return f"path ends at ({last[0]}, {last[1]}), not at the reached goal {reply.goal}"
    if why:
        return why
    if problem == "repeats_corner":
        return "any-angle path repeats a corner"
    if problem == "not_8_connected":
        return "path is not a chain of 8-connected steps"
    if problem == "blocked":
        return f"segment {segment} of the path crosses an obstacle or cuts its corner"
    if not math.isfinite(reply.cost_cells) or abs(reply.cost_cells - length) > 1e-6 * max(1.0, length):
        return f"cost {reply.cost_cells!r} cells is not the path's length {length:.6g}"
    return ""
