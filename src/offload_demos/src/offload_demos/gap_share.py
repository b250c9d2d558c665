"""The share of the hindsight-threshold-to-oracle gap a policy closes, with an interval over rounds of repeats that
says whether the bench can tell, and the same pooled over several bench-policies runs.

A round is repeat r of every policy, minutes apart on one state of the machine (offload_demos.mean_ratio: the run,
not the request, is the unit of replication). In round r the policy gains A_r = threshold_r - policy_r on the best
threshold in hindsight, of a gap B_r = threshold_r - oracle_r; the share is mean(A) / mean(B). Its interval is
Fieller's: the shares s for which a paired t-test does not reject mean(A - s B) = 0 at the level, so a share is
judged by the same test as "the policy's mean is at the point s of the way from the threshold to the oracle". When
the gap itself is not told apart from zero at the level (the oracle's lead on the threshold is inside the spread
between rounds), every share passes that test: there is no interval, and no share, however large, is evidence.

    python -m offload_demos.gap_share runs/bench-policies-<time> [runs/bench-policies-<time> ...]
"""
import argparse
import json
import math
import pathlib
import sys
from typing import NamedTuple, Optional, Sequence

import numpy as np
from scipy.stats import t as student_t

BASELINE, ORACLE = "threshold_best", "oracle"


class GapShare(NamedTuple):
    share: Optional[float]    # mean gain over mean gap (None: no gap on average)
    low: Optional[float]      # None: one round, or the gap not told apart from zero (see why)
    high: Optional[float]
    rounds: int
    why: str = ""             # why there is no interval
    level: float = 0.95

    def describe(self) -> str:
        share = "n/a" if self.share is None else f"{100 * self.share:.0f} %"
        if self.low is None:
            return f"{share} over {self.rounds} rounds ({self.why})"
        return (f"{share} over {self.rounds} rounds ({100 * self.level:.0f} % interval {100 * self.low:.0f} to "
                f"{100 * self.high:.0f} %)")


def gap_share(policy_means: Sequence[float], baseline_means: Sequence[float], oracle_means: Sequence[float],
              level: float = 0.95) -> GapShare:
    """A policy's share of the gap from its round-mates' threshold to their oracle, from each round's run means."""
    means = np.asarray([policy_means, baseline_means, oracle_means], dtype=np.float64)
    if means.ndim != 2 or not means.shape[1] or not np.all(np.isfinite(means)):
        raise ValueError("gap_share needs one finite run mean per round for the policy, the threshold and the oracle")
    gain, gap = means[1] - means[0], means[1] - means[2]
    rounds = len(gain)
    a, b = float(gain.mean()), float(gap.mean())
    share = a / b if b > 1e-12 else None
    if rounds < 2:
        return GapShare(share, None, None, rounds, "one round: nothing says how far the share moves between rounds",
                        level)
    (saa, sab), (_, sbb) = np.cov(gain, gap, ddof=1) / rounds     # the covariance of the two means
    t2 = float(student_t.ppf((1 + level) / 2, rounds - 1)) ** 2
    # (a - s b)^2 <= t^2 var(a - s b): a quadratic in s, bounded only when b stands clear of zero.
    lead, half, const = b * b - t2 * sbb, a * b - t2 * sab, a * a - t2 * saa
    if lead <= 0 or share is None:
        return GapShare(share, None, None, rounds, "the gap is not told apart from zero over these rounds", level)
    root = math.sqrt(max(half * half - lead * const, 0.0))
    return GapShare(share, (half - root) / lead, (half + root) / lead, rounds, "", level)


def rounds_of(results: dict, policy: str):
    """The run means of (policy, threshold_best, oracle) of one bench's results, repeat by repeat; None when one is
    missing or their repeats differ."""
    runs = [results.get("policies", {}).get(name, {}).get("run_means_s") for name in (policy, BASELINE, ORACLE)]
    if any(not means for means in runs) or len({len(means) for means in runs}) != 1:
        return None
    return runs


def pooled(bench_results: Sequence[dict], policy: str, level: float = 0.95) -> Optional[GapShare]:
    """The policy's gap share over every round of every bench that ran it with the threshold and the oracle."""
    rounds = [[], [], []]
    for results in bench_results:
        runs = rounds_of(results, policy)
        for pooled_runs, means in zip(rounds, runs or ()):
            pooled_runs.extend(means)
    return gap_share(*rounds, level=level) if rounds[0] else None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bench_dirs", nargs="+", type=pathlib.Path)
    parser.add_argument("--level", type=float, default=0.95)
    args = parser.parse_args(argv)
    benches = []
    for bench in args.bench_dirs:
        try:
            benches.append(json.loads((bench / "results.json").read_text()))
        except (OSError, ValueError) as err:
            parser.error(f"{bench}: no readable results.json ({err})")
    policies = sorted({name for results in benches for name in results.get("policies", {})} - {BASELINE, ORACLE})
    print(f"share of the {BASELINE}-to-{ORACLE} gap closed, pooled over the rounds of {len(benches)} bench(es)")
    for policy in policies:
        try:
            share = pooled(benches, policy, args.level)
        except ValueError as err:      # a run that answered nothing has no mean
            print(f"{policy:<16}no share: {err}")
            continue
        if share is not None:
            print(f"{policy:<16}{share.describe()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
