"""Off-policy evaluation from a robot's own logs: how would another policy (a retrained checkpoint, a
baseline) have done on the requests the robot served, judged before deploying it, and is a new model not
worse than the one in use (`not_worse`, the gate a fleet learner publishes by).

Every logged request carries its action, the probability with which the logging policy chose it (its
propensity) and the measured latency of the side it took; a probe request (every request in learning mode,
a probe_rate share when deployed, drawn independently of the state) has both sides measured. Probes are
scored directly; inverse propensity scoring (IPS), its self-normalised form (SNIPS) and the doubly robust
estimator (DR) serve only the requests with one side measured, and the parts combine into one estimate
whose 95 % interval accounts for both (off_policy_combined). Where the logs cannot say (no probes of
requests whose needed side the logger never took, too few effective samples) the estimate is "n/a".

The modules, by job: off_policy_intervals (Estimate, intervals, combining parts), off_policy_estimators
(IPS, SNIPS, DR, the latency model), off_policy_steps (LoggedSteps from a RequestLog), off_policy_combined
(estimates, evaluate_policy, not_worse), this one (the table and the command line):

    python -m offload_learner_py.offline.off_policy BAGS... [--model NEW.pt [--current CURRENT.pt]]
"""
import argparse
import json
import sys
from dataclasses import asdict
from typing import Dict, Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.dqn import greedy_actions
from offload_learner_py.offline.off_policy_combined import ESTIMATORS, GATE_ESTIMATOR, MIN_EFFECTIVE_SAMPLES, \
    MIN_PROBE_ROWS, RARE, estimate, evaluate_policy, needed_propensity, not_worse, strata  # noqa: F401  (the API, from one place)
from offload_learner_py.offline.off_policy_estimators import _features, cross_fitted_latencies, doubly_robust, \
    effective_sample_size, fit_latency_model, ips, snips, target_probabilities  # noqa: F401  (_features: schema test)
from offload_learner_py.offline.off_policy_intervals import Z_95, Estimate, clipped, not_available, \
    wilson_interval  # noqa: F401
from offload_learner_py.offline.off_policy_steps import FORCED_LOCAL, LoggedSteps  # noqa: F401

_EMPTY = not_available("")


def to_jsonable(result: Dict) -> Dict:
    return {key: asdict(value) if isinstance(value, Estimate) else value for key, value in result.items()}


def format_results(results: Dict[str, Dict]) -> str:
    """One line per policy: mean latency in ms by SNIPS (the gate's), DR and IPS (probes direct, the other
    requests by that estimator) and on the probes alone, how many requests were probes and how many the logging policy
    could not inform, the effective sample size of the requests with one side measured, the accuracy on
    the probes in %. Then why any figure is n/a."""
    lines = [f"{'policy':16}" + "".join(f"{e.upper() + ' (ms)':>24}" for e in ESTIMATORS)
             + f"{'probes only (ms)':>24}{'probes':>8}{'unsupp.':>9}{'ESS':>6}{'accuracy, probes (%)':>22}"]
    reasons = []
    for name, result in results.items():
        ess = result.get("effective_sample_size", float("nan"))
        lines.append(f"{name:16}" + "".join(f"{result.get(f'latency_{e}_s', _EMPTY).format(1000):>24}"
                                            for e in ESTIMATORS)
                     + f"{result.get('latency_probe_s', _EMPTY).format(1000):>24}"
                     + f"{result.get('probe_steps', 0):>8}{result.get('unsupported_steps', 0):>9}"
                     + (f"{ess:6.0f}" if np.isfinite(ess) else f"{'-':>6}")
                     + f"{result.get('accuracy_probe', _EMPTY).format(100, 1):>22}")
        why = {result[f"latency_{e}_s"].reason for e in ESTIMATORS
               if f"latency_{e}_s" in result and result[f"latency_{e}_s"].reason}
        reasons += [f"n/a for {name}: {reason}" for reason in sorted(why)]
    lines.append(f"(probes scored directly; the other requests by {' / '.join(e.upper() for e in ESTIMATORS)} where "
                 f"their effective sample size is at least {MIN_EFFECTIVE_SAMPLES}, else by the probes among them; "
                 f"unsupp.: requests needing a side the logging policy could not take, which their probes stand "
                 f"for; 95 % intervals)")
    lines += reasons
    censored = max((result.get("censored_steps", 0) for result in results.values()), default=0)
    if censored:
        lines.append(f"note: {censored} hedged requests enter at their delivery time, a lower bound of the taken "
                     "side's latency: the other side answered first and the taken side was cancelled")
    return "\n".join(lines)


def candidate_actions(steps: LoggedSteps, model: Optional[str] = None) -> Dict[str, np.ndarray]:
    """Actions of always-local, always-cloud and, with a checkpoint, its greedy policy."""
    candidates = {"always_local": np.full(len(steps), LOCAL), "always_cloud": np.full(len(steps), CLOUD)}
    if model:
        candidates["model"] = checkpoint_actions(model, steps)
    return candidates


def checkpoint_actions(path: str, steps: LoggedSteps) -> np.ndarray:
    from offload_learner_py.core.checkpoint import load_checkpoint

    return greedy_actions(load_checkpoint(path).q_values(steps.states))


def format_gate(accepted: bool, difference: Estimate, margin_s: float) -> str:
    verdict = "not worse: yes" if accepted else "not worse: no"
    why = f" ({difference.reason})" if difference.reason else ""
    return (f"{verdict}: mean latency of --model minus --current {difference.format(1000)} ms{why}, "
            f"accepted when the interval's upper end is at most the margin {margin_s * 1000:.2f} ms")


def main(argv=None) -> int:
    from offload_learner_py.data.bags import read_bags
    from offload_learner_py.offline.output import terminal_text

    parser = argparse.ArgumentParser(description="Mean latency of always-local, always-cloud and a checkpoint's "
                                                 "greedy policy on the bags' requests: probes measured directly, "
                                                 "the other requests by IPS, SNIPS and DR from the logged "
                                                 "propensities; with --current, whether --model is not worse.")
    parser.add_argument("bags", nargs="+", help="bag files, globs or directories")
    parser.add_argument("--model", help="a DQN checkpoint to evaluate")
    parser.add_argument("--current", help="the checkpoint in use: judge whether --model is not worse than it")
    parser.add_argument("--margin-ms", type=float, default=0.0, help="how much slower still counts as not worse")
    parser.add_argument("--json", help="write the estimates here")
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args(argv)
    if args.current and not args.model:
        parser.error("--current needs --model (the new checkpoint)")
    data = read_bags(args.bags, workers=args.workers)
    print(terminal_text(data.report.format()), file=sys.stderr)
    if len(data.log) == 0:
        print("error: no request read from the bags", file=sys.stderr)
        return 2
    steps = LoggedSteps.from_log(data.log)
    predicted = steps.latency_model()
    try:
        candidates = candidate_actions(steps, args.model)
        current = checkpoint_actions(args.current, steps) if args.current else None
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    results = {name: evaluate_policy(steps, actions, predicted) for name, actions in candidates.items()}
    print(format_results(results))
    out = {name: to_jsonable(result) for name, result in results.items()}
    if current is not None:
        accepted, difference = not_worse(steps, candidates["model"], current, args.margin_ms / 1000, predicted=predicted)
        print(format_gate(accepted, difference, args.margin_ms / 1000))
        out["gate"] = {"accepted": accepted, "difference_s": asdict(difference), "margin_s": args.margin_ms / 1000}
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(out, handle, indent=2)
    return 1 if data.report.failed else 0   # a bag that could not be read is not a documented skip


if __name__ == "__main__":
    sys.exit(main())
