"""Off-policy evaluation from a robot's own logs: how would another policy (a retrained checkpoint, a
baseline) have done on the requests the robot served, judged before deploying it.

Every logged request carries its action and the probability with which the logging policy chose it
(its propensity), and the measured latency of the side it took. Inverse propensity scoring (IPS)
reweights those latencies by pi(a|s) / mu(a|s); the doubly robust estimator (DR) adds a model of the
latency per action (ridge regression on the state, cross-fitted so no request scores its own fit)
and corrects that model with the same weights. Both use only the taken side's latency, so they work
at any probe rate. Intervals are 95 % intervals of the per-request terms: normal for DR, corrected for
skewness for IPS and SNIPS, whose weighted terms are heavy-tailed (see _skew_corrected).

Accuracy (does the policy pick the faster side) needs both latencies, which only probe steps have;
probe steps are drawn independently of the state, so they are an unbiased sample. On them the
policy's latency and accuracy are measured directly: that is the on-policy figure ("probe truth")
printed beside the estimates.
"""
import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass
from typing import Dict, Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.dqn import greedy_actions
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.data.records import RequestLog
from offload_learner_py.online.breaker import OPEN, SLOW

Z_95 = 1.959963984540054


# Routing (the decision's `breaker` field) that sends a request to the local planner whatever the policy chose.
FORCED_LOCAL = (OPEN, SLOW)

MIN_EFFECTIVE_SAMPLES = 30   # below it, an importance-weighted figure rests on a handful of steps


@dataclass
class Estimate:
    value: float
    low: float
    high: float
    std_error: float
    n: int

    def contains(self, x: float) -> bool:
        return self.low <= x <= self.high

    def format(self, scale: float = 1.0, digits: int = 2) -> str:
        if self.n == 0 or not math.isfinite(self.value):
            return "n/a"
        return (f"{self.value * scale:.{digits}f} [{self.low * scale:.{digits}f}, "
                f"{self.high * scale:.{digits}f}]")


def _mean_interval(terms: np.ndarray) -> Estimate:
    terms = np.asarray(terms, dtype=np.float64)
    n = len(terms)
    if n == 0:
        return Estimate(math.nan, math.nan, math.nan, math.nan, 0)
    value = float(terms.mean())
    std_error = float(terms.std(ddof=1) / math.sqrt(n)) if n > 1 else math.inf
    return Estimate(value, value - Z_95 * std_error, value + Z_95 * std_error, std_error, n)


def _skew_corrected(value: float, std_error: float, skewness: float, n: int, kurtosis: float = 3.0) -> Estimate:
    """95 % interval of a mean from Hall's transformation of the studentised mean (P. Hall, "On the
    removal of skewness by transformation", JRSS B 54, 1992), which removes the first-order effect of
    the terms' skewness on the t statistic. Importance-weighted latencies are zero where the policies
    disagree and large on the few rows a rare logged action was taken with a heavy-tailed latency: when
    those rows happen to be few or cheap the mean is low and so is the sample variance, so the normal
    interval misses on the low side far more often than 2.5 %. The transformed interval extends upward
    by as much as the skewness says. With no skewness it is the symmetric t interval below.

    The quantile is Student's t with Satterthwaite's degrees of freedom for a variance estimated from terms
    of this kurtosis, 2 n / (kurtosis - 1) (n for normal terms): when a handful of rows carry the variance,
    the variance is itself known only from that handful, and the interval widens accordingly."""
    if not (math.isfinite(std_error) and math.isfinite(skewness)) or std_error == 0:
        return Estimate(value, value - Z_95 * std_error, value + Z_95 * std_error, std_error, n)
    quantile = _t_quantile(2.0 * n / (kurtosis - 1.0) if kurtosis > 1.0 else math.inf)
    if abs(skewness) < 1e-12:
        return Estimate(value, value - quantile * std_error, value + quantile * std_error, std_error, n)
    a = skewness / math.sqrt(n)
    inverse = lambda t: 3.0 / a * (float(np.cbrt(1.0 + a * (t - a / 6.0))) - 1.0)  # noqa: E731  g^-1 of Hall's g
    return Estimate(value, value - std_error * inverse(quantile), value - std_error * inverse(-quantile), std_error, n)


def _t_quantile(degrees_of_freedom: float) -> float:
    """The 97.5 % quantile of Student's t (Z_95 for infinite degrees of freedom)."""
    if not math.isfinite(degrees_of_freedom) or degrees_of_freedom > 1e6:
        return Z_95
    from scipy.stats import t
    return float(t.ppf(0.975, max(degrees_of_freedom, 1.0)))


def _shape(deviation: np.ndarray) -> tuple:
    """Skewness and kurtosis of terms from their deviations from the mean (second moment with n - 1)."""
    n = len(deviation)
    second = float(np.sum(deviation ** 2) / (n - 1))
    if not second > 0:
        return 0.0, 3.0
    return float(np.mean(deviation ** 3)) / second ** 1.5, float(np.mean(deviation ** 4)) / second ** 2


def wilson_interval(successes: int, n: int) -> Estimate:
    """95 % Wilson score interval of a proportion (honest near 0 and 1, unlike the normal one)."""
    if n == 0:
        return Estimate(math.nan, math.nan, math.nan, math.nan, 0)
    p = successes / n
    denominator = 1 + Z_95 ** 2 / n
    centre = (p + Z_95 ** 2 / (2 * n)) / denominator
    half = Z_95 * math.sqrt(p * (1 - p) / n + Z_95 ** 2 / (4 * n * n)) / denominator
    return Estimate(p, centre - half, centre + half, math.sqrt(p * (1 - p) / n), n)


def target_probabilities(actions: np.ndarray) -> np.ndarray:
    """N x 2 pi(a|s) of a deterministic policy from its actions."""
    actions = np.asarray(actions, dtype=np.int64)
    probabilities = np.zeros((len(actions), 2))
    probabilities[np.arange(len(actions)), actions] = 1.0
    return probabilities


def ips(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray, outcome: np.ndarray) -> Estimate:
    """Mean of pi(a_i|s_i) / mu_i * y_i, with a skewness-corrected interval (see _skew_corrected)."""
    weight = pi[np.arange(len(action)), action] / propensity
    terms = np.asarray(weight * outcome, dtype=np.float64)
    estimate = _mean_interval(terms)
    if estimate.n < 3:
        return estimate
    skewness, kurtosis = _shape(terms - estimate.value)
    return _skew_corrected(estimate.value, estimate.std_error, skewness, estimate.n, kurtosis)


def snips(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray, outcome: np.ndarray) -> Estimate:
    """Self-normalised IPS: sum w_i y_i / sum w_i, with a jackknife interval. Slightly biased, but it does
    not swing with the count of rare large weights the way plain IPS does: when the few exploratory steps
    of a mostly greedy logger (weight 1 / 0.05 = 20) happen to be cheap or dear, plain IPS moves with them.
    The interval comes from the leave-one-out ratios (their pseudo-values' spread and skewness, see
    _skew_corrected): a ratio's linearised (delta-method) error understates how far it moves when one of
    those few rows is left out, and its intervals covered the truth in 87-89 % of logs at epsilon 0.05
    (test_off_policy_coverage.py) where the jackknife's cover 89-90 %, and 91-93 % on Student's t with the
    pseudo-values' Satterthwaite degrees of freedom."""
    weight = pi[np.arange(len(action)), action] / propensity
    total = weight.sum()
    n = len(action)
    if n == 0 or total <= 0:
        return Estimate(math.nan, math.nan, math.nan, math.nan, n)
    weighted = weight * outcome
    value = float(weighted.sum() / total)
    rest = total - weight
    if np.any(rest <= 0):   # one row holds all the weight: nothing to leave out
        return Estimate(value, -math.inf, math.inf, math.inf, n)
    pseudo = n * value - (n - 1) * (weighted.sum() - weighted) / rest
    deviation = pseudo - pseudo.mean()
    std_error = math.sqrt(float(np.sum(deviation ** 2) / (n - 1)) / n)
    skewness, kurtosis = _shape(deviation)
    return _skew_corrected(value, std_error, skewness, n, kurtosis)


def effective_sample_size(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray) -> float:
    """(sum w)^2 / sum w^2: how many on-policy samples the reweighted log is worth."""
    weight = pi[np.arange(len(action)), action] / propensity
    squares = float(np.sum(weight ** 2))
    return float(weight.sum() ** 2 / squares) if squares > 0 else 0.0


def doubly_robust(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray, outcome: np.ndarray,
                  predicted: np.ndarray) -> Estimate:
    """Mean of sum_a pi(a|s_i) q(s_i, a) + pi(a_i|s_i) / mu_i * (y_i - q(s_i, a_i))."""
    rows = np.arange(len(action))
    weight = pi[rows, action] / propensity
    terms = (pi * predicted).sum(axis=1) + weight * (outcome - predicted[rows, action])
    return _mean_interval(terms)


def _features(states: np.ndarray) -> np.ndarray:
    """Every state field (log d, u, b: on the schema's log scale where it hints one) and their squares and
    products: enough shape for a latency that grows with d and falls with u, cheap enough to fit on every run."""
    base = STATE_SCHEMA.log_scaled(states)
    mean, scale = base.mean(axis=0), np.maximum(base.std(axis=0), 1e-9)
    z = (base - mean) / scale
    k = z.shape[1]
    columns = [np.ones(len(z))] + [z[:, i] for i in range(k)]
    columns += [z[:, i] * z[:, j] for i in range(k) for j in range(i, k)]
    return np.stack(columns, axis=1)


def fit_latency_model(states: np.ndarray, action: np.ndarray, outcome: np.ndarray, folds: int = 2,
                      ridge: float = 1.0) -> np.ndarray:
    """N x 2 predicted latency of each action for each row, cross-fitted: a row's prediction comes
    from a ridge regression of log latency fitted on the other folds' rows that took that action.
    Falls back to the action's mean latency where too few rows took it."""
    n = len(action)
    features = _features(np.asarray(states, dtype=np.float64))
    target = np.log(np.maximum(outcome, 1e-9))
    fold = np.arange(n) % folds
    predicted = np.zeros((n, 2))
    for k in range(folds):
        test, train = fold == k, fold != k
        for a in (LOCAL, CLOUD):
            rows = train & (action == a)
            if rows.sum() < features.shape[1] * 3:
                took = outcome[action == a]
                predicted[test, a] = took.mean() if len(took) else outcome.mean()
                continue
            x, y = features[rows], target[rows]
            coefficients = np.linalg.solve(x.T @ x + ridge * np.eye(x.shape[1]), x.T @ y)
            residual = y - x @ coefficients
            # exp of a log fit predicts the median; the lognormal correction brings it to the mean
            predicted[test, a] = np.exp(features[test] @ coefficients + residual.var() / 2)
    return predicted


@dataclass
class LoggedSteps:
    """What off-policy evaluation needs of each logged request."""
    states: np.ndarray          # N x 3 (d, u, b)
    action: np.ndarray
    propensity: np.ndarray
    latency_s: np.ndarray       # measured latency of the taken side
    probe: np.ndarray           # both sides measured on a probe step
    local_s: np.ndarray         # NaN where not measured
    cloud_s: np.ndarray
    censored: int = 0           # requests at a lower bound: the taken side was cancelled (a hedge's other side won)

    def __len__(self):
        return len(self.action)

    @classmethod
    def from_log(cls, log: RequestLog, rows: Optional[np.ndarray] = None) -> "LoggedSteps":
        pick = (lambda name: np.asarray(log[name])) if rows is None else (lambda name: np.asarray(log[name])[rows])
        # The behaviour is what the router did: the side it called first (the decided action unless the circuit
        # breaker kept a cloud decision local). Where the breaker was open, or the hedge's slow-link guard applied,
        # the router would have called the local planner whatever the policy drew: that side's propensity is 1,
        # not the drawn decision's.
        action = pick("routed" if "routed" in log.columns else "action").astype(np.int64)
        forced = np.isin(np.asarray(pick("breaker"), dtype=object), FORCED_LOCAL) if "breaker" in log.columns \
            else np.zeros(len(action), dtype=bool)
        local_s, cloud_s = pick("outcome_local_s").astype(np.float64), pick("outcome_cloud_s").astype(np.float64)
        both = np.isfinite(local_s) & np.isfinite(cloud_s) & (local_s > 0) & (cloud_s > 0)
        probe = pick("probe").astype(bool) & both
        latency_s = np.where(action == CLOUD, cloud_s, local_s)
        # A hedged request whose other side answered first had its taken side cancelled then: that side would
        # have taken longer than the request's delivery time, which enters as its latency (a lower bound, so the
        # estimate errs low by less than leaving the slow request out would).
        delivered_s = pick("outcome_delivered_s").astype(np.float64)
        censored = ~np.isfinite(latency_s) & np.isfinite(delivered_s)
        latency_s = np.where(censored, delivered_s, latency_s)
        steps = cls(states=STATE_SCHEMA.stack(pick),
                    action=action, propensity=np.where(forced, 1.0, pick("action_propensity").astype(np.float64)),
                    latency_s=latency_s, probe=probe, local_s=local_s, cloud_s=cloud_s, censored=int(censored.sum()))
        known = np.isfinite(latency_s)
        return steps if known.all() else steps.slice(known)   # nothing known of it at all: left out

    def slice(self, rows) -> "LoggedSteps":
        return LoggedSteps(**{name: getattr(self, name)[rows] for name in
                              ("states", "action", "propensity", "latency_s", "probe", "local_s", "cloud_s")},
                           censored=self.censored)


def evaluate_policy(steps: LoggedSteps, actions: np.ndarray, predicted: Optional[np.ndarray] = None) -> Dict:
    """IPS and DR estimates of a deterministic policy's mean latency (all steps) and accuracy (probe
    steps), and its directly measured latency and accuracy on probe steps, with 95 % intervals."""
    actions = np.asarray(actions, dtype=np.int64)
    pi = target_probabilities(actions)
    if predicted is None:
        predicted = fit_latency_model(steps.states, steps.action, steps.latency_s)
    result = {"steps": len(steps), "probe_steps": int(steps.probe.sum()), "censored_steps": steps.censored,
              "effective_sample_size": effective_sample_size(pi, steps.action, steps.propensity),
              "latency_ips_s": ips(pi, steps.action, steps.propensity, steps.latency_s),
              "latency_snips_s": snips(pi, steps.action, steps.propensity, steps.latency_s),
              "latency_dr_s": doubly_robust(pi, steps.action, steps.propensity, steps.latency_s, predicted)}
    p = steps.probe
    if p.any():
        local_s, cloud_s = steps.local_s[p], steps.cloud_s[p]
        chosen = np.where(actions[p] == CLOUD, cloud_s, local_s)
        best = np.minimum(local_s, cloud_s)
        correct = chosen <= best
        result["latency_probe_s"] = _mean_interval(chosen)
        result["accuracy_probe"] = wilson_interval(int(correct.sum()), int(p.sum()))
        # the same accuracy estimated the off-policy way: only the taken action's correctness is used
        taken_correct = (np.where(steps.action[p] == CLOUD, cloud_s, local_s) <= best).astype(np.float64)
        # An accuracy is a share: IPS can overshoot it on few steps, so the estimate and its interval are
        # clipped to [0, 1] (the clipping is visible as an interval that ends at 0 or 100 %).
        result["accuracy_ips"] = clipped(ips(pi[p], steps.action[p], steps.propensity[p], taken_correct), 0.0, 1.0)
    return result


def clipped(estimate: Estimate, low: float, high: float) -> Estimate:
    clip = lambda value: min(max(value, low), high) if math.isfinite(value) else value  # noqa: E731
    return Estimate(clip(estimate.value), clip(estimate.low), clip(estimate.high), estimate.std_error, estimate.n)


def to_jsonable(result: Dict) -> Dict:
    return {key: asdict(value) if isinstance(value, Estimate) else value for key, value in result.items()}


def format_results(results: Dict[str, Dict]) -> str:
    """One line per policy: latency IPS / SNIPS / DR / probe truth in ms, effective sample size,
    accuracy on probe steps in %."""
    lines = [f"{'policy':16}{'latency IPS (ms)':>26}{'SNIPS (ms)':>26}{'DR (ms)':>26}{'probe steps (ms)':>26}"
             f"{'ESS':>7}{'accuracy, probe (%)':>22}{'accuracy IPS (%)':>22}"]
    for name, result in results.items():
        empty = Estimate(math.nan, math.nan, math.nan, math.nan, 0)
        lines.append(f"{name:16}{result['latency_ips_s'].format(1000):>26}{result['latency_snips_s'].format(1000):>26}"
                     f"{result['latency_dr_s'].format(1000):>26}"
                     f"{result.get('latency_probe_s', empty).format(1000):>26}"
                     f"{result['effective_sample_size']:7.0f}"
                     f"{result.get('accuracy_probe', empty).format(100, 1):>22}"
                     f"{result.get('accuracy_ips', empty).format(100, 1):>22}")
    censored = max((result.get("censored_steps", 0) for result in results.values()), default=0)
    if censored:
        lines.append(f"note: {censored} hedged requests enter at their delivery time, a lower bound of the taken "
                     "side's latency: the other side answered first and the taken side was cancelled")
    few = [name for name, result in results.items() if result["effective_sample_size"] < MIN_EFFECTIVE_SAMPLES]
    if few:
        lines.append(f"warning: effective sample size under {MIN_EFFECTIVE_SAMPLES} for {', '.join(few)}: their IPS, "
                     "SNIPS and DR figures rest on a handful of logged steps (record more, or with more probes)")
    return "\n".join(lines)


def candidate_actions(steps: LoggedSteps, model: Optional[str] = None) -> Dict[str, np.ndarray]:
    """Actions of always-local, always-cloud and, with a checkpoint, its greedy policy."""
    candidates = {"always_local": np.full(len(steps), LOCAL), "always_cloud": np.full(len(steps), CLOUD)}
    if model:
        from offload_learner_py.core.checkpoint import load_checkpoint

        q = load_checkpoint(model).q_values(steps.states)
        candidates["model"] = greedy_actions(q)
    return candidates


def main(argv=None) -> int:
    from offload_learner_py.data.bags import read_bags
    from offload_learner_py.offline.output import terminal_text

    parser = argparse.ArgumentParser(description="Off-policy estimates (IPS, DR) of always-local, always-cloud "
                                                 "and a checkpoint's greedy policy from the bags' logged "
                                                 "propensities, beside the probe-step truth.")
    parser.add_argument("bags", nargs="+", help="bag files, globs or directories")
    parser.add_argument("--model", help="a DQN checkpoint to evaluate")
    parser.add_argument("--json", help="write the estimates here")
    parser.add_argument("--workers", type=int, default=None)
    args = parser.parse_args(argv)
    data = read_bags(args.bags, workers=args.workers)
    print(terminal_text(data.report.format()), file=sys.stderr)
    if len(data.log) == 0:
        print("error: no request read from the bags", file=sys.stderr)
        return 2
    steps = LoggedSteps.from_log(data.log)
    predicted = fit_latency_model(steps.states, steps.action, steps.latency_s)
    try:
        candidates = candidate_actions(steps, args.model)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    results = {name: evaluate_policy(steps, actions, predicted) for name, actions in candidates.items()}
    print(format_results(results))
    if args.json:
        with open(args.json, "w") as out:
            json.dump({name: to_jsonable(result) for name, result in results.items()}, out, indent=2)
    return 1 if data.report.failed else 0   # a bag that could not be read is not a documented skip


if __name__ == "__main__":
    sys.exit(main())
