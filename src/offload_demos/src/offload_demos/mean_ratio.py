"""How much slower one policy's mean delivered latency is than a baseline's, with an interval that says whether the
bench can tell. A bar such as "within 3 % of always-local" sits below the spread between runs: on a loaded robot core
the same policy's runs of 200 requests differ by up to 25 % (bench-policies' "run means"), while the requests within a
run are nearly independent (block means of 5-50 requests vary 1.0-1.2 times as i.i.d. requests would). The noise is
the machine's state over minutes, so the run, not the request, is the unit of replication: resampling requests gives
intervals that exclude the truth.

bench-policies runs each repeat as a round, every policy once, minutes apart, so repeat r of the policy and of the
baseline met the same state of the machine: a pair. The ratio is the policy's pooled mean over the baseline's (the
table's figures); its interval is Student's t on the pairs' log ratios, as wide as the pairs disagree, with one pair
no interval at all."""
import math
from typing import Dict, NamedTuple, Optional, Sequence

import numpy as np
from scipy.stats import t as student_t


class MeanRatio(NamedTuple):
    ratio: float
    low: Optional[float]      # None with a single pair: nothing says how far the ratio moves between runs
    high: Optional[float]
    pairs: int

    def as_dict(self) -> dict:
        return self._asdict()

    def describe(self, policy: str, baseline: str) -> str:
        interval = "no interval from one pair of runs (--repeats 2 or more)" if self.low is None else \
            f"95 % interval {self.low:.3f}-{self.high:.3f} over {self.pairs} pairs of runs"
        return f"{policy}: mean {self.ratio:.3f}x {baseline}'s ({interval})"


def mean_ratio(runs: Sequence[Sequence[float]], baseline_runs: Sequence[Sequence[float]],
               level: float = 0.95) -> MeanRatio:
    """The ratio of `runs`' pooled mean delivered latency to `baseline_runs`', each a list of runs' latencies, paired
    by position (repeat r with repeat r), with a `level` interval."""
    if not runs or len(runs) != len(baseline_runs):
        raise ValueError(f"mean_ratio pairs runs: got {len(runs)} and {len(baseline_runs)}")
    runs = [np.asarray(run, dtype=np.float64) for run in runs]
    baseline_runs = [np.asarray(run, dtype=np.float64) for run in baseline_runs]
    for run in [*runs, *baseline_runs]:
        if not len(run) or not np.all(np.isfinite(run)) or run.mean() <= 0:
            raise ValueError("mean_ratio needs runs of finite latencies with a positive mean")
    ratio = float(np.concatenate(runs).mean() / np.concatenate(baseline_runs).mean())
    pairs = len(runs)
    if pairs < 2:
        return MeanRatio(ratio, None, None, pairs)
    logs = np.log([run.mean() / base.mean() for run, base in zip(runs, baseline_runs)])
    half = float(student_t.ppf((1 + level) / 2, pairs - 1)) * float(np.std(logs, ddof=1)) / math.sqrt(pairs)
    return MeanRatio(ratio, ratio * math.exp(-half), ratio * math.exp(half), pairs)


def ratios_to(runs: Dict[str, Sequence[Sequence[float]]], baseline: str) -> Dict[str, Optional[dict]]:
    """Every other policy's MeanRatio to `baseline` (as a dict), from each policy's runs in repeat order; None (and a
    line saying why) for a policy whose runs cannot be compared (a run without an answered request), so a bench
    that ran for an hour still writes its results. Empty without the baseline."""
    if baseline not in runs:
        return {}
    ratios = {}
    for name, policy_runs in runs.items():
        if name == baseline:
            continue
        try:
            ratios[name] = mean_ratio(policy_runs, runs[baseline]).as_dict()
        except ValueError as error:
            print(f"{name}: no ratio to {baseline}: {error}", flush=True)
            ratios[name] = None
    return ratios
