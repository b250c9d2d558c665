"""The planner reproduces MovingAI optimal lengths on every benchmark map, bundled and shared (short and
long buckets), and the CLI reports mismatches."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import offload_planner_cpp
from offload_planner_cpp.maps import Scenario, length_tolerance, load_movingai_map, load_scenarios
from offload_demos.movingai import check, spread

from planner_testdata import BUNDLED_MOVINGAI, SHARED_MAPS, movingai_maps

MAP_FILES = movingai_maps()


def bucket_spread(scenarios, per_bucket=3, buckets=12):
    """A few queries from each of `buckets` buckets spread from the shortest to the longest."""
    by_bucket = {}
    for s in scenarios:
        by_bucket.setdefault(s.bucket, []).append(s)
    keys = sorted(by_bucket)
    chosen = sorted({keys[i] for i in np.linspace(0, len(keys) - 1, min(buckets, len(keys))).round().astype(int)})
    return [s for k in chosen for s in by_bucket[k][:per_bucket]]


def assert_legal_path(grid, path):
    steps = np.diff(path, axis=0)
    assert np.abs(steps).max() <= 1 and (np.abs(steps).sum(axis=1) > 0).all()
    assert (grid[path[:, 1], path[:, 0]] == 0).all(), "path crosses an obstacle"
    diagonal = (steps[:, 0] != 0) & (steps[:, 1] != 0)
    corners_a = grid[path[:-1, 1][diagonal], path[1:, 0][diagonal]]
    corners_b = grid[path[1:, 1][diagonal], path[:-1, 0][diagonal]]
    assert (corners_a == 0).all() and (corners_b == 0).all(), "diagonal step cuts a corner"


def test_bundled_movingai_maps_are_present():
    # Without this, losing the bundled set would only show as fewer parametrized cases and the
    # optimality check would silently stop running on a bare clone. Both precisions are covered: dao
    # prints about 6 significant digits, street 8 decimals (and uses CRLF lines).
    bundled = sorted(p.relative_to(BUNDLED_MOVINGAI).as_posix() for p in BUNDLED_MOVINGAI.glob("*/*.map"))
    assert {"dao/arena.map", "street/Berlin_0_256.map"} <= set(bundled), bundled
    for map_file in BUNDLED_MOVINGAI.glob("*/*.map"):
        assert map_file in MAP_FILES
        assert Path(str(map_file) + ".scen").is_file(), f"{map_file} has no .scen beside it"
    assert (BUNDLED_MOVINGAI.parent / "README.md").read_text().count("ODC-By") >= 1, "attribution missing"


def test_shared_movingai_maps_are_used_when_present():
    shared = sorted((SHARED_MAPS / "movingai").glob("*/*.map"))
    if not shared:
        pytest.skip(f"no shared MovingAI set at {SHARED_MAPS / 'movingai'}: only the bundled maps are checked "
                    f"(put the set at ../shared/data/maps beside the workspace or point OFFLOAD_SHARED_MAPS at it)")
    names = {p.relative_to(p.parents[1]).as_posix() for p in MAP_FILES}
    assert {p.relative_to(p.parents[1]).as_posix() for p in shared} <= names


def test_bundled_copies_match_the_shared_set():
    # The bundled files claim to be unchanged copies (CRLF and missing final newline included).
    shared_root = SHARED_MAPS / "movingai"
    pairs = [(p, shared_root / p.relative_to(BUNDLED_MOVINGAI)) for p in BUNDLED_MOVINGAI.glob("*/*.map*")]
    pairs = [(ours, theirs) for ours, theirs in pairs if theirs.is_file()]
    if not pairs:
        pytest.skip(f"no shared MovingAI set at {shared_root} to compare the bundled copies with")
    for ours, theirs in pairs:
        assert ours.read_bytes() == theirs.read_bytes(), f"{ours} differs from {theirs}"


@pytest.mark.parametrize("map_file", MAP_FILES, ids=lambda p: p.stem)
def test_optimal_lengths(map_file):
    occupancy = load_movingai_map(map_file)
    every = load_scenarios(Path(str(map_file) + ".scen"))
    scenarios = bucket_spread(every)
    assert {min(s.bucket for s in every), max(s.bucket for s in every)} <= {s.bucket for s in scenarios}
    summary = check(occupancy.grid, scenarios)
    assert summary.checked == len(scenarios) >= 12
    assert summary.mismatches == 0, f"max abs error {summary.max_abs_error}"
    longest = max(scenarios, key=lambda s: s.optimal_length)
    result = offload_planner_cpp.plan(occupancy.grid, longest.start, longest.goal)
    assert_legal_path(occupancy.grid, result.path)
    steps = np.abs(np.diff(result.path, axis=0)).sum(axis=1)
    assert np.isclose((steps == 1).sum() + np.sqrt(2) * (steps == 2).sum(), result.cost)


@pytest.mark.parametrize("map_file", MAP_FILES, ids=lambda p: p.stem)
def test_jump_point_search_astar_and_auto_are_exact_on_every_query(map_file):
    """algorithm jps, astar (A* on buckets, which reopens cells) and auto on every query of the file: the optimal length (the default's, which
    test_optimal_lengths and the CLI check) and a legal path (no blocked cell, no cut corner) whose steps add
    up to it; on the bucket spread also the default's own cost, query by query."""
    grid = load_movingai_map(map_file).grid
    every = load_scenarios(Path(str(map_file) + ".scen"))
    for scenario in every:
        for algorithm in ("jps", "astar", "auto"):
            result = offload_planner_cpp.plan(grid, scenario.start, scenario.goal, algorithm=algorithm)
            assert abs(result.cost - scenario.optimal_length) <= length_tolerance(scenario), (algorithm, scenario)
            assert tuple(result.path[0]) == scenario.start and tuple(result.path[-1]) == scenario.goal
            if len(result.path) > 1:
                assert_legal_path(grid, result.path)
            steps = np.abs(np.diff(result.path, axis=0)).sum(axis=1)
            assert (steps == 1).sum() + np.sqrt(2) * (steps == 2).sum() == pytest.approx(result.cost, abs=1e-9)
    for scenario in bucket_spread(every):
        default = offload_planner_cpp.plan(grid, scenario.start, scenario.goal).cost
        for algorithm in ("jps", "astar", "auto"):
            cost = offload_planner_cpp.plan(grid, scenario.start, scenario.goal, algorithm=algorithm).cost
            assert cost == pytest.approx(default, rel=1e-12, abs=1e-12), (algorithm, scenario)


def test_tolerance_follows_printed_precision():
    exact = Scenario(0, "m", (0, 0), (1, 1), 1000.0, decimals=8)
    rough = Scenario(0, "m", (0, 0), (1, 1), 1000.0, decimals=4)
    assert length_tolerance(exact) < 2e-6
    assert length_tolerance(rough) == 0.01


def test_spread_covers_the_file_ends():
    scenarios = [Scenario(i // 10, "m", (0, 0), (0, 0), float(i), 8) for i in range(100)]
    picked = spread(scenarios, 5)
    assert [s.optimal_length for s in picked] == [0.0, 25.0, 50.0, 74.0, 99.0]
    assert spread(scenarios, 0) == scenarios


def test_cli_reports_mismatches(tmp_path):
    (tmp_path / "tiny.map").write_text("type octile\r\nheight 3\r\nwidth 4\r\nmap\r\n....\r\n.@@.\r\n....")
    scen = "version 1\n0\ttiny.map\t4\t3\t0\t0\t3\t2\t{}\n"
    exact = 5.0  # round the wall: no diagonal may cut its corners
    (tmp_path / "ok.scen").write_text(scen.format(f"{exact:.8f}"))
    (tmp_path / "bad.scen").write_text(scen.format("4.00000000") + "\n")
    run = lambda scen_file: subprocess.run(
        [sys.executable, "-m", "offload_demos.movingai", str(tmp_path / "tiny.map"), str(tmp_path / scen_file)],
        capture_output=True, text=True)
    good = run("ok.scen")
    assert good.returncode == 0, good.stderr
    assert "1 queries checked, 0 mismatches" in good.stdout
    bad = run("bad.scen")
    assert bad.returncode == 1
    assert "1 queries checked, 1 mismatches" in bad.stdout
    jumps = subprocess.run([sys.executable, "-m", "offload_demos.movingai", str(tmp_path / "tiny.map"),
                            str(tmp_path / "ok.scen"), "--algorithm", "jps"], capture_output=True, text=True)
    assert jumps.returncode == 0 and "1 queries checked, 0 mismatches" in jumps.stdout, jumps.stdout + jumps.stderr
