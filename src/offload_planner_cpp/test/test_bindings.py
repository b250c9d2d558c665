"""The pybind11 module: results, zero-copy grids, GIL release, error types, agreement with scipy."""
import threading
import time

import numpy as np
import pytest
from scipy.sparse import csgraph

import offload_planner_cpp
from offload_planner_cpp import NoPathError, PlanError, PlanStatus, plan
from offload_demos.grid_graph import grid_graph, oracle_free_mask
from offload_planner_cpp.maps import load_map


def test_result_fields():
    grid = np.zeros((5, 7), np.int8)
    grid[1:, 3] = 100
    result = plan(grid, (0, 4), (6, 4))
    assert result.path.dtype == np.int32 and result.path.shape[1] == 2
    assert result.path[0].tolist() == [0, 4] and result.path[-1].tolist() == [6, 4]
    assert result.goal == (6, 4)
    # Up to row 0 round the wall and down again: 2 + 2 diagonals + ... checked against the path itself.
    steps = np.abs(np.diff(result.path, axis=0)).sum(axis=1)
    assert result.cost == pytest.approx((steps == 1).sum() + np.sqrt(2) * (steps == 2).sum())
    assert (grid[result.path[:, 1], result.path[:, 0]] == 0).all()
    assert result.expansions > 0 and result.seconds > 0


def test_grid_is_not_copied():
    # The core reports the buffer it planned on: the caller's own array, for plan and plan_raw alike.
    grid = np.zeros((300, 200), np.int8)
    assert plan(grid, (0, 0), (199, 299)).grid_address == grid.ctypes.data
    assert offload_planner_cpp.plan_raw(grid, (0, 0), (5, 5))["grid_address"] == grid.ctypes.data
    failed = offload_planner_cpp.plan_raw(grid, (0, 0), (500, 5))
    assert failed["status"] == PlanStatus.GOAL_OFF_MAP and failed["grid_address"] == grid.ctypes.data
    view = np.zeros((400, 300), np.int8)[50:350, 50:250]  # not contiguous: refused rather than copied
    with pytest.raises(ValueError, match="C-contiguous"):
        plan(view, (0, 0), (1, 1))
    # The planner reads the caller's buffer as it is now: blocking a cell in place changes the answer.
    grid = np.zeros((3, 3), np.int8)
    assert plan(grid, (0, 1), (2, 1)).cost == 2.0
    grid[:, 1] = 100
    with pytest.raises(NoPathError):
        plan(grid, (0, 1), (2, 1))


def test_gil_released_while_planning():
    rng = np.random.default_rng(1)
    grid = ((rng.random((2500, 2500)) < 0.2) * 100).astype(np.int8)
    grid[0, 0] = grid[-1, -1] = 0
    window = {}

    def work():
        window["start"] = time.perf_counter()
        window["result"] = plan(grid, (0, 0), (2499, 2499), stop_at_goal=False)
        window["end"] = time.perf_counter()

    worker = threading.Thread(target=work)
    ticks = []
    worker.start()
    while worker.is_alive():
        ticks.append(time.perf_counter())
    worker.join()
    inside = [t for t in ticks if window["start"] < t < window["end"]]
    span = window["end"] - window["start"]
    # With the GIL held during the search this thread could not run for the whole plan.
    gaps = np.diff([window["start"], *inside, window["end"]])
    assert len(inside) > 100 and gaps.max() < 0.5 * span, f"longest stall {gaps.max():.3f} s of {span:.3f} s"


@pytest.mark.parametrize("args, status", [
    ((np.zeros((0, 5), np.int8), (0, 0), (0, 0)), PlanStatus.INVALID_MAP),
    ((np.zeros((4, 4), np.int8), (4, 0), (0, 0)), PlanStatus.START_OFF_MAP),
    ((np.zeros((4, 4), np.int8), (0, 0), (0, -1)), PlanStatus.GOAL_OFF_MAP),
    ((np.full((4, 4), 100, np.int8), (0, 0), (1, 1)), PlanStatus.START_BLOCKED),
])
def test_bad_input_raises_value_error(args, status):
    with pytest.raises(ValueError) as error:
        plan(*args)
    assert isinstance(error.value, PlanError) and error.value.status == status
    assert status.name in str(error.value)


def test_bad_arguments_are_clear():
    grid = np.zeros((4, 4), np.int8)
    with pytest.raises(ValueError, match="int8"):
        plan(np.zeros((4, 4), np.uint8), (0, 0), (1, 1))
    with pytest.raises(ValueError, match="2-D"):
        plan(np.zeros(16, np.int8), (0, 0), (1, 1))
    with pytest.raises(ValueError, match=r"start must be an \(x, y\) pair"):
        plan(grid, (0, 0, 0), (1, 1))
    with pytest.raises(ValueError, match="goal must be"):
        plan(grid, (0, 0), "xy")
    with pytest.raises(ValueError, match="lethal_threshold"):
        plan(grid, (0, 0), (1, 1), lethal_threshold=0)
    with pytest.raises(ValueError, match="tolerance"):
        plan(grid, (0, 0), (1, 1), goal_tolerance=-2.0)
    with pytest.raises(TypeError):
        plan([[0, 0]], (0, 0), (1, 0))


def test_goal_blocked_and_unreachable_are_distinct():
    grid = np.zeros((5, 5), np.int8)
    grid[:, 2] = 100
    with pytest.raises(PlanError, match="GOAL_BLOCKED"):
        plan(grid, (0, 0), (2, 2))
    with pytest.raises(NoPathError, match="unreachable"):
        plan(grid, (0, 0), (4, 4))
    assert not issubclass(NoPathError, ValueError)
    # Within tolerance the nearest reachable free cell is planned to instead.
    result = plan(grid, (0, 0), (2, 2), goal_tolerance=1.0)
    assert result.goal == (1, 2)


def test_agrees_with_scipy_on_a_real_map(bundled_maps):
    grid = load_map(bundled_maps / "turtlebot3_world" / "map.yaml").grid
    graph = grid_graph(grid)
    rng = np.random.default_rng(3)
    free = np.flatnonzero(grid.ravel() == 0)
    width = grid.shape[1]
    agreed = 0
    for start in rng.choice(free, 5, replace=False):
        distances = csgraph.dijkstra(graph, indices=int(start))
        for goal in rng.choice(free, 20, replace=False):
            s, g = (int(start % width), int(start // width)), (int(goal % width), int(goal // width))
            if np.isinf(distances[goal]):
                with pytest.raises(NoPathError):
                    plan(grid, s, g)
            else:
                assert plan(grid, s, g).cost == pytest.approx(distances[goal], abs=1e-9)
                agreed += 1
    assert agreed >= 20


@pytest.mark.parametrize("lethal_threshold", [1, 30, 61, 100, 101])
@pytest.mark.parametrize("unknown_is_obstacle", [True, False])
def test_options_reach_the_core(lethal_threshold, unknown_is_obstacle):
    """Every option changes the answer as the independent scipy oracle on the same move rules says."""
    rng = np.random.default_rng(lethal_threshold + 7 * unknown_is_obstacle)
    values = np.array([-1, 0, 20, 40, 60, 80, 100], np.int8)
    grid = rng.choice(values, size=(30, 40), p=[0.04, 0.8, 0.04, 0.04, 0.04, 0.02, 0.02])
    # A wall across the map whose cells take every value: which side reaches the other hangs on the options.
    grid[:, 20] = np.resize(values[values != 0], 30)
    options = dict(lethal_threshold=lethal_threshold, unknown_is_obstacle=unknown_is_obstacle)
    graph = grid_graph(grid, **options)
    free = np.flatnonzero(oracle_free_mask(grid, **options).ravel())
    width = grid.shape[1]
    checked = 0
    for start in rng.choice(free, 4, replace=False):
        distances = csgraph.dijkstra(graph, indices=int(start))
        for goal in rng.choice(free, 10, replace=False):
            s, g = (int(start % width), int(start // width)), (int(goal % width), int(goal // width))
            raw = offload_planner_cpp.plan_raw(grid, s, g, **options)
            if np.isinf(distances[goal]):
                assert raw["status"] == PlanStatus.NO_PATH
            else:
                assert raw["status"] == PlanStatus.OK and raw["cost"] == pytest.approx(distances[goal], abs=1e-9)
                checked += 1
    assert checked >= 5


def test_stop_at_goal_reaches_the_core():
    grid = np.zeros((200, 200), np.int8)
    near = offload_planner_cpp.plan_raw(grid, (0, 0), (2, 2), stop_at_goal=True)
    whole = offload_planner_cpp.plan_raw(grid, (0, 0), (2, 2), stop_at_goal=False)
    assert near["cost"] == whole["cost"] == pytest.approx(2 * np.sqrt(2))
    assert near["expansions"] < 100 and whole["expansions"] == grid.size


@pytest.mark.parametrize("lethal_threshold, unknown_is_obstacle", [(50, True), (1, False), (101, False), (61, True)])
def test_free_cells_is_the_planners_rule(lethal_threshold, unknown_is_obstacle):
    grid = np.arange(-128, 128, dtype=np.int16).astype(np.int8).reshape(16, 16)
    free = offload_planner_cpp.free_cells(grid, lethal_threshold, unknown_is_obstacle)
    expected = oracle_free_mask(grid, lethal_threshold=lethal_threshold, unknown_is_obstacle=unknown_is_obstacle)
    np.testing.assert_array_equal(free, expected)
    # And the planner itself agrees: a one-step plan into each cell works exactly where it is free.
    for y, x in [(8, 0), (8, 5), (8, 10), (8, 12), (0, 0), (15, 15)]:
        row = np.zeros((1, 2), np.int8)
        row[0, 1] = grid[y, x]
        ok = offload_planner_cpp.plan_raw(row, (0, 0), (1, 0), lethal_threshold=lethal_threshold,
                                          unknown_is_obstacle=unknown_is_obstacle)["status"] == PlanStatus.OK
        assert ok == free[y, x], (grid[y, x], lethal_threshold, unknown_is_obstacle)
    with pytest.raises(ValueError, match="lethal_threshold"):
        offload_planner_cpp.free_cells(grid, 0)
