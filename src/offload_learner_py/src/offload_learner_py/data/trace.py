"""A trace of real local planning times: random free start/goal pairs on a real map, each planned by
the real planner and timed, with the input size d_t of the pair. The synthetic datasets of the paper
(eq. 13-15) are built on such a trace, so l_local is always a measured time.

Record one with
    python -m offload_learner_py.data.trace --map /path/map.yaml --queries 300 --seed 1 --out trace.npz
"""
import argparse
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, Optional

import numpy as np

from offload_learner_py.data.npz_io import VersionedNpz
from offload_learner_py.core.state import input_size_from_cells

TRACE_FORMAT = "offload_learner_py.trace/1"
_ARRAYS = ("start_cell", "goal_cell", "distance_m", "input_size", "local_s", "planner_s", "expansions")
_INTEGER_ARRAYS = ("start_cell", "goal_cell", "expansions")


@dataclass
class PlanningTrace(VersionedNpz):
    NPZ_FORMAT, NPZ_ARRAYS, NPZ_WHAT = TRACE_FORMAT, _ARRAYS, "planning trace"
    start_cell: np.ndarray    # N x 2 int (x, y)
    goal_cell: np.ndarray     # N x 2 int (x, y)
    distance_m: np.ndarray    # |AB| in metres
    input_size: np.ndarray    # normalised d_t (eq. 11-12 over the map's cell count)
    local_s: np.ndarray       # wall time of the whole plan() call, seconds
    planner_s: np.ndarray     # time the planner reports for its own search (nan if it reports none)
    expansions: np.ndarray    # cells the planner settled (-1 if it reports none)
    metadata: Dict = field(default_factory=dict)

    def __post_init__(self):
        arrays = {}
        for name in _ARRAYS:
            try:
                array = np.asarray(getattr(self, name))
                if name in _INTEGER_ARRAYS:
                    if array.dtype.kind not in "biu" and not (array.size == 0 and array.dtype.kind == "f"):
                        raise ValueError(f"dtype {array.dtype} is not an integer type")
                    array = array.astype(np.int64)
                else:
                    array = array.astype(np.float64)
            except (TypeError, ValueError) as error:
                raise ValueError(f"trace array {name} is not {'integer' if name in _INTEGER_ARRAYS else 'numeric'}: "
                                 f"{error}") from error
            expected = 2 if name in ("start_cell", "goal_cell") else 1
            if array.ndim != expected or (expected == 2 and array.shape[1] != 2):
                raise ValueError(f"trace array {name} must be {'N x 2' if expected == 2 else 'one-dimensional'}, "
                                 f"got shape {array.shape}")
            arrays[name] = array
            setattr(self, name, array)
        lengths = {name: len(array) for name, array in arrays.items()}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"trace arrays have different lengths: {lengths}")
        for name, ok, rule in (("distance_m", np.isfinite(self.distance_m) & (self.distance_m >= 0), "finite and >= 0"),
                               ("input_size", np.isfinite(self.input_size) & (self.input_size >= 0), "finite and >= 0"),
                               ("local_s", np.isfinite(self.local_s) & (self.local_s > 0), "finite and > 0"),
                               ("planner_s", np.isnan(self.planner_s) | (np.isfinite(self.planner_s)
                                                                        & (self.planner_s >= 0)), "nan or >= 0")):
            bad = np.flatnonzero(~ok)
            if len(bad):
                raise ValueError(f"trace array {name} must be {rule} in every row; row {bad[0]} is "
                                 f"{getattr(self, name)[bad[0]]}")

    def __len__(self) -> int:
        return len(self.local_s)



def free_cell_coordinates(grid: np.ndarray, lethal_threshold: int = 50, unknown_is_obstacle: bool = True) -> np.ndarray:
    """N x 2 (x, y) of every cell the planner may start or end on, by the planner's own rule (its binding)."""
    from offload_planner_cpp import free_cells as planner_free_cells

    ys, xs = np.nonzero(planner_free_cells(grid, lethal_threshold, unknown_is_obstacle))
    return np.stack([xs, ys], axis=1)


def record_trace(plan: Callable, grid: np.ndarray, resolution_m: float, queries: int,
                 rng: np.random.Generator, map_name: str = "", clock: Callable[[], float] = time.perf_counter,
                 max_attempts: Optional[int] = None, progress: Optional[Callable[[int, int], None]] = None,
                 **plan_options) -> PlanningTrace:
    """Plan `queries` random free start/goal pairs with `plan(grid, start, goal, **plan_options)` and
    time each call. Unreachable pairs (RuntimeError, e.g. offload_planner_cpp.NoPathError) are
    skipped and counted; bad input (ValueError) is a bug and propagates."""
    if queries < 1:
        raise ValueError(f"queries must be >= 1, got {queries}")
    candidates = free_cell_coordinates(grid, plan_options.get("lethal_threshold", 50), plan_options.get("unknown_is_obstacle", True))
    if len(candidates) < 2:
        raise ValueError("the map has fewer than two free cells")
    cell_count = int(grid.shape[0] * grid.shape[1])
    max_attempts = max_attempts or 10 * queries
    rows = {name: [] for name in _ARRAYS}
    attempts = unreachable = 0
    while len(rows["local_s"]) < queries:
        if attempts >= max_attempts:
            raise RuntimeError(f"only {len(rows['local_s'])} of {queries} pairs were reachable after "
                               f"{attempts} attempts")
        attempts += 1
        start, goal = (tuple(int(v) for v in candidates[i]) for i in rng.choice(len(candidates), 2, replace=False))
        began = clock()
        try:
            result = plan(grid, start, goal, **plan_options)
        except ValueError:
            raise
        except RuntimeError:
            unreachable += 1
            continue
        elapsed_s = clock() - began
        distance_cells = float(np.hypot(goal[0] - start[0], goal[1] - start[1]))
        rows["start_cell"].append(start)
        rows["goal_cell"].append(goal)
        rows["distance_m"].append(distance_cells * resolution_m)
        rows["input_size"].append(input_size_from_cells(start, goal, resolution_m, cell_count))
        rows["local_s"].append(elapsed_s)
        rows["planner_s"].append(float(getattr(result, "seconds", np.nan)))
        rows["expansions"].append(int(getattr(result, "expansions", -1)))
        if progress is not None:
            progress(len(rows["local_s"]), queries)
    metadata = {"map_name": map_name, "resolution_m": resolution_m, "map_cell_count": cell_count,
                "map_shape": list(grid.shape), "queries": queries, "attempts": attempts,
                "unreachable": unreachable, "plan_options": plan_options}
    return PlanningTrace(start_cell=np.array(rows["start_cell"], dtype=np.int64).reshape(-1, 2),
                         goal_cell=np.array(rows["goal_cell"], dtype=np.int64).reshape(-1, 2),
                         distance_m=np.array(rows["distance_m"]), input_size=np.array(rows["input_size"]),
                         local_s=np.array(rows["local_s"]), planner_s=np.array(rows["planner_s"]),
                         expansions=np.array(rows["expansions"], dtype=np.int64), metadata=metadata)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Record real local planning times on a map_server map.")
    parser.add_argument("--map", required=True, help="map_server YAML file")
    parser.add_argument("--queries", type=int, default=300)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", required=True, help="output .npz")
    args = parser.parse_args(argv)
    import offload_planner_cpp  # the real planner; imported here so the core never needs it
    from offload_planner_cpp import maps

    occupancy_map = maps.load_map_server_yaml(args.map)

    def report(done: int, total: int) -> None:
        if done % 25 == 0 or done == total:
            print(f"planned {done}/{total}", file=sys.stderr, flush=True)

    trace = record_trace(offload_planner_cpp.plan, occupancy_map.grid, occupancy_map.resolution, args.queries,
                         np.random.default_rng(args.seed), map_name=args.map, progress=report)
    trace.metadata["seed"] = args.seed
    trace.save_npz(args.out)
    print(f"wrote {args.out}: {len(trace)} plans, local_s median {np.median(trace.local_s) * 1e3:.2f} ms, "
          f"input_size {trace.input_size.min():.3g}..{trace.input_size.max():.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
