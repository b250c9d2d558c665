"""A policy's mean latency, and the difference between two policies', from a robot's logged requests: the
estimate a model gate can trust.

Probe requests had both sides measured: a policy's latency on them is read directly (its action picks the
measured side, no weighting). The counterfactual estimators (IPS, SNIPS, DR of off_policy_estimators) serve
only the requests with one side measured. The requests are split by q, the probability the logging policy
had of taking the side (for a difference: the sides) the target needs; q depends on the state and the logged
propensity alone, never on a latency, and so do the strata (strata()):

- known: the two policies of a difference agree there, so the difference is 0 exactly;
- common (q >= RARE) and rare (0 < q < RARE: the few exploratory requests carry all of these): probes among
  them are scored directly, the others by the counterfactual estimator, one mean over both (the per-request
  terms all have the stratum's expectation: probes are drawn independently of the state and the action);
- unsupported (q = 0: a greedy policy without exploration, a breaker that kept the request local): nothing of
  these requests' own logs says what the needed side would have cost; the probes among them, a random
  sample of them, stand for them all.

A stratum whose one-side requests have an effective sample size under MIN_EFFECTIVE_SAMPLES is represented by
its probes alone too, and one represented by fewer than MIN_PROBE_ROWS probes makes the estimate "n/a", with
the reason. Each stratum's share of the requests weights its mean; variances and third cumulants add, and the
interval is Hall's skewness-corrected one on Welch-Satterthwaite's degrees of freedom
(off_policy_intervals.combine). Estimates and bounds stay within what latencies can be: [0, the largest
measured latency] for a policy, +- that for a difference.
"""
import math
from typing import Dict, Optional, Tuple

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.offline.off_policy_estimators import doubly_robust_terms, effective_sample_size, \
    ips_terms, snips_pseudo_values, target_probabilities
from offload_learner_py.offline.off_policy_intervals import Estimate, clipped, combine, not_available, part, \
    wilson_interval
from offload_learner_py.offline.off_policy_steps import LoggedSteps

ESTIMATORS = ("snips", "dr", "ips")
GATE_ESTIMATOR = "snips"     # the best calibrated on the real bag's rows (test_off_policy_calibration.py)
MIN_EFFECTIVE_SAMPLES = 10   # fewer in a stratum: an importance-weighted figure rests on a handful of requests
MIN_PROBE_ROWS = 8           # probes needed to stand for a stratum of the requests on their own
RARE = 0.2                   # a side taken with a smaller probability: its requests are a stratum of their own
_CERTAIN = 1.0 - 1e-9        # a propensity at least this: the other side had no chance


def _direct(pi: np.ndarray, local_s: np.ndarray, cloud_s: np.ndarray) -> np.ndarray:
    """sum_a pi(a) y(a) per request (NaN where a needed side was not measured, 0 where pi is 0)."""
    return np.where(pi[:, LOCAL] != 0, pi[:, LOCAL] * local_s, 0.0) + \
        np.where(pi[:, CLOUD] != 0, pi[:, CLOUD] * cloud_s, 0.0)


def _counterfactual(estimator: str, pi, action, propensity, outcome, predicted) -> Optional[np.ndarray]:
    """Per-request terms whose mean is the estimator's estimate (SNIPS: the jackknife's pseudo-values)."""
    if estimator == "ips":
        return ips_terms(pi, action, propensity, outcome)
    if estimator == "dr":
        return doubly_robust_terms(pi, action, propensity, outcome, predicted)
    if estimator == "snips":
        jackknife = snips_pseudo_values(pi, action, propensity, outcome)
        return None if jackknife is None else jackknife[1]
    raise ValueError(f"unknown estimator {estimator!r} (one of {', '.join(ESTIMATORS)})")


def needed_propensity(steps: LoggedSteps, pi: np.ndarray) -> np.ndarray:
    """Per request, the smallest probability the logging policy had of taking a side the target needs (pi
    not 0 there): 0 where it could not take one, NaN where the target needs no side (a difference of two
    policies that agree)."""
    taken = steps.propensity
    mu = np.where(np.arange(2)[None, :] == steps.action[:, None], taken[:, None], 1.0 - taken[:, None])
    mu = np.where(mu <= 1.0 - _CERTAIN, 0.0, mu)
    needed = np.where(pi != 0, mu, np.inf).min(axis=1)
    return np.where(np.isfinite(needed), needed, np.nan)


def strata(steps: LoggedSteps, pi: np.ndarray) -> Dict[str, np.ndarray]:
    """Masks of the requests by what the logs can say of them: known (the target needs no side), unsupported
    (it needs a side the logger could not take), rare (one it took with probability under RARE: the few
    times it did carry the whole of these requests), common (the rest)."""
    q = needed_propensity(steps, pi)
    known = np.isnan(q)
    return {"known": known, "unsupported": ~known & (q == 0), "rare": ~known & (q > 0) & (q < RARE),
            "common": ~known & (q >= RARE)}


def estimate(steps: LoggedSteps, pi: np.ndarray, estimator: str = GATE_ESTIMATOR,
             predicted: Optional[np.ndarray] = None, difference: bool = False) -> Tuple[Estimate, Dict]:
    """(estimate of mean_i sum_a pi_i(a) y_i(a) over the logged requests, what it rests on). pi: one-hot
    actions of a policy, or the difference of two policies' (difference=True: bounds +- the largest latency).
    See the module docstring."""
    n = len(steps)
    masks = strata(steps, pi)
    probe = steps.probe
    info = {"steps": n, "probe_steps": int(probe.sum()), "unsupported_steps": int(masks["unsupported"].sum()),
            "effective_sample_size": math.nan, "counterfactual_steps": 0}
    if n == 0:
        return not_available("no requests"), info
    local_s, cloud_s = steps.sides()
    direct = _direct(pi, local_s, cloud_s)
    parts, pooled, ess_total = [], [], 0.0
    for name in ("common", "rare", "unsupported"):
        stratum = masks[name]
        rows = stratum & ~probe
        if not rows.any():                  # every request of it a probe (or none): each scored directly
            pooled.append(stratum)
            continue
        terms, ess = None, 0.0
        if name != "unsupported":
            # a difference needs both policies' sides: it rests on the scarcer of the two
            ess = min(effective_sample_size(side[rows], steps.action[rows], steps.propensity[rows])
                      for side in (np.clip(pi, 0, None), np.clip(-pi, 0, None)) if np.any(side[rows] != 0))
            ess_total += ess
            if ess >= MIN_EFFECTIVE_SAMPLES:
                if predicted is None and estimator == "dr":
                    predicted = steps.latency_model()
                terms = _counterfactual(estimator, pi[rows], steps.action[rows], steps.propensity[rows],
                                        steps.latency_s[rows], None if predicted is None else predicted[rows])
        if terms is not None:
            info["counterfactual_steps"] += int(rows.sum())
            pooled.append((stratum & probe, terms))
            continue
        probes = int((stratum & probe).sum())
        if probes < MIN_PROBE_ROWS:
            if name == "unsupported":
                reason = (f"no support: {int(stratum.sum())} requests needed a side the logging policy could not "
                          f"take there")
            else:
                reason = (f"too few effective samples: {ess:.0f} among {int(rows.sum())} requests with one side "
                          f"measured" + (f" (a side taken with probability under {RARE:g})" if name == "rare" else ""))
            return not_available(f"{reason}, and {probes} probes of them (at least {MIN_PROBE_ROWS} needed)"), info
        parts.append(part(direct[stratum & probe], stratum.sum() / n))   # its probes stand for all of it
    # One term per request of the other strata (probes direct, the others counterfactual): their mean is the
    # mean over those requests, whatever stratum each is in.
    terms = [direct[entry] if isinstance(entry, np.ndarray) else np.concatenate([direct[entry[0]], entry[1]])
             for entry in pooled]
    count = sum(len(t) for t in terms)
    if count:
        parts.append(part(np.concatenate(terms), count / n))
    info["effective_sample_size"] = ess_total if info["probe_steps"] < n else math.nan
    if any(p is None for p in parts):
        return not_available("too few requests to estimate a variance"), info
    combined = combine(parts)
    combined.n = n
    largest = steps.largest_latency_s()
    return clipped(combined, -largest if difference else 0.0, largest), info


def evaluate_policy(steps: LoggedSteps, actions: np.ndarray, predicted: Optional[np.ndarray] = None) -> Dict:
    """A deterministic policy's mean latency on the logged requests by each estimator (latency_dr_s,
    latency_snips_s, latency_ips_s: probes direct, the rest counterfactual; see the module docstring), its
    latency and accuracy measured on the probe requests alone, and what the estimates rest on."""
    actions = np.asarray(actions, dtype=np.int64)
    pi = target_probabilities(actions)
    if predicted is None:
        predicted = steps.latency_model()
    result = {"censored_steps": steps.censored}
    for name in ESTIMATORS:
        result[f"latency_{name}_s"], info = estimate(steps, pi, name, predicted)
    result.update(info)
    result["latency_s"] = result[f"latency_{GATE_ESTIMATOR}_s"]
    p = steps.probe
    if p.any():
        local_s, cloud_s = steps.local_s[p], steps.cloud_s[p]
        chosen = np.where(actions[p] == CLOUD, cloud_s, local_s)
        probes = part(chosen, 1.0)
        result["latency_probe_s"] = not_available("fewer than 2 probes") if probes is None else \
            clipped(combine([probes]), 0.0, steps.largest_latency_s())
        correct = chosen <= np.minimum(local_s, cloud_s)
        result["accuracy_probe"] = wilson_interval(int(correct.sum()), int(p.sum()))
    return result


def not_worse(steps: LoggedSteps, actions_new: np.ndarray, actions_current: np.ndarray, margin_s: float = 0.0,
              estimator: str = GATE_ESTIMATOR, predicted: Optional[np.ndarray] = None) -> Tuple[bool, Estimate]:
    """Is the new policy not worse than the current one on these logged requests?

    steps: a robot's recent requests (LoggedSteps.from_log(request_log)); actions_new, actions_current: each
    policy's action (0 local, 1 cloud) for every one of them, e.g. checkpoint.greedy_actions(steps.states).
    margin_s: how much slower on average (seconds) still counts as not worse.

    Returns (accepted, the estimate of mean latency(new) - mean latency(current) in seconds over the same
    requests, with its 95 % interval). Paired: where the two agree the difference is exactly 0, on probes it
    is measured, elsewhere estimated (see the module docstring). Accepted only when the whole interval is at
    most margin_s, so an estimate that cannot say ("n/a": no probes where the logs cannot tell, too few
    effective samples) is refused, and so is a new policy whose interval reaches above the margin."""
    pi = target_probabilities(actions_new) - target_probabilities(actions_current)
    difference, _ = estimate(steps, pi, estimator, predicted, difference=True)
    return bool(difference.available and difference.high <= margin_s), difference
