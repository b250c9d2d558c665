"""The planner's move graph as a scipy sparse matrix: an independent solver for tests and the
benchmark baseline (scipy.sparse.csgraph.dijkstra on the same graph)."""
import numpy as np
from scipy.sparse import csr_matrix

_SQRT2 = float(np.sqrt(2.0))


def oracle_free_mask(grid: np.ndarray, lethal_threshold: int = 50, unknown_is_obstacle: bool = True) -> np.ndarray:
    """Boolean [y, x] mask of the cells the planner may enter, written apart from the planner (numpy) so
    that tests compare the two; the product uses the planner's own, offload_planner_cpp.free_cells."""
    return np.where(grid < 0, not unknown_is_obstacle, grid < lethal_threshold)


def grid_graph(grid: np.ndarray, cost_factor: float = 0.0, neutral_cost: float = 50.0, **options) -> csr_matrix:
    """Directed graph over cell indices y * width + x: 8-connected, cost 1 and sqrt(2), a diagonal only
    when both orthogonal neighbours are free. With cost_factor > 0 a move costs its length times the mean of
    neutral_cost + cost_factor * occupancy over its two cells (unknown cells: occupancy 0), the planner's
    cost-aware model."""
    free = oracle_free_mask(grid, **options)
    weight = neutral_cost + cost_factor * np.maximum(grid.astype(np.float64), 0.0)
    height, width = free.shape
    index = np.arange(height * width).reshape(height, width)
    rows, cols, costs = [], [], []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        # Pairs (a, b) with b = a + (dx, dy); each edge is added both ways.
        ys = slice(0, height - dy)
        xs = slice(max(0, -dx), width - max(0, dx))
        ys2 = slice(dy, height)
        xs2 = slice(max(0, dx), width + min(0, dx))
        ok = free[ys, xs] & free[ys2, xs2]
        if dx and dy:
            ok &= free[ys, xs2] & free[ys2, xs]  # no corner cutting
        a, b = index[ys, xs][ok], index[ys2, xs2][ok]
        length = _SQRT2 if dx and dy else 1.0
        if cost_factor > 0:
            cost = length * 0.5 * (weight[ys, xs][ok] + weight[ys2, xs2][ok])
        else:
            cost = np.full(a.size, length)
        rows += [a, b]
        cols += [b, a]
        costs += [cost, cost]
    rows, cols, costs = np.concatenate(rows), np.concatenate(cols), np.concatenate(costs)
    return csr_matrix((costs, (rows, cols)), shape=(height * width, height * width))
