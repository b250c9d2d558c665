"""Any-angle against the default (part of `make bench-planner`, or alone:
`python -m offload_demos.bench_planner_any_angle`): per map, the planner core's time summed over the same
queries for the default (8-connected, the two waves) and for any_angle=True on the same search, query by query
in this one process, their ratio, and the path lengths against the 8-connected optimum. Every any-angle
path is checked with path_clear (the core's line-of-sight rule: no blocked cell, no blocked corner) and
against the optimum (never longer). Maps as bench_planner_p2p's."""
import argparse
import sys

from offload_planner_cpp import path_clear, plan

from offload_demos.bench_planner_p2p import bench_maps

MODES = {"default": {}, "any-angle": {"any_angle": True}}


def bench_any_angle(name, grid, pairs, runs):
    """(time summed per mode, length summed per mode): the fastest of `runs` core times per query and mode,
    the modes' order turning from query to query."""
    total = {mode: 0.0 for mode in MODES}
    length = {mode: 0.0 for mode in MODES}
    for options in MODES.values():   # buffers sized for this map, not timed
        plan(grid, *pairs[0], **options)
    names = list(MODES)
    for k, (start, goal) in enumerate(pairs):
        for mode in names[k % 2:] + names[:k % 2]:
            results = [plan(grid, start, goal, **MODES[mode]) for _ in range(runs)]
            total[mode] += min(r.seconds for r in results)
            length[mode] += results[0].cost
            if mode == "any-angle":
                path = results[0].path
                assert path_clear(grid, path) == -1, (name, start, goal)
                assert tuple(path[0]) == tuple(start) and tuple(path[-1]) == tuple(goal), (name, start, goal)
        assert length["any-angle"] <= length["default"] * (1 + 1e-9), (name, start, goal)
    return total, length


def run(pairs=20, runs=3, random_sizes=(2000, 4000), movingai=True, ros=True):
    print(f"## Any-angle against the default: ms summed over the queries (fastest of {runs} runs per query and "
          f"mode, one process), lengths against the 8-connected optimum")
    print(f"{'map':22s} {'size':13s} {'qs':>4s}  {'default':>9s}  {'any-angle':>9s}  {'ratio':>6s}  "
          f"{'8-conn length':>13s}  {'any-angle':>9s}")
    ratios = []

    def one(name, grid, queries):
        total, length = bench_any_angle(name, grid, queries, runs)
        ratio = total["any-angle"] / total["default"]
        ratios.append(ratio)
        print(f"{name:22s} {grid.shape[1]:5d} x {grid.shape[0]:<5d} {len(queries):4d}  "
              f"{total['default'] * 1e3:9.2f}  {total['any-angle'] * 1e3:9.2f}  {ratio:5.2f}x  "
              f"{length['default']:13.1f}  {100 * (length['any-angle'] / length['default'] - 1):+8.2f}%", flush=True)

    for name, grid, queries in bench_maps(pairs, random_sizes, movingai, ros):
        one(name, grid, queries)
    print(f"any-angle / default from {min(ratios):.2f}x to {max(ratios):.2f}x over {len(ratios)} maps "
          f"({sum(r > 1.5 for r in ratios)} above 1.5x)")
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
