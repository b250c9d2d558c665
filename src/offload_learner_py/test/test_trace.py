import os
import subprocess
import sys

import numpy as np
import pytest

from offload_learner_py.core.state import input_size_from_cells
from offload_learner_py.data.trace import PlanningTrace, free_cell_coordinates, record_trace


class NoPathError(RuntimeError):
    pass


class FakeResult:
    def __init__(self, seconds, expansions):
        self.seconds, self.expansions = seconds, expansions


class FakePlanner:
    """Stands in for offload_planner_cpp.plan: unreachable when the goal is in the right half."""

    def __init__(self):
        self.calls = []

    def __call__(self, grid, start, goal, **options):
        assert grid.dtype == np.int8
        self.calls.append((start, goal, options))
        if goal[0] >= grid.shape[1] // 2 and start[0] < grid.shape[1] // 2:
            raise NoPathError("wall between the halves")
        return FakeResult(0.001, 42)


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        self.now += 0.5  # each call advances: elapsed per plan is always 0.5 s
        return self.now


def _grid():
    grid = np.zeros((20, 30), np.int8)
    grid[:, 15] = 100       # a wall splits the map
    grid[0, :] = -1         # unknown row
    return grid


def test_free_cells_skip_obstacles_and_unknown():
    cells = free_cell_coordinates(_grid())
    assert len(cells) == 19 * 29
    assert not np.any(cells[:, 0] == 15) and not np.any(cells[:, 1] == 0)


def test_free_cells_follow_the_planners_unknown_rule():
    """The planner's own rule through its binding: with unknown cells free, the unknown row counts too."""
    cells = free_cell_coordinates(_grid(), unknown_is_obstacle=False)
    assert len(cells) == 20 * 29 + 1 and np.any(cells[:, 1] == 0)   # + the wall cell the unknown row covers


def test_record_trace_with_an_injected_planner(tmp_path):
    planner = FakePlanner()
    trace = record_trace(planner, _grid(), 0.05, 40, np.random.default_rng(2), map_name="fake", clock=FakeClock(),
                         lethal_threshold=50)
    assert len(trace) == 40
    assert np.all(trace.local_s == 0.5) and np.all(trace.planner_s == 0.001) and np.all(trace.expansions == 42)
    assert trace.metadata["unreachable"] == trace.metadata["attempts"] - 40 > 0
    assert all(options == {"lethal_threshold": 50} for _, _, options in planner.calls)
    for start, goal, d, x in zip(trace.start_cell, trace.goal_cell, trace.input_size, trace.distance_m):
        assert d == pytest.approx(input_size_from_cells(start, goal, 0.05, 600))
        assert x == pytest.approx(0.05 * np.hypot(*(goal - start)))
    path = str(tmp_path / "trace.npz")
    trace.save_npz(path)
    loaded = PlanningTrace.load_npz(path)
    assert np.array_equal(loaded.local_s, trace.local_s) and loaded.metadata == trace.metadata


def test_bad_planner_input_propagates():
    def rejecting(grid, start, goal):
        raise ValueError("start off the map")

    with pytest.raises(ValueError):
        record_trace(rejecting, _grid(), 0.05, 3, np.random.default_rng(0))


def test_all_unreachable_stops_after_max_attempts():
    def never(grid, start, goal):
        raise NoPathError("no")

    with pytest.raises(RuntimeError, match="reachable"):
        record_trace(never, _grid(), 0.05, 3, np.random.default_rng(0), max_attempts=10)


def test_bundled_trace_holds_real_planner_times(bundled_trace):
    trace = bundled_trace
    assert len(trace) >= 300
    assert "husky_playpen" in trace.metadata["map_name"] and trace.metadata["resolution_m"] == 0.05
    assert np.all(trace.local_s > 0) and np.all(trace.expansions > 0)
    assert np.all(trace.planner_s <= trace.local_s)  # the call wraps the search
    # Real Dijkstra times grow with the input size (not a formula: correlation, not equality).
    assert np.corrcoef(np.log(trace.input_size), np.log(trace.local_s))[0, 1] > 0.5


def test_corrupt_or_invalid_trace_files_are_clear_errors(tmp_path, small_trace):
    from test_dataset import _corrupt_member

    good = str(tmp_path / "trace.npz")
    small_trace.save_npz(good)
    for path in _corrupt_member(good, "local_s.npy", tmp_path):
        with pytest.raises(ValueError, match=r"corrupt-\d+\.npz: cannot read planning trace: array 'local_s'"):
            PlanningTrace.load_npz(path)
    with pytest.raises(ValueError, match="absent.npz: cannot read planning trace"):
        PlanningTrace.load_npz(str(tmp_path / "absent.npz"))
    arrays = {name: getattr(small_trace, name) for name in ("start_cell", "goal_cell", "distance_m", "input_size",
                                                             "local_s", "planner_s", "expansions")}
    for name, value, message in [("local_s", np.nan, "local_s must be finite and > 0 in every row; row 3 is nan"),
                                 ("input_size", -1.0, "input_size must be finite and >= 0"),
                                 ("planner_s", np.inf, "planner_s must be nan or >= 0")]:
        bad = np.array(arrays[name], dtype=np.float64)
        bad[3] = value
        path = str(tmp_path / "bad.npz")
        np.savez(path, format=np.array("offload_learner_py.trace/1"), metadata=np.array("{}"), **{**arrays, name: bad})
        with pytest.raises(ValueError, match=f"bad.npz: invalid planning trace: trace array {message}"):
            PlanningTrace.load_npz(path)
    with pytest.raises(ValueError, match="start_cell must be N x 2"):
        PlanningTrace(**{**arrays, "start_cell": np.zeros(50, np.int64)})
    with pytest.raises(ValueError, match="different lengths"):
        PlanningTrace(**{**arrays, "local_s": arrays["local_s"][:10]})


SMALL_REAL_MAP = os.path.join(os.path.dirname(__file__), "..", "..", "offload_planner_cpp", "maps", "turtlebot3_world",
                              "map.yaml")


def _trace_cli(*args, cwd):
    return subprocess.run([sys.executable, "-m", "offload_learner_py.data.trace", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120)


def test_trace_command_records_the_real_planner_on_a_real_map(tmp_path):
    """End to end: the CLI, offload_planner_cpp's map loader and planner, the saved file. Needs the
    built workspace (`source devel/setup.bash`)."""
    import offload_planner_cpp
    from offload_planner_cpp import maps

    result = _trace_cli("--map", SMALL_REAL_MAP, "--queries", "12", "--seed", "3", "--out", "t.npz", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("wrote t.npz: 12 plans") and "planned 12/12" in result.stderr
    trace = PlanningTrace.load_npz(str(tmp_path / "t.npz"))
    occupancy = maps.load_map_server_yaml(SMALL_REAL_MAP)
    grid, resolution = occupancy.grid, occupancy.resolution
    assert (grid.shape, resolution) == ((384, 384), 0.05)
    assert len(trace) == 12 and trace.metadata["seed"] == 3 and trace.metadata["map_cell_count"] == 384 * 384
    assert trace.metadata["map_shape"] == [384, 384] and trace.metadata["resolution_m"] == 0.05
    for cells in (trace.start_cell, trace.goal_cell):  # (x, y) of known free cells
        assert np.all((grid[cells[:, 1], cells[:, 0]] >= 0) & (grid[cells[:, 1], cells[:, 0]] < 50))
    assert not np.any(np.all(trace.start_cell == trace.goal_cell, axis=1))
    # Eq. 11-12 by hand: n = (x^2 / 2) / r^2, d = n ln n over the map's cells.
    x = 0.05 * np.hypot(*(trace.goal_cell - trace.start_cell).T)
    n = x ** 2 / 2 / 0.05 ** 2
    assert np.allclose(trace.distance_m, x) and np.allclose(trace.input_size, n * np.log(n) / (384 * 384))
    assert np.all(trace.expansions > 0) and np.all((trace.planner_s > 0) & (trace.planner_s <= trace.local_s))
    # The real planner again on the same pairs: it finds each path, no shorter than the straight line, after
    # settling the same cells it reported in the trace (Dijkstra is deterministic).
    for start, goal, distance_m, expansions in zip(trace.start_cell, trace.goal_cell, trace.distance_m,
                                                   trace.expansions):
        plan = offload_planner_cpp.plan(grid, tuple(int(v) for v in start), tuple(int(v) for v in goal))
        assert plan.cost * resolution >= distance_m - 1e-9
        assert plan.expansions == expansions
        assert tuple(plan.path[0]) == tuple(start) and tuple(plan.path[-1]) == tuple(goal)
    again = _trace_cli("--map", SMALL_REAL_MAP, "--queries", "12", "--seed", "3", "--out", "again.npz", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    same_seed = PlanningTrace.load_npz(str(tmp_path / "again.npz"))
    assert np.array_equal(same_seed.start_cell, trace.start_cell) and np.array_equal(same_seed.goal_cell,
                                                                                     trace.goal_cell)
