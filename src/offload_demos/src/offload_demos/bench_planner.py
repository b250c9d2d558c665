"""Planner benchmark (`make bench-planner`): median times and expansions per second of the C++ Dijkstra,
against scipy.sparse.csgraph.dijkstra on the same graph, run in this process. Not a test: it prints
measured figures. Every distance is cross-checked against scipy while measuring.

1. 2000 x 2000 grid, 20% random obstacles (seeded), corner to corner.
2. ROS maps (shared set, else the bundled ones), random free start/goal pairs.
The modes sections first: every mode side by side (bench_planner_modes) and the point-to-point modes (astar,
jps, auto) against the default per map (bench_planner_p2p), and any-angle against the default per map, time
and length (bench_planner_any_angle).
"""
import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.sparse import csgraph

from offload_planner_cpp import NoPathError, plan
from offload_demos.grid_graph import grid_graph
from offload_planner_cpp.maps import load_map

from offload_demos import bench_planner_modes as planner_modes
from offload_demos import bench_planner_any_angle, bench_planner_p2p
from offload_demos.bench_planner_modes import median_of

HERE = Path(__file__).resolve()
WORKSPACE = HERE.parents[4]
SHARED_ROS = WORKSPACE.parent / "shared" / "data" / "maps" / "ros"
BUNDLED = WORKSPACE / "src" / "offload_planner_cpp" / "maps"

# The sections against scipy time the two waves (their expansions per second mean something); the default,
# auto, takes jump points on open maps (bench_planner_p2p compares the modes).
WAVES = "dijkstra"


def random_grid(size, density, seed):
    rng = np.random.default_rng(seed)
    grid = ((rng.random((size, size)) < density) * 100).astype(np.int8)
    grid[0, 0] = grid[-1, -1] = 0
    return grid


def bench_random(size, runs):
    grid = random_grid(size, 0.2, seed=0)
    start, goal = (0, 0), (size - 1, size - 1)
    t_goal, r_goal = median_of(runs, lambda: plan(grid, start, goal, algorithm=WAVES))
    # A short plan on the same big map: its cost must follow the path, not the map's size.
    near_start, near_goal = (size // 2, size // 2), (size // 2 + 40, size // 2 + 30)
    grid[near_start[1], near_start[0]] = grid[near_goal[1], near_goal[0]] = 0
    t_short, r_short = median_of(10 * runs, lambda: plan(grid, near_start, near_goal, algorithm=WAVES))
    t_full, r_full = median_of(runs, lambda: plan(grid, start, goal, stop_at_goal=False, algorithm=WAVES))
    built = time.perf_counter()
    graph = grid_graph(grid)
    t_build = time.perf_counter() - built
    t_scipy, dist = median_of(max(1, runs // 2), lambda: csgraph.dijkstra(graph, indices=0))
    assert abs(dist[-1] - r_goal.cost) < 1e-6, (dist[-1], r_goal.cost)
    print(f"## {size} x {size}, 20% random obstacles (seed 0), corner to corner, median of {runs}")
    print(f"planner, stop at goal : {t_goal * 1e3:8.1f} ms  {r_goal.expansions:>9d} expansions  "
          f"{r_goal.expansions / t_goal / 1e6:5.1f} M expansions/s  cost {r_goal.cost:.3f}")
    print(f"planner, full search  : {t_full * 1e3:8.1f} ms  {r_full.expansions:>9d} expansions  "
          f"{r_full.expansions / t_full / 1e6:5.1f} M expansions/s")
    print(f"planner, short query  : {t_short * 1e3:8.3f} ms  {r_short.expansions:>9d} expansions  "
          f"(40 x 30 cells apart on the same map: no per-call pass over the whole map)")
    print(f"scipy dijkstra (full) : {t_scipy * 1e3:8.1f} ms  (+ {t_build * 1e3:.0f} ms to build its graph, excluded)")
    print(f"speed-up vs scipy     : {t_scipy / t_full:5.1f}x same full search, {t_scipy / t_goal:5.1f}x stop at goal")
    print("anchor (DESIGN.md, this machine class): ROS navfn makePlan 184 ms on this grid\n")


def bench_map(yaml_file, pairs, starts, rng):
    occupancy = load_map(yaml_file)
    grid = occupancy.grid
    free = np.flatnonzero(grid.ravel() == 0)
    width = grid.shape[1]
    cell = lambda i: (int(i % width), int(i // width))
    times, expansions, skipped = [], 0, 0
    for _ in range(pairs):
        s, g = rng.choice(free, 2, replace=False)
        try:
            result = plan(grid, cell(s), cell(g), algorithm=WAVES)
        except NoPathError:
            skipped += 1
            continue
        times.append(result.seconds)
        expansions += result.expansions
    graph = grid_graph(grid)
    full, scipy_times = [], []
    for s in rng.choice(free, starts, replace=False):
        t_ours, result = median_of(3, lambda: plan(grid, cell(s), cell(s), stop_at_goal=False, algorithm=WAVES))
        t_scipy, dist = median_of(1, lambda: csgraph.dijkstra(graph, indices=int(s)))
        reached = np.isfinite(dist)
        assert reached.sum() == result.expansions, "planner and scipy disagree on the reachable set"
        full.append(t_ours)
        scipy_times.append(t_scipy)
    per_query = statistics.median(times) if times else float("nan")
    print(f"{occupancy.name:20s} {grid.shape[1]:5d} x {grid.shape[0]:<5d} {len(times):4d} pairs "
          f"median {per_query * 1e3:7.2f} ms  {expansions / max(sum(times), 1e-12) / 1e6:5.1f} M exp/s  "
          f"full search {statistics.median(full) * 1e3:7.1f} ms vs scipy {statistics.median(scipy_times) * 1e3:7.1f} ms "
          f"({statistics.median(scipy_times) / statistics.median(full):4.1f}x)"
          + (f"  [{skipped} unreachable pairs skipped]" if skipped else ""))


def main(argv=None):
    parser = argparse.ArgumentParser(description="planner benchmark against scipy")
    parser.add_argument("--size", type=int, default=2000)
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--pairs", type=int, default=50, help="random pairs per ROS map")
    parser.add_argument("--starts", type=int, default=3, help="full searches per ROS map compared with scipy")
    parser.add_argument("--figure", type=Path, default=BUNDLED.parent / "docs" / "planner_modes.png",
                        help="PNG of the same plan in each mode on the Husky playpen")
    parser.add_argument("--only-modes", action="store_true", help="only the modes sections")
    args = parser.parse_args(argv)
    print("## Planner modes")
    planner_modes.run(3, args.figure, BUNDLED / "husky_playpen" / "playpen_map.yaml")
    bench_planner_p2p.run(random_sizes=(args.size, 2 * args.size))
    bench_planner_any_angle.run(random_sizes=(args.size, 2 * args.size))
    if args.only_modes:
        return 0
    bench_random(args.size, args.runs)
    maps_dir = SHARED_ROS if SHARED_ROS.is_dir() else BUNDLED
    print(f"## ROS maps from {maps_dir}: random free start/goal pairs (seed 0), stop at goal; "
          f"full searches from {args.starts} starts vs scipy")
    rng = np.random.default_rng(0)
    for yaml_file in sorted(maps_dir.glob("*/*.yaml")):
        bench_map(yaml_file, args.pairs, args.starts, rng)
    return 0


if __name__ == "__main__":
    sys.exit(main())
