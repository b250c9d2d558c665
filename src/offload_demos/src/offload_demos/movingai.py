"""Check the planner against a MovingAI scenario file's optimal lengths.

    python -m offload_demos.movingai MAP SCEN [--limit N] [--algorithm NAME]

Prints one line: queries checked, mismatches, max absolute error. Exits 1 on any mismatch."""
import argparse
import sys
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from offload_planner_cpp import ALGORITHM_NAMES, OPTION_DEFAULTS, plan
from offload_planner_cpp.maps import Scenario, length_tolerance, load_movingai_map, load_scenarios


@dataclass
class CheckSummary:
    checked: int
    mismatches: int
    max_abs_error: float
    expansions: int
    seconds: float


def spread(scenarios: Sequence[Scenario], limit: int) -> Sequence[Scenario]:
    """`limit` queries evenly spaced through the file, so short and long buckets are both covered."""
    if limit <= 0 or limit >= len(scenarios):
        return scenarios
    picks = np.linspace(0, len(scenarios) - 1, limit).round().astype(int)
    return [scenarios[i] for i in picks]


def check(grid: np.ndarray, scenarios: Sequence[Scenario], **options) -> CheckSummary:
    """Plans every scenario with `options` (plan()'s keywords, e.g. algorithm="jps")."""
    summary = CheckSummary(0, 0, 0.0, 0, 0.0)
    for scenario in scenarios:
        result = plan(grid, scenario.start, scenario.goal, **options)
        error = abs(result.cost - scenario.optimal_length)
        summary.checked += 1
        summary.mismatches += error > length_tolerance(scenario)
        summary.max_abs_error = max(summary.max_abs_error, error)
        summary.expansions += result.expansions
        summary.seconds += result.seconds
    return summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", help="MovingAI .map file")
    parser.add_argument("scen", help="MovingAI .map.scen file")
    parser.add_argument("--limit", type=int, default=0, help="check N queries spread over the file (0: all)")
    parser.add_argument("--algorithm", default=OPTION_DEFAULTS["algorithm"], choices=ALGORITHM_NAMES,
                        help="the planner's algorithm (default: the planner's default)")
    args = parser.parse_args(argv)
    occupancy = load_movingai_map(args.map)
    scenarios = spread(load_scenarios(args.scen), args.limit)
    summary = check(occupancy.grid, scenarios, algorithm=args.algorithm)
    print(f"{occupancy.name}: {summary.checked} queries checked, {summary.mismatches} mismatches, "
          f"max abs error {summary.max_abs_error:.3g}, {summary.expansions / max(summary.seconds, 1e-9) / 1e6:.1f} "
          f"M expansions/s")
    return 1 if summary.mismatches else 0


if __name__ == "__main__":
    sys.exit(main())
