"""Per-side latency models: they learn a latency that depends on the state, impute it and bound it."""
import math

import numpy as np
import pytest

from offload_learner_py.online.latency_model import LatencyModel, LatencyModelConfig


def local_latency_s(d, u, b):
    """A planner whose time grows with d_t and with a busy CPU, as the robot's does."""
    return 0.02 * (1 + d) ** 1.5 / max(u, 0.1)


def test_learns_a_state_dependent_latency_and_imputes_it():
    rng = np.random.default_rng(4)
    model = LatencyModel()
    for _ in range(400):
        state = (rng.uniform(0, 3), rng.uniform(0.2, 1), rng.uniform(0.02, 0.4))
        model.observe(state, local_latency_s(*state) * math.exp(rng.normal(0, 0.05)))
    for state in ((0.2, 0.9, 0.1), (2.5, 0.3, 0.1), (1.0, 0.6, 0.3)):
        assert model.impute_s(state) == pytest.approx(local_latency_s(*state), rel=0.15)
    short, long = model.impute_s((0.2, 0.9, 0.1)), model.impute_s((2.5, 0.3, 0.1))
    assert long > 5 * short


def test_quantile_is_above_the_median_and_widens_with_noise():
    rng = np.random.default_rng(5)
    quiet, noisy = LatencyModel(), LatencyModel()
    for _ in range(300):
        state = (1.0, 0.5, 0.1)
        quiet.observe(state, 0.1 * math.exp(rng.normal(0, 0.02)))
        noisy.observe(state, 0.1 * math.exp(rng.normal(0, 0.4)))
    state = (1.0, 0.5, 0.1)
    assert quiet.quantile_s(state, 0.95) > quiet.impute_s(state)
    spread = lambda model: math.log(model.quantile_s(state, 0.95) / model.impute_s(state))  # noqa: E731
    assert spread(noisy) == pytest.approx(1.645 * 0.4, rel=0.2) and spread(quiet) == pytest.approx(1.645 * 0.02, rel=0.3)


def test_not_ready_before_min_samples_and_ignores_invalid_latencies():
    model = LatencyModel(LatencyModelConfig(min_samples=5))
    for latency in (float("nan"), float("inf"), 0.0, -1.0):
        model.observe((1.0, 0.5, 0.1), latency)
    assert model.samples == 0 and model.impute_s((1.0, 0.5, 0.1)) is None
    for _ in range(5):
        model.observe((1.0, 0.5, 0.1), 0.1)
    assert model.ready and model.impute_s((1.0, 0.5, 0.1)) == pytest.approx(0.1, rel=0.05)


def test_forgetting_follows_a_latency_that_drifts():
    model = LatencyModel(LatencyModelConfig(forgetting=0.97))
    for _ in range(200):
        model.observe((1.0, 0.5, 0.1), 0.1)
    for _ in range(200):
        model.observe((1.0, 0.5, 0.1), 0.4)
    assert model.impute_s((1.0, 0.5, 0.1)) == pytest.approx(0.4, rel=0.05)


@pytest.mark.parametrize("kwargs", [{"forgetting": 0.2}, {"prior_precision": 0.0}, {"min_samples": 0}])
def test_config_rejects_bad_values(kwargs):
    with pytest.raises(ValueError):
        LatencyModelConfig(**kwargs)
