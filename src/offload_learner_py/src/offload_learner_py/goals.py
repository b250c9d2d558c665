"""Random reachable goals, as the paper drew them: uniform over the free cells the start can reach.

Reachability uses 4-connected free cells. A 4-connected path is also a valid path for the planner
(8-connected without corner cutting), so every goal drawn here is reachable by it."""
import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class GridFrame:
    """Where a grid sits in the map frame: cell (x, y) has its centre at origin + R(yaw) (x+.5, y+.5) res."""
    resolution_m: float
    origin_x_m: float = 0.0
    origin_y_m: float = 0.0
    yaw: float = 0.0

    def __post_init__(self):
        if not (self.resolution_m > 0 and math.isfinite(self.resolution_m)):
            raise ValueError(f"resolution_m must be positive, got {self.resolution_m}")

    def cell_centre_m(self, x: int, y: int) -> Tuple[float, float]:
        local_x, local_y = (x + 0.5) * self.resolution_m, (y + 0.5) * self.resolution_m
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return self.origin_x_m + c * local_x - s * local_y, self.origin_y_m + s * local_x + c * local_y

    def cell_of(self, x_m: float, y_m: float) -> Tuple[int, int]:
        dx, dy = x_m - self.origin_x_m, y_m - self.origin_y_m
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return (int(math.floor((c * dx + s * dy) / self.resolution_m)),
                int(math.floor((-s * dx + c * dy) / self.resolution_m)))


def free_cells(grid: np.ndarray, lethal_threshold: int = 50, unknown_is_obstacle: bool = True) -> np.ndarray:
    """Boolean [y, x] mask of cells the planner may enter (its rules: occupancy < threshold, unknown -1
    free unless unknown_is_obstacle)."""
    grid = np.asarray(grid)
    if grid.ndim != 2 or grid.size == 0:
        raise ValueError(f"grid must be a non-empty 2-D array, got shape {grid.shape}")
    if not 1 <= lethal_threshold <= 101:
        raise ValueError(f"lethal_threshold must be in 1..101, got {lethal_threshold}")
    values = grid.astype(np.int16)
    unknown = values < 0
    free = (values < lethal_threshold) & ~unknown
    return free | (unknown & (not unknown_is_obstacle))


def nearest_free_cell(free: np.ndarray, x: int, y: int) -> Tuple[int, int]:
    """The free cell nearest to (x, y) (the cell itself when free)."""
    if not free.any():
        raise ValueError("the map has no free cell")
    ys, xs = np.nonzero(free)
    k = int(np.argmin((xs - x) ** 2 + (ys - y) ** 2))
    return int(xs[k]), int(ys[k])


class GoalSampler:
    """Seeded uniform draws from the free cells reachable from `start_cell` (x, y), at least
    `min_distance_cells` from it."""

    def __init__(self, free: np.ndarray, start_cell: Tuple[int, int], seed: int = 1,
                 min_distance_cells: float = 0.0):
        height, width = free.shape
        x, y = start_cell
        if not (0 <= x < width and 0 <= y < height):
            raise ValueError(f"start cell {start_cell} is off the {width} x {height} map")
        if not free[y, x]:
            raise ValueError(f"start cell {start_cell} is not free")
        labels, _ = ndimage.label(free)   # 4-connected by default
        reachable = labels == labels[y, x]
        ys, xs = np.nonzero(reachable)
        far = (xs - x) ** 2 + (ys - y) ** 2 >= min_distance_cells ** 2
        self.xs, self.ys = xs[far], ys[far]
        if len(self.xs) == 0:
            raise ValueError(f"no reachable free cell at least {min_distance_cells} cells from {start_cell}")
        self.start_cell = (x, y)
        self.rng = np.random.default_rng(seed)

    @property
    def reachable_cells(self) -> int:
        return len(self.xs)

    def draw(self) -> Tuple[int, int]:
        k = int(self.rng.integers(0, len(self.xs)))
        return int(self.xs[k]), int(self.ys[k])


def default_start_cell(free: np.ndarray, start_cell: Optional[Tuple[int, int]] = None) -> Tuple[int, int]:
    """The given start, or the free cell nearest the map's centre (the paper planned from the centre)."""
    height, width = free.shape
    if start_cell is None:
        start_cell = (width // 2, height // 2)
    return nearest_free_cell(free, *start_cell)
