"""The robot guard's test statistic against scipy's own Welch test, and its settings' bounds (found by
`make mutate` over online/model_guard.py, #31: 41 of 109 run survived test_fleet_robot.py, the statistic's
variance and degrees of freedom among them)."""
import dataclasses
import math

import numpy as np
import pytest
from scipy import stats

from offload_learner_py.online.model_guard import GuardConfig, welch_worse


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("margin", [0.0, 0.05])
def test_the_statistic_is_welchs_one_sided_test_beyond_the_margin(seed, margin):
    rng = np.random.default_rng(seed)
    new = list(rng.gamma(2.0 + seed, 0.01, 25 + seed))
    old = list(rng.gamma(2.0, 0.012, 31))
    worse, t, critical = welch_worse(new, old, margin, 0.95)
    # Welch's test of mean(new) - (1 + margin) mean(old) > 0: the same as testing new against old shifted by
    # margin * mean(old) (a shift moves no variance)
    shifted = np.asarray(old) + margin * np.mean(old)
    reference = stats.ttest_ind(new, shifted, equal_var=False, alternative="greater")
    assert t == pytest.approx(reference.statistic, rel=1e-9)
    se2 = np.var(new, ddof=1) / len(new) + np.var(old, ddof=1) / len(old)
    df = se2 ** 2 / ((np.var(new, ddof=1) / len(new)) ** 2 / (len(new) - 1)
                     + (np.var(old, ddof=1) / len(old)) ** 2 / (len(old) - 1))
    assert critical == pytest.approx(stats.t.ppf(0.95, df), rel=1e-9)
    assert worse == (reference.pvalue < 0.05)


def test_samples_without_spread_decide_by_the_means_alone():
    assert welch_worse([2.0, 2.0], [1.0, 1.0], 0.05, 0.95) == (True, math.inf, 0.0)
    assert welch_worse([1.0, 1.0], [2.0, 2.0], 0.05, 0.95) == (False, -math.inf, 0.0)
    assert welch_worse([1.25, 1.25], [1.0, 1.0], 0.25, 0.95)[:2] == (False, 0.0)   # exactly at the margin


@pytest.mark.parametrize("changes", [{"requests": -1}, {"requests": 1}, {"margin": -0.01}, {"margin": 10.0},
                                     {"confidence": 0.49}, {"confidence": 1.0}])
def test_settings_out_of_bounds_are_refused(changes):
    with pytest.raises(ValueError):
        GuardConfig(**changes)


@pytest.mark.parametrize("changes", [{"requests": 0}, {"requests": 2}, {"margin": 0.0}, {"margin": 9.99},
                                     {"confidence": 0.5}, {"confidence": 0.999}])
def test_settings_at_their_bounds_are_taken(changes):
    assert dataclasses.asdict(GuardConfig(**changes)).items() >= changes.items()


def test_the_guard_settings_are_fixed_once_made():
    with pytest.raises(dataclasses.FrozenInstanceError):
        GuardConfig().requests = 5
