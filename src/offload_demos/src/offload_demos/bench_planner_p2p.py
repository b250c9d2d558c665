"""Point-to-point modes against the default (part of `make bench-planner`, or alone:
`python -m offload_demos.bench_planner_p2p`): per map, the planner core's time summed over the same queries
for the default (the two waves), astar, jps and auto, query by query in this one process, and
the ratio default / mode. Every mode's cost is checked against the default's on every query.

Maps: the ROS maps (bundled and shared), the MovingAI maps (bundled and shared; queries spread over the
scenario file), and 20 % random grids corner to corner (the DESIGN.md navfn anchors)."""
import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

import offload_planner_cpp
from offload_planner_cpp import plan
from offload_planner_cpp.maps import load_map, load_movingai_map, load_scenarios

from offload_demos.movingai import spread

HERE = Path(__file__).resolve()
WORKSPACE = HERE.parents[4]
SHARED = WORKSPACE.parent / "shared" / "data" / "maps"
BUNDLED = WORKSPACE / "src" / "offload_planner_cpp"
MODES = ("dijkstra", "astar", "jps", "auto")


def _by_name(*roots, pattern):
    found = {}
    for root in roots:
        if root.is_dir():
            for path in sorted(root.glob(pattern)):
                found.setdefault(path.relative_to(root).as_posix(), path)
    return [found[key] for key in sorted(found)]


def random_pairs(grid, count, rng):
    """`count` start/goal pairs drawn from the largest 8-connected free component."""
    free = offload_planner_cpp.free_cells(grid)
    labels, _ = ndimage.label(free, structure=np.ones((3, 3)))
    biggest = labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1
    cells = np.argwhere(biggest)[:, ::-1]
    return [tuple(tuple(int(v) for v in cells[k]) for k in rng.choice(len(cells), 2, replace=False))
            for _ in range(count)]


def bench_maps(pairs, random_sizes=(2000, 4000), movingai=True, ros=True):
    """(name, grid, queries) of the planner benchmarks' maps: the ROS maps (bundled and shared, `pairs` random
    pairs each), the MovingAI maps (bundled and shared, `pairs` queries spread over the scenario file) and 20 %
    random grids corner to corner."""
    rng = np.random.default_rng(0)
    if ros:
        for yaml_file in _by_name(BUNDLED / "maps", SHARED / "ros", pattern="*/*.yaml"):
            occupancy = load_map(yaml_file)
            yield occupancy.name, occupancy.grid, random_pairs(occupancy.grid, pairs, rng)
    if movingai:
        for map_file in _by_name(BUNDLED / "test" / "data" / "movingai", SHARED / "movingai", pattern="*/*.map"):
            scenarios = spread(load_scenarios(Path(str(map_file) + ".scen")), pairs)
            yield map_file.stem, load_movingai_map(map_file).grid, [(s.start, s.goal) for s in scenarios]
    for size in random_sizes:
        grid = ((np.random.default_rng(0).random((size, size)) < 0.2) * 100).astype(np.int8)
        grid[0, 0] = grid[-1, -1] = 0
        yield f"random 20 % {size}", grid, [((0, 0), (size - 1, size - 1))]


def bench_fastest(name, grid, pairs, runs, modes=MODES):
    """Sum over `pairs` of each mode's fastest of `runs` core times; fails when a mode's cost differs from
    the default's. A mode's runs of one query go in a row, as a planner serving one mode plans (run after
    another mode, a search finds its buffers out of cache: up to 10 % on small queries), and the modes'
    order turns from query to query, so a change of machine load hits them alike."""
    total = {mode: 0.0 for mode in modes}
    for mode in modes:   # buffers sized for this map (the first plan on a map allocates them), not timed
        plan(grid, *pairs[0], algorithm=mode)
    for k, (start, goal) in enumerate(pairs):
        costs = {}
        for mode in modes[k % len(modes):] + modes[:k % len(modes)]:
            results = [plan(grid, start, goal, algorithm=mode) for _ in range(runs)]
            total[mode] += min(r.seconds for r in results)
            costs[mode] = results[0].cost
        assert all(abs(costs[m] - costs["dijkstra"]) <= 1e-9 * max(1.0, costs["dijkstra"]) for m in modes), \
            (name, start, goal, costs)
    return total


def report(name, shape, count, total):
    base = total["dijkstra"]
    cells = "  ".join(f"{total[m] * 1e3:9.2f}" for m in MODES)
    ratios = "  ".join(f"{base / total[m]:5.2f}x" for m in MODES[1:])
    print(f"{name:22s} {shape[1]:5d} x {shape[0]:<5d} {count:4d}  {cells}   {ratios}", flush=True)


def run(pairs=20, runs=3, random_sizes=(2000, 4000), movingai=True, ros=True):
    print(f"## Point to point: ms summed over the queries (fastest of {runs} runs per query and mode, one "
          f"process); default / mode")
    print(f"{'map':22s} {'size':13s} {'qs':>4s}  " + "  ".join(f"{m:>9s}" for m in MODES) + "   "
          + "  ".join(f"{m:>6s}" for m in MODES[1:]))
    ratios = {mode: [] for mode in MODES[1:]}

    def one(name, grid, queries):
        total = bench_fastest(name, grid, queries, runs)
        report(name, grid.shape, len(queries), total)
        for mode in MODES[1:]:
            ratios[mode].append(total["dijkstra"] / total[mode])

    for name, grid, queries in bench_maps(pairs, random_sizes, movingai, ros):
        one(name, grid, queries)
    for mode, values in ratios.items():
        print(f"{mode}: default / {mode} from {min(values):.2f}x to {max(values):.2f}x over {len(values)} maps "
              f"({sum(v < 1.0 for v in values)} slower than the default)")
    print()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=20, help="queries per map")
    parser.add_argument("--runs", type=int, default=3, help="runs per query and mode (the fastest counts)")
    parser.add_argument("--random-sizes", type=int, nargs="*", default=[2000, 4000])
    args = parser.parse_args(argv)
    run(args.pairs, args.runs, tuple(args.random_sizes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
