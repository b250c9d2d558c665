"""The combined off-policy estimate's thresholds and signs, each at its boundary (off_policy_combined): how many
effective samples let the counterfactual estimator speak for a stratum (10), how many probes let probes alone
stand for one (8), where a rare side begins (q < 0.2), when a propensity counts as certain, and the signs of a
difference of two policies. The model gate (fleet learner) and `off_policy` rest on each; `make mutate` left
every one of them unchecked before these tests."""
import math

import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.offline.off_policy_combined import estimate, evaluate_policy, not_worse
from offload_learner_py.offline.off_policy_estimators import target_probabilities
from offload_learner_py.offline.off_policy_steps import LoggedSteps

NAN = math.nan


def logged(action, propensity, latency_s, probe=None, local_s=None, cloud_s=None) -> LoggedSteps:
    """Requests as a logger took them: the taken side's latency, both sides where probe."""
    action = np.asarray(action, dtype=np.int64)
    n = len(action)
    latency_s = np.asarray(latency_s, dtype=np.float64)
    probe = np.zeros(n, dtype=bool) if probe is None else np.asarray(probe, dtype=bool)
    local_s = np.where(action == LOCAL, latency_s, NAN) if local_s is None else np.asarray(local_s, float)
    cloud_s = np.where(action == CLOUD, latency_s, NAN) if cloud_s is None else np.asarray(cloud_s, float)
    return LoggedSteps(states=np.zeros((n, len(STATE_SCHEMA))), action=action,
                       propensity=np.asarray(propensity, dtype=np.float64) * np.ones(n), latency_s=latency_s,
                       probe=probe, local_s=local_s, cloud_s=cloud_s)


def always(side: int, n: int) -> np.ndarray:
    return target_probabilities(np.full(n, side, dtype=np.int64))


def half_and_half(taken: int, others: int, rng) -> LoggedSteps:
    """A logger that took each side with probability 0.5: `taken` requests went local, `others` to the cloud."""
    action = np.r_[np.full(taken, LOCAL), np.full(others, CLOUD)]
    return logged(action, 0.5, rng.uniform(0.01, 0.05, len(action)))


@pytest.mark.parametrize("matching, available", [(9, False), (10, True)])
def test_ten_effective_samples_let_the_counterfactual_estimator_speak(matching, available):
    """Always-local over a 50/50 logger without probes: the importance weights are 2 on the local requests, so
    the effective sample size is their count. 10 are enough, 9 are not (and no probes stand in)."""
    steps = half_and_half(matching, 10, np.random.default_rng(1))
    result, info = estimate(steps, always(LOCAL, len(steps)), "ips")
    assert result.available == available, result.reason
    assert info["counterfactual_steps"] == (len(steps) if available else 0)
    if available:
        assert info["effective_sample_size"] == pytest.approx(matching)
    else:
        assert f"too few effective samples: {matching} among {len(steps)}" in result.reason


def _unsupported(probes: int) -> LoggedSteps:
    """A greedy logger that never offloads (propensity 1): always-cloud has no support, except on the probes."""
    n = 40
    probe = np.arange(n) < probes
    rng = np.random.default_rng(2)
    local_s, cloud_s = rng.uniform(0.02, 0.04, n), rng.uniform(0.01, 0.03, n)
    return logged(np.zeros(n), 1.0, local_s, probe, local_s, np.where(probe, cloud_s, NAN))


@pytest.mark.parametrize("probes, available", [(7, False), (8, True), (9, True)])
def test_eight_probes_stand_for_requests_the_logs_cannot_judge(probes, available):
    steps = _unsupported(probes)
    result, info = estimate(steps, always(CLOUD, len(steps)))
    assert result.available == available, result.reason
    assert info["unsupported_steps"] == len(steps)   # the probes among them included
    if available:   # the probes' mean cloud latency, direct
        assert result.value == pytest.approx(np.mean(steps.cloud_s[:probes]))
    else:
        assert result.reason.startswith("no support: 40 requests") and "7 probes" in result.reason


@pytest.mark.parametrize("propensity, rare", [(0.2, False), (0.19, True)])
def test_a_side_taken_with_probability_under_a_fifth_is_rare(propensity, rare):
    """Always-cloud over a logger that offloaded with probability `propensity` (5 such requests: too few
    effective samples either way); the reason names the rare stratum only below 0.2."""
    steps = logged(np.ones(5, dtype=np.int64), propensity, np.full(5, 0.02))
    result, _ = estimate(steps, always(CLOUD, 5))
    assert not result.available
    assert result.reason.startswith("too few effective samples: 5 among 5")
    assert ("a side taken with probability under 0.2" in result.reason) == rare


@pytest.mark.parametrize("propensity", [1.0 - 1e-9, 1.0 - 1e-10])
def test_a_propensity_within_a_billionth_of_one_leaves_the_other_side_unsupported(propensity):
    """A logger that kept requests local with probability 1 - 1e-9 (or closer) could not have offloaded them:
    no support, not a rare side whose weights of a billion would swamp the estimate."""
    steps = logged(np.zeros(30, dtype=np.int64), propensity, np.full(30, 0.02))
    result, info = estimate(steps, always(CLOUD, 30))
    assert not result.available and result.reason.startswith("no support: 30 requests")
    assert info["unsupported_steps"] == 30


def _probed(n=12, seed=3) -> LoggedSteps:
    rng = np.random.default_rng(seed)
    local_s, cloud_s = rng.uniform(0.02, 0.04, n), rng.uniform(0.01, 0.05, n)
    return logged(np.zeros(n, dtype=np.int64), 0.5, local_s, np.ones(n, dtype=bool), local_s, cloud_s)


def test_a_difference_counts_each_side_with_its_sign():
    """On probes the difference of two policies is measured: local minus cloud, request by request."""
    steps = _probed()
    for new, current, expected in ((LOCAL, CLOUD, steps.local_s - steps.cloud_s),
                                   (CLOUD, LOCAL, steps.cloud_s - steps.local_s)):
        pi = always(new, len(steps)) - always(current, len(steps))
        result, info = estimate(steps, pi, difference=True)
        assert result.value == pytest.approx(expected.mean())
        assert math.isnan(info["effective_sample_size"])   # every request a probe: nothing reweighted
    accepted, difference = not_worse(steps, np.full(len(steps), LOCAL), np.full(len(steps), CLOUD))
    assert difference.value == pytest.approx((steps.local_s - steps.cloud_s).mean())


def test_a_difference_needs_support_for_the_side_it_gives_up_too():
    """New always-local, current always-cloud, over a logger that never offloaded: the current policy's side was
    never taken, so the difference has no support (its negative side counts)."""
    steps = logged(np.zeros(30, dtype=np.int64), 1.0, np.full(30, 0.02))
    pi = always(LOCAL, 30) - always(CLOUD, 30)
    result, _ = estimate(steps, pi, difference=True)
    assert not result.available and result.reason.startswith("no support: 30 requests")


def test_a_difference_rests_on_the_scarcer_of_its_two_sides():
    """30 requests went local and 4 to the cloud (a 50/50 logger): always-local minus always-cloud has 30
    effective samples on its positive side and 4 on its negative one; 4 it is."""
    steps = half_and_half(30, 4, np.random.default_rng(4))
    pi = always(LOCAL, len(steps)) - always(CLOUD, len(steps))
    result, _ = estimate(steps, pi, "ips", difference=True)
    assert not result.available and "too few effective samples: 4 among 34" in result.reason


def test_a_policys_mean_latency_is_never_below_zero():
    """Eight probes, seven fast and one very slow: the t interval reaches below zero, a latency cannot."""
    local_s = np.r_[np.full(7, 0.001), 2.0]
    steps = logged(np.zeros(8, dtype=np.int64), 0.5, local_s, np.ones(8, dtype=bool), local_s, local_s + 0.01)
    result, _ = estimate(steps, always(LOCAL, 8))
    assert result.available and result.low == 0.0 and result.value > 0
    probes = evaluate_policy(steps, np.zeros(8, dtype=np.int64))["latency_probe_s"]
    assert probes.low == 0.0 and probes.value == pytest.approx(local_s.mean())


def test_each_estimator_is_its_own_and_an_unknown_one_is_refused():
    rng = np.random.default_rng(5)
    action = rng.integers(0, 2, 200)
    latency = np.where(action == CLOUD, rng.uniform(0.01, 0.05, 200), rng.uniform(0.02, 0.03, 200))
    steps = logged(action, 0.5, latency)
    pi = always(CLOUD, 200)
    values = {name: estimate(steps, pi, name)[0].value for name in ("ips", "snips", "dr")}
    assert len({round(v, 12) for v in values.values()}) == 3, values
    for bogus in ("bogus", "zzz"):
        with pytest.raises(ValueError, match="unknown estimator"):
            estimate(steps, pi, bogus)


def test_no_requests_is_said_as_such():
    assert estimate(logged([], 0.5, []), always(LOCAL, 0))[0].reason == "no requests"
    one = estimate(logged([0], 0.5, [0.02], [True], [0.02], [0.03]), always(LOCAL, 1))[0]
    assert not one.available and one.reason != "no requests"


def test_evaluate_policy_uses_the_latency_model_it_is_given():
    rng = np.random.default_rng(6)
    action = rng.integers(0, 2, 200)
    steps = logged(action, 0.5, rng.uniform(0.01, 0.05, 200))
    actions = np.ones(200, dtype=np.int64)
    given = np.full((200, 2), 0.5)   # far from every latency: DR's figure moves with it
    with_given = evaluate_policy(steps, actions, predicted=given)["latency_dr_s"]
    assert with_given.value == pytest.approx(estimate(steps, always(CLOUD, 200), "dr", given)[0].value)
    assert with_given.value != pytest.approx(evaluate_policy(steps, actions)["latency_dr_s"].value)
