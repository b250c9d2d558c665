"""The state s_t = {d_t, u_t, b_t} of the paper (eq. 4) and the input size d_t of a path-planning
request (eq. 11 and 12)."""
import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

STATE_SIZE = 3
STATE_FIELDS = ("input_size", "cpu_availability", "round_trip_s")


def node_count(distance_m: float, resolution_m: float) -> float:
    """Eq. 11: cells in the rectangle whose diagonal is the segment from start to goal, taken as a
    square of area x^2 / 2 (the largest rectangle with that diagonal)."""
    if resolution_m <= 0:
        raise ValueError(f"resolution_m must be positive, got {resolution_m}")
    if distance_m < 0:
        raise ValueError(f"distance_m must be non-negative, got {distance_m}")
    return (0.5 * distance_m * distance_m) / (resolution_m * resolution_m)


def raw_input_size(distance_m: float, resolution_m: float) -> float:
    """Eq. 12: d = n ln n with the natural log (the paper's worked example only matches ln).
    Below one node n ln n is negative, which means nothing for a cost, so it is clamped to 0."""
    n = node_count(distance_m, resolution_m)
    return n * math.log(n) if n > 1.0 else 0.0


def input_size(start_m: Sequence[float], goal_m: Sequence[float], resolution_m: float,
               map_cell_count: int) -> float:
    """Normalised input size d_t: n ln n divided by the map's cell count, as the paper normalised
    by the global map size (its values ran from 0 to 5)."""
    if map_cell_count <= 0:
        raise ValueError(f"map_cell_count must be positive, got {map_cell_count}")
    distance_m = math.hypot(goal_m[0] - start_m[0], goal_m[1] - start_m[1])
    return raw_input_size(distance_m, resolution_m) / map_cell_count


def input_size_from_cells(start_cell: Sequence[int], goal_cell: Sequence[int], resolution_m: float,
                          map_cell_count: int) -> float:
    """Same as input_size for grid cells (x, y): distances in cells times the resolution."""
    return input_size((start_cell[0] * resolution_m, start_cell[1] * resolution_m),
                      (goal_cell[0] * resolution_m, goal_cell[1] * resolution_m),
                      resolution_m, map_cell_count)


@dataclass(frozen=True)
class State:
    """One observation s_t. input_size is normalised d_t, cpu_availability is u_t in [0, 1],
    round_trip_s is b_t in seconds."""
    input_size: float
    cpu_availability: float
    round_trip_s: float

    def __post_init__(self):
        if not (self.input_size >= 0 and math.isfinite(self.input_size)):
            raise ValueError(f"input_size must be finite and >= 0, got {self.input_size}")
        if not 0.0 <= self.cpu_availability <= 1.0:
            raise ValueError(f"cpu_availability must be in [0, 1], got {self.cpu_availability}")
        if not (self.round_trip_s >= 0 and math.isfinite(self.round_trip_s)):
            raise ValueError(f"round_trip_s must be finite and >= 0, got {self.round_trip_s}")

    def as_array(self) -> np.ndarray:
        return np.array([self.input_size, self.cpu_availability, self.round_trip_s], dtype=np.float64)
