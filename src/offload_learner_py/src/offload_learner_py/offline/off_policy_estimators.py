"""The counterfactual estimators of off-policy evaluation, on requests where only the taken side was measured:
inverse propensity scoring (IPS) reweights the taken side's latency by pi(a|s) / mu(a|s); self-normalised IPS
(SNIPS) divides by the weights' sum; the doubly robust estimator (DR) adds a model of the latency per action
(ridge regression of log latency on the state, cross-fitted so no request scores its own fit) and corrects
that model with the same weights. off_policy_combined uses them for the requests that were not probes.

`pi` is an N x 2 array of target coefficients: a deterministic policy's one-hot actions
(target_probabilities), or the difference of two policies' (each row +1 / -1, or 0 where they agree), whose
IPS and DR estimate the difference of the two mean latencies over the same requests."""
import math

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.offline.off_policy_intervals import Estimate, _mean_interval, _shape, _skew_corrected

EXTRAPOLATION = 10.0   # a latency model's predictions stay under this many times the largest measured latency


def target_probabilities(actions: np.ndarray) -> np.ndarray:
    """N x 2 pi(a|s) of a deterministic policy from its actions."""
    actions = np.asarray(actions, dtype=np.int64)
    probabilities = np.zeros((len(actions), 2))
    probabilities[np.arange(len(actions)), actions] = 1.0
    return probabilities


def weights(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray) -> np.ndarray:
    """pi(a_i|s_i) / mu_i of each logged request."""
    return pi[np.arange(len(action)), action] / propensity


def ips_terms(pi, action, propensity, outcome) -> np.ndarray:
    return np.asarray(weights(pi, action, propensity) * outcome, dtype=np.float64)


def ips(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray, outcome: np.ndarray) -> Estimate:
    """Mean of pi(a_i|s_i) / mu_i * y_i, with a skewness-corrected interval (see _skew_corrected)."""
    terms = ips_terms(pi, action, propensity, outcome)
    estimate = _mean_interval(terms)
    if estimate.n < 3:
        return estimate
    skewness, kurtosis = _shape(terms - estimate.value)
    return _skew_corrected(estimate.value, estimate.std_error, skewness, estimate.n, kurtosis)


def snips_pseudo_values(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray, outcome: np.ndarray):
    """(sum w y / sum w, the jackknife's pseudo-values n R - (n - 1) R_-i) for a policy's one-hot pi; for
    pi = one-hot(new) - one-hot(current), those of R_new - R_current. None where a ratio has no weight, or a
    row holds all of it (nothing to leave out)."""
    n = len(action)
    parts = [np.clip(pi, 0, None), np.clip(-pi, 0, None)] if np.any(pi < 0) else [pi]
    value, pseudo = 0.0, np.zeros(n)
    for sign, coefficients in zip((1.0, -1.0), parts):
        weight = weights(coefficients, action, propensity)
        total = weight.sum()
        rest = total - weight
        if n == 0 or total <= 0 or np.any(rest <= 0):
            return None
        weighted = weight * outcome
        ratio = float(weighted.sum() / total)
        value += sign * ratio
        pseudo += sign * (n * ratio - (n - 1) * (weighted.sum() - weighted) / rest)
    return value, pseudo


def snips(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray, outcome: np.ndarray) -> Estimate:
    """Self-normalised IPS: sum w_i y_i / sum w_i, with a jackknife interval. Slightly biased, but it does
    not swing with the count of rare large weights the way plain IPS does: when the few exploratory steps
    of a mostly greedy logger (weight 1 / 0.05 = 20) happen to be cheap or dear, plain IPS moves with them.
    The interval comes from the leave-one-out ratios (their pseudo-values' spread and skewness, see
    _skew_corrected): a ratio's linearised (delta-method) error understates how far it moves when one of
    those few rows is left out, and its intervals covered the truth in 87-89 % of logs at epsilon 0.05
    (test_off_policy_coverage.py) where the jackknife's cover 89-90 %, and 91-93 % on Student's t with the
    pseudo-values' Satterthwaite degrees of freedom."""
    n = len(action)
    weight = weights(pi, action, propensity)
    total = weight.sum()
    if n == 0 or total <= 0:
        return Estimate(math.nan, math.nan, math.nan, math.nan, n)
    value = float((weight * outcome).sum() / total)
    jackknife = snips_pseudo_values(pi, action, propensity, outcome)
    if jackknife is None:   # one row holds all the weight: nothing to leave out
        return Estimate(value, -math.inf, math.inf, math.inf, n)
    pseudo = jackknife[1]
    deviation = pseudo - pseudo.mean()
    std_error = math.sqrt(float(np.sum(deviation ** 2) / (n - 1)) / n)
    skewness, kurtosis = _shape(deviation)
    return _skew_corrected(value, std_error, skewness, n, kurtosis)


def effective_sample_size(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray) -> float:
    """(sum |w|)^2 / sum w^2: how many on-policy samples the reweighted log is worth."""
    weight = np.abs(weights(pi, action, propensity))
    squares = float(np.sum(weight ** 2))
    return float(weight.sum() ** 2 / squares) if squares > 0 else 0.0


def doubly_robust_terms(pi, action, propensity, outcome, predicted) -> np.ndarray:
    rows = np.arange(len(action))
    return (pi * predicted).sum(axis=1) + weights(pi, action, propensity) * (outcome - predicted[rows, action])


def doubly_robust(pi: np.ndarray, action: np.ndarray, propensity: np.ndarray, outcome: np.ndarray,
                  predicted: np.ndarray) -> Estimate:
    """Mean of sum_a pi(a|s_i) q(s_i, a) + pi(a_i|s_i) / mu_i * (y_i - q(s_i, a_i))."""
    return _mean_interval(doubly_robust_terms(pi, action, propensity, outcome, predicted))


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


def cross_fitted_latencies(states: np.ndarray, local_s: np.ndarray, cloud_s: np.ndarray, folds: int = 2,
                           ridge: float = 1.0) -> np.ndarray:
    """N x 2 predicted latency of each side for each row, cross-fitted: a row's prediction comes from a ridge
    regression of log latency fitted on the other folds' measured latencies of that side (NaN: not measured;
    a probe's two sides both count). Falls back to the side's mean latency where too few rows measured it.
    A prediction is at most EXTRAPOLATION times the largest latency measured on either side. Not at most that
    latency itself: a side measured only where it is fast (a logger that runs big inputs in the cloud) is slower
    elsewhere, and capping the fit there cost DR's intervals a tenth of their coverage (test_off_policy_coverage)."""
    n = len(states)
    features = _features(np.asarray(states, dtype=np.float64))
    predicted = np.zeros((n, 2))
    fold = np.arange(n) % folds
    measured_any = np.concatenate([values[np.isfinite(values) & (values > 0)] for values in (local_s, cloud_s)])
    overall = float(measured_any.mean()) if len(measured_any) else math.nan
    for a, values in ((LOCAL, np.asarray(local_s, dtype=np.float64)), (CLOUD, np.asarray(cloud_s, dtype=np.float64))):
        measured = np.isfinite(values) & (values > 0)
        if not measured.any():
            predicted[:, a] = overall
            continue
        target = np.log(np.where(measured, values, 1.0))
        for k in range(folds):
            test, train = fold == k, (fold != k) & measured
            if train.sum() < features.shape[1] * 3:
                took = values[train] if train.any() else values[measured]
                predicted[test, a] = took.mean()
                continue
            x, y = features[train], target[train]
            coefficients = np.linalg.solve(x.T @ x + ridge * np.eye(x.shape[1]), x.T @ y)
            residual = y - x @ coefficients
            # exp of a log fit predicts the median; the lognormal correction brings it to the mean
            predicted[test, a] = np.exp(features[test] @ coefficients + residual.var() / 2)
    return np.minimum(predicted, EXTRAPOLATION * measured_any.max()) if len(measured_any) else predicted


def fit_latency_model(states: np.ndarray, action: np.ndarray, outcome: np.ndarray, folds: int = 2,
                      ridge: float = 1.0) -> np.ndarray:
    """cross_fitted_latencies from the taken side's latency of each row alone."""
    action = np.asarray(action)
    outcome = np.asarray(outcome, dtype=np.float64)
    return cross_fitted_latencies(states, np.where(action == LOCAL, outcome, np.nan),
                                  np.where(action == CLOUD, outcome, np.nan), folds, ridge)
