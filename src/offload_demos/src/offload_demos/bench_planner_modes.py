"""The planner's modes side by side (part of `make bench-planner`): time, cells settled, path length against
the 8-connected optimum, and cost against scipy on the same (weighted, inflated) graph, in one run; and a
figure of the same plan in each mode on the Husky playpen."""
import statistics
import time
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.sparse import csgraph

import offload_planner_cpp
from offload_planner_cpp import inflate, path_clear, plan
from offload_demos.grid_graph import grid_graph
from offload_planner_cpp.maps import load_map

# name: plan() keywords. Radii in cells (the Husky playpen has 5 cm cells: a 0.2 m robot, 0.6 m inflation).
INFLATION = dict(robot_radius_cells=4.0, inflation_radius_cells=12.0, inflation_decay=0.5)
# A random map's free cells are mostly within a few cells of an obstacle: inflation there grades only.
RANDOM_INFLATION = dict(robot_radius_cells=0.0, inflation_radius_cells=3.0, inflation_decay=0.5)


def modes(inflation: dict) -> dict:
    return {
        "dijkstra": dict(algorithm="dijkstra"),
        "auto (the default)": {},
        "astar": dict(algorithm="astar"),
        "any-angle": dict(any_angle=True),
        "cost-aware + inflation": dict(cost_factor=3.0, **inflation),
        "cost-aware A* + inflation": dict(algorithm="astar", cost_factor=3.0, **inflation),
        "cost-aware any-angle + inflation": dict(any_angle=True, cost_factor=3.0, **inflation),
    }


def median_of(runs, fn):
    """Median wall time of `runs` calls of fn, and its last result (bench_planner.py uses it too)."""
    times, out = [], None
    for _ in range(runs):
        started = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - started)
    return statistics.median(times), out


def _pairs(grid, count, rng, min_apart, clearance=0.0):
    free = offload_planner_cpp.free_cells(grid)
    labels, _ = ndimage.label(free, structure=np.ones((3, 3)))
    biggest = labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1
    if clearance:
        biggest &= ndimage.distance_transform_edt(free) >= clearance
    cells = np.argwhere(biggest)[:, ::-1]
    pairs = []
    while len(pairs) < count:
        s, g = (tuple(int(v) for v in cells[k]) for k in rng.choice(len(cells), 2, replace=False))
        if np.hypot(s[0] - g[0], s[1] - g[1]) >= min_apart:
            pairs.append((s, g))
    return pairs


def bench_modes(name, grid, pairs, runs, inflation):
    """Prints one row per mode: median time per plan, cells settled, length against the 8-connected optimum
    and the weighted cost checked against scipy on the same graph (one full scipy search per start)."""
    print(f"### {name}, {len(pairs)} pairs, median of {runs} runs each")
    print(f"{'mode':34s} {'ms/plan':>8s} {'settled':>10s} {'length vs 8-conn':>17s} {'cost = scipy':>13s}")
    optimum = {pair: plan(grid, *pair).cost for pair in pairs}
    graphs = {}
    for mode, options in modes(inflation).items():
        times, settled, ratios, exact = [], 0, [], 0
        for pair in pairs:
            seconds, result = median_of(runs, lambda: plan(grid, *pair, **options))
            times.append(seconds)
            settled += result.expansions
            ratios.append(result.cost / optimum[pair])
            if options.get("any_angle"):
                assert path_clear(grid, result.path) == -1
            if not options.get("any_angle"):
                key = (options.get("cost_factor", 0.0), options.get("inflation_radius_cells", 0.0))
                if key not in graphs:
                    inflated = inflate(grid, options.get("robot_radius_cells", 0.0),
                                       options.get("inflation_radius_cells", 0.0),
                                       options.get("inflation_decay", 0.5)) if key[1] else grid
                    graphs[key] = grid_graph(inflated, cost_factor=key[0])
                width = grid.shape[1]
                (s, g) = pair
                distance = csgraph.dijkstra(graphs[key], indices=s[1] * width + s[0])[g[1] * width + g[0]]
                assert abs(distance - result.weighted_cost) <= 1e-9 * max(1.0, distance), (mode, distance, result)
                exact += 1
        shown = f"{exact}/{len(pairs)}" if exact else "-"
        print(f"{mode:34s} {statistics.median(times) * 1e3:8.2f} {settled // len(pairs):10d} "
              f"{100 * (np.mean(ratios) - 1):+16.2f}% {shown:>13s}")
    print()


def figure(grid, pair, out: Path, resolution: float) -> None:
    """The same plan in each mode on `grid`, cropped to the plans, over the inflated costs."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = {"dijkstra (8-connected)": dict(algorithm="dijkstra"), "any-angle": dict(any_angle=True),
             "cost-aware + inflation": dict(cost_factor=3.0, **INFLATION),
             "cost-aware any-angle + inflation": dict(any_angle=True, cost_factor=3.0, **INFLATION)}
    paths = {name: plan(grid, *pair, **options) for name, options in shown.items()}
    cells = np.concatenate([p.path for p in paths.values()])
    x0, y0 = np.maximum(cells.min(axis=0) - 25, 0)
    x1, y1 = np.minimum(cells.max(axis=0) + 25, np.array(grid.shape[::-1]) - 1)
    inflated = inflate(grid, INFLATION["robot_radius_cells"], INFLATION["inflation_radius_cells"],
                       INFLATION["inflation_decay"])[y0:y1 + 1, x0:x1 + 1].astype(float)
    crop = grid[y0:y1 + 1, x0:x1 + 1]
    picture = np.where(crop < 0, 0.75, np.where(crop >= 50, 0.0, 1.0 - 0.35 * np.clip(inflated, 0, 100) / 100))
    picture = np.where((crop >= 0) & (crop < 50) & (inflated >= 100), 0.55, picture)
    fig, ax = plt.subplots(figsize=(8, 8 * (y1 - y0 + 1) / (x1 - x0 + 1) + 0.6), dpi=110)
    ax.imshow(picture, cmap="gray", vmin=0, vmax=1, origin="lower", interpolation="nearest")
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:red"]
    for colour, (name, result) in zip(colours, paths.items()):
        xs, ys = result.path[:, 0] - x0, result.path[:, 1] - y0
        ax.plot(xs, ys, "-", color=colour, lw=1.8,
                label=f"{name}: {result.cost * resolution:.2f} m, {result.expansions:,} cells settled")
    ax.plot(*(np.array(pair[0]) - (x0, y0)), "ko", ms=6)
    ax.plot(*(np.array(pair[1]) - (x0, y0)), "k*", ms=10)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.01), fontsize=8, frameon=False)
    ax.set_title("Husky playpen: the same plan in each mode (grey: inflation, robot radius 0.2 m, 0.6 m)",
                 fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, bbox_inches="tight")
    plt.close(fig)


def run(runs: int, figure_out: Path = None, husky_yaml: Path = None) -> None:
    rng = np.random.default_rng(0)
    grid = (rng.random((600, 600)) < 0.2).astype(np.int8) * 100
    bench_modes("600 x 600, 20 % random obstacles (seed 0), inflation radius 3 cells", grid,
                _pairs(grid, 12, rng, 300), runs, RANDOM_INFLATION)
    if husky_yaml is None:
        return
    husky = load_map(husky_yaml)
    pairs = _pairs(husky.grid, 12, rng, 150, clearance=INFLATION["robot_radius_cells"] + 1)
    bench_modes(f"{husky.name} {husky.grid.shape[1]} x {husky.grid.shape[0]}, known free space, robot radius 4 "
                f"cells, inflation 12", husky.grid, pairs, runs, INFLATION)
    if figure_out is not None:
        figure(husky.grid, pairs[0], figure_out, husky.resolution)
        print(f"figure: {figure_out}")
