"""bench-policies' ratio of a policy's mean latency to always-local's: the point is the table's pooled means, the
interval comes from the pairs of runs (the machine's state between rounds is the noise) and covers the truth at its
nominal rate."""
import numpy as np
import pytest

from offload_demos.mean_ratio import mean_ratio, ratios_to


def rounds(rng, pairs, truth, requests=200, machine=0.12, run=0.08):
    """Repeats as bench-policies runs them: the same seeded requests every run; each round's machine state slows both
    runs of the round alike; each run has its own drift and request noise."""
    base = rng.lognormal(np.log(2.5e-3), 0.6, requests)
    policy, baseline = [], []
    for _ in range(pairs):
        state = rng.normal(0.0, machine)
        policy.append(base * truth * np.exp(state + rng.normal(0.0, run)) * rng.lognormal(0.0, 0.5, requests))
        baseline.append(base * np.exp(state + rng.normal(0.0, run)) * rng.lognormal(0.0, 0.5, requests))
    return policy, baseline


@pytest.mark.parametrize("pairs", [3, 5])
def test_the_interval_covers_the_true_ratio_at_its_nominal_rate(pairs):
    covered = 0
    for seed in range(400):
        ratio = mean_ratio(*rounds(np.random.default_rng(seed), pairs, truth=1.05))
        covered += ratio.low <= 1.05 <= ratio.high
    assert 0.91 <= covered / 400 <= 0.985


def test_the_ratio_is_of_the_pooled_means_and_the_interval_is_as_wide_as_the_pairs_disagree():
    policy = [np.full(100, 3.3e-3), np.full(50, 2.2e-3)]
    baseline = [np.full(100, 3.0e-3), np.full(50, 2.0e-3)]
    same = mean_ratio(policy, baseline)
    assert same.ratio == pytest.approx((100 * 3.3 + 50 * 2.2) / (100 * 3.0 + 50 * 2.0))
    assert same.low == pytest.approx(same.ratio) and same.high == pytest.approx(same.ratio)   # both pairs 1.1x
    apart = mean_ratio([np.full(100, 3.3e-3), np.full(100, 2.0e-3)], [np.full(100, 3.0e-3), np.full(100, 2.0e-3)])
    assert apart.low < 1.0 < 1.1 < apart.high
    assert apart.pairs == 2


def test_one_pair_gives_no_interval():
    ratio = mean_ratio([np.full(10, 2e-3)], [np.full(10, 1e-3)])
    assert ratio.ratio == pytest.approx(2.0)
    assert ratio.low is None and ratio.high is None
    assert "no interval" in ratio.describe("dqn", "local")


@pytest.mark.parametrize("policy,baseline", [([], []), ([[1e-3]], []), ([[1e-3]], [[float("nan")]]), ([[1e-3]], [[]]),
                                             ([[1e-3]], [[0.0]])])
def test_refuses_what_it_cannot_compare(policy, baseline):
    with pytest.raises(ValueError):
        mean_ratio(policy, baseline)


def test_every_policy_against_the_baseline_and_a_run_without_answers_loses_only_its_own_ratio(capsys):
    runs = {"local": [np.full(10, 2e-3), np.full(10, 2e-3)], "dqn": [np.full(10, 2.2e-3), np.full(10, 2.2e-3)],
            "cloud": [np.full(10, 3e-3), np.array([])]}
    ratios = ratios_to(runs, "local")
    assert set(ratios) == {"dqn", "cloud"}
    assert ratios["dqn"]["ratio"] == pytest.approx(1.1) and ratios["dqn"]["pairs"] == 2
    assert ratios["cloud"] is None
    assert "cloud: no ratio to local" in capsys.readouterr().out
    assert ratios_to({"dqn": runs["dqn"]}, "local") == {}
