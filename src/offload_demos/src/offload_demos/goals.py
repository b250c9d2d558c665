"""Random reachable goals, as the paper drew them: uniform over the free cells the start can reach.
The free cells come from the planner's own rule (offload_planner_cpp.free_cells); world <-> cell
conversion is the planner's request contract (offload_planner_cpp._core.check_map), not redone here.

Reachability uses 4-connected free cells. A 4-connected path is also a valid path for the planner
(8-connected without corner cutting), so every goal drawn here is reachable by it."""
from typing import Optional, Tuple

import numpy as np
from scipy import ndimage


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
