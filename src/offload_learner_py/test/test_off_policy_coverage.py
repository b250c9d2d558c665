"""Coverage of the off-policy intervals. On a population of states whose local and
cloud latencies are both known (so the truth of any target policy is known), a few hundred resampled logs
are drawn, each logged by a greedy rule with epsilon exploration (propensity = probability of the logged
action), and the 95 % IPS, SNIPS and DR intervals of always-local, always-cloud and a threshold policy
must contain the population mean latency in at least 90 % of them.

The latencies are lognormal around a state-dependent median (local grows with d / u, cloud with the round
trip and d), so the weighted terms are heavy-tailed: the situation in which a normal interval of IPS
misses on the low side (see off_policy._skew_corrected)."""
import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.offline import off_policy
from statetools import raw_states

TARGETS = ("always_local", "always_cloud", "threshold")
ESTIMATORS = ("ips", "snips", "dr")
LOGS = 1000


def population(size=4000, seed=0, sigma=0.5):
    rng = np.random.default_rng(seed)
    d = 10 ** rng.uniform(-2, 0.7, size)
    u = rng.uniform(0.2, 1.0, size)
    b = rng.uniform(0.02, 0.06, size)
    local_s = (0.005 + 0.04 * d / u) * rng.lognormal(0, sigma, size)
    cloud_s = (b + 0.01 * d) * rng.lognormal(0, sigma, size)
    return raw_states(d, u, b), local_s, cloud_s


STATES, LOCAL_S, CLOUD_S = population()
TARGET_ACTIONS = {"always_local": np.full(len(STATES), LOCAL), "always_cloud": np.full(len(STATES), CLOUD),
                  "threshold": np.where(STATES[:, 0] > 0.3, CLOUD, LOCAL)}
TRUTH = {name: float(np.where(actions == CLOUD, CLOUD_S, LOCAL_S).mean()) for name, actions in TARGET_ACTIONS.items()}
GREEDY = np.where(STATES[:, 0] > 1.0, CLOUD, LOCAL)   # the logger offloads big inputs


def draw_logs(epsilon, n, logs=LOGS, seed=1):
    """logs x n resampled rows, their epsilon-greedy actions, propensities and taken latencies."""
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, len(STATES), (logs, n))
    p_cloud = np.where(GREEDY[rows] == CLOUD, 1 - epsilon / 2, epsilon / 2)
    action = (rng.random((logs, n)) < p_cloud).astype(np.int64)
    propensity = np.where(action == CLOUD, p_cloud, 1 - p_cloud)
    latency = np.where(action == CLOUD, CLOUD_S[rows], LOCAL_S[rows])
    return rows, action, propensity, latency


def estimates(rows, action, propensity, latency, predicted=None):
    """{(target, estimator): Estimate} of one log."""
    if predicted is None:
        predicted = off_policy.fit_latency_model(STATES[rows], action, latency)
    out = {}
    for target in TARGETS:
        pi = off_policy.target_probabilities(TARGET_ACTIONS[target][rows])
        out[target, "ips"] = off_policy.ips(pi, action, propensity, latency)
        out[target, "snips"] = off_policy.snips(pi, action, propensity, latency)
        out[target, "dr"] = off_policy.doubly_robust(pi, action, propensity, latency, predicted)
    return out


def coverage(epsilon, n):
    logs = draw_logs(epsilon, n)
    hits = {key: 0 for key in ((t, e) for t in TARGETS for e in ESTIMATORS)}
    for i in range(LOGS):
        for (target, estimator), estimate in estimates(*(array[i] for array in logs)).items():
            hits[target, estimator] += estimate.contains(TRUTH[target])
    return {key: count / LOGS for key, count in hits.items()}


_CACHE = {}


def cached_coverage(epsilon, n):
    if (epsilon, n) not in _CACHE:
        _CACHE[epsilon, n] = coverage(epsilon, n)
    return _CACHE[epsilon, n]


# (epsilon, rows per log). At epsilon 0.05 a log of 300 rows holds about 2 exploratory local steps among
# the big inputs (effective sample size about 10-40, under off_policy.MIN_EFFECTIVE_SAMPLES); 1200 rows
# give it as many exploratory steps as epsilon 0.2 gives 300.
SETTINGS = [(0.05, 1200), (0.2, 300), (0.5, 300)]
# SNIPS at epsilon 0.05 (1000 logs of 1200 rows, seed 1), the threshold policy: 0.872 with the delta-method
# interval, 0.888 with the jackknife's on the normal quantile, 0.908 with Student's t on Satterthwaite's degrees
# of freedom (off_policy._skew_corrected). Its misses were nearly all low: about six rows, logged at propensity
# 0.025, carry the cloud latency of the inputs between the threshold and the logger's, and when they happen to
# be cheap so is their spread. No setting below is a known shortfall any more.
KNOWN_SHORT = {}   # (epsilon, n, target, estimator): a documented floor under 0.90


@pytest.mark.parametrize("estimator", ESTIMATORS)
@pytest.mark.parametrize("epsilon,n", SETTINGS)
def test_intervals_cover_the_truth_in_nine_of_ten_resampled_logs(epsilon, n, estimator):
    figures = cached_coverage(epsilon, n)
    short = {target: figures[target, estimator] for target in TARGETS
             if figures[target, estimator] < KNOWN_SHORT.get((epsilon, n, target, estimator), 0.90)}
    assert not short, f"coverage under 90 % at epsilon {epsilon}, n {n}: {short}"


@pytest.mark.xfail(strict=True, reason="epsilon 0.05 with 300 rows: about two exploratory steps where the logger "
                                       "is greedy-cloud, so a log without one carries no information on the "
                                       "local latency of big inputs; no interval from the logged outcomes "
                                       "covers then (effective sample size under MIN_EFFECTIVE_SAMPLES)")
def test_too_little_exploration_is_not_covered():
    figures = cached_coverage(0.05, 300)
    assert min(figures.values()) >= 0.90


def test_the_logs_are_biased_for_a_naive_mean():
    rows, action, propensity, latency = draw_logs(0.2, 300, logs=1)
    naive = latency[0][action[0] == LOCAL].mean()
    assert naive < 0.6 * TRUTH["always_local"]   # the logger runs locally only what is cheap locally


OBP_REASON = ("obp (0.5.7, the newest) pins numpy==1.23.5, scipy==1.9.3, torch==1.12, pandas==1.5.2 and "
              "python<3.11; the venv pins numpy==2.2.6, scipy==1.15.3, torch==2.13.0 on python 3.11")


def test_point_estimates_agree_with_open_bandit_pipeline():
    ope = pytest.importorskip("obp.ope", reason=OBP_REASON)
    for epsilon in (0.05, 0.2, 0.5):
        rows, action, propensity, latency = (array[0] for array in draw_logs(epsilon, 300, logs=1, seed=7))
        predicted = off_policy.fit_latency_model(STATES[rows], action, latency)
        ours = estimates(rows, action, propensity, latency, predicted)
        for target in TARGETS:
            pi = off_policy.target_probabilities(TARGET_ACTIONS[target][rows])
            common = dict(reward=latency, action=action, pscore=propensity, action_dist=pi[:, :, None],
                          position=np.zeros(len(action), dtype=int))
            theirs = {"ips": ope.InverseProbabilityWeighting().estimate_policy_value(**common),
                      "snips": ope.SelfNormalizedInverseProbabilityWeighting().estimate_policy_value(**common),
                      "dr": ope.DoublyRobust().estimate_policy_value(
                          **common, estimated_rewards_by_reg_model=predicted[:, :, None])}
            for estimator, value in theirs.items():
                assert ours[target, estimator].value == pytest.approx(value, rel=1e-6), (epsilon, target, estimator)
