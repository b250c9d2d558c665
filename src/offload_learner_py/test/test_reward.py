import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.reward import CostWeights, cloud_latency_s, reward, rewards


def test_local_action_is_always_zero_reward():
    assert reward(LOCAL, 0.2, 0.1) == 0.0
    assert reward(LOCAL, 0.1, 0.2) == 0.0


def test_offloading_reward_sign_and_value():
    assert reward(CLOUD, 0.3, 0.1) == pytest.approx(0.5)    # -(0.05 - 0.15) / 0.2
    assert reward(CLOUD, 0.1, 0.3) == pytest.approx(-0.5)


def test_equal_times_give_zero():
    assert reward(CLOUD, 0.07, 0.07) == 0.0


@pytest.mark.parametrize("local_s,cloud_s", [(0.0, 0.1), (0.1, 0.0), (0.0, 0.0), (-0.1, 0.1), (np.inf, 0.1),
                                             (0.1, np.nan)])
def test_zero_negative_or_non_finite_times_are_rejected(local_s, cloud_s):
    with pytest.raises(ValueError):
        reward(CLOUD, local_s, cloud_s)


def test_rewards_stay_in_minus_one_to_one():
    rng = np.random.default_rng(3)
    local_s, cloud_s = 10.0 ** rng.uniform(-6, 1, (2, 5000))
    for alpha in (0.0, 0.3, 0.5, 1.0):
        r = rewards(np.full(5000, CLOUD), local_s, cloud_s, CostWeights(alpha, 1.0 - alpha))
        assert np.all((r >= -1.0) & (r <= 1.0))
    # The bounds are reached at the extremes of the weights.
    assert reward(CLOUD, 0.1, 0.2, CostWeights(0.0, 1.0)) == -1.0
    assert reward(CLOUD, 0.1, 0.2, CostWeights(1.0, 0.0)) == 1.0


def test_weights_must_sum_to_one_and_lie_in_unit_interval():
    CostWeights(0.3, 0.7)
    for alpha, beta in [(0.5, 0.6), (1.2, -0.2), (-0.1, 1.1)]:
        with pytest.raises(ValueError):
            CostWeights(alpha, beta)


def test_alpha_above_beta_favours_offloading():
    neutral = reward(CLOUD, 0.1, 0.12)
    assert neutral < 0
    assert reward(CLOUD, 0.1, 0.12, CostWeights(0.6, 0.4)) > 0


def test_cloud_timeout_counts_as_the_timeout():
    assert cloud_latency_s(None, 5.0) == 5.0
    assert cloud_latency_s(7.5, 5.0) == 5.0
    assert cloud_latency_s(0.08, 5.0) == 0.08
    assert reward(CLOUD, 0.1, cloud_latency_s(None)) == pytest.approx(-(5.0 - 0.1) / 5.1)
    with pytest.raises(ValueError):
        cloud_latency_s(0.1, 0.0)


def test_vector_rewards_match_scalar():
    rng = np.random.default_rng(1)
    actions = rng.integers(0, 2, 100)
    local_s, cloud_s = rng.uniform(0.01, 1, (2, 100))
    expected = [reward(int(a), l, c) for a, l, c in zip(actions, local_s, cloud_s)]
    assert np.allclose(rewards(actions, local_s, cloud_s), expected)
    with pytest.raises(ValueError):
        rewards([2], [0.1], [0.1])


def test_weights_cannot_be_changed_after_validation():
    weights = CostWeights(0.3, 0.7)
    with pytest.raises(AttributeError):
        weights.alpha = 0.9  # would break alpha + beta = 1 behind the validation's back


def test_any_positive_timeout_is_valid_and_none_other():
    assert cloud_latency_s(0.1, 0.5) == 0.1 and cloud_latency_s(None, 0.5) == 0.5
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="timeout_s must be positive"):
            cloud_latency_s(0.1, bad)


@pytest.mark.parametrize("local_s,cloud_s", [(0.1, -0.1), (0.1, np.inf), (np.nan, 0.1)])
def test_scalar_reward_rejects_each_bad_latency(local_s, cloud_s):
    with pytest.raises(ValueError, match="latencies must be finite and positive"):
        reward(CLOUD, local_s, cloud_s)


@pytest.mark.parametrize("column", ["local_s", "cloud_s"])
@pytest.mark.parametrize("bad", [0.0, -0.1, -2.0, np.inf, np.nan])
def test_vector_rewards_reject_a_bad_latency_in_either_column(column, bad):
    good = {"local_s": [0.1, 0.2], "cloud_s": [0.2, 0.1]}
    good[column] = [0.1, bad]
    with pytest.raises(ValueError, match="latencies must be finite and positive"):
        rewards([CLOUD, CLOUD], good["local_s"], good["cloud_s"])


@pytest.mark.parametrize("action", [-1, 2, 3])
def test_vector_rewards_reject_actions_other_than_local_and_cloud(action):
    with pytest.raises(ValueError, match="actions must be"):
        rewards([LOCAL, action], [0.1, 0.1], [0.2, 0.2])
