"""The hindsight threshold: the best fixed "offload when d_t > t" rule on a run's probes, over an exhaustive grid;
and the share of its gap to the oracle a policy closes."""
import numpy as np
import pytest

from offload_demos.hindsight import best_threshold, gap_closed, rule_mean_s, threshold_grid


def probes(seed, n=200):
    rng = np.random.default_rng(seed)
    d = rng.choice(rng.uniform(0, 5, n // 2), n)          # repeated d values too, as a run's equal distances give
    local = 0.01 + 0.05 * d * rng.uniform(0.5, 1.5, n)
    cloud = rng.choice([0.02, 0.3], n) + 0.01 * d         # a link that is sometimes slow: no rule is the oracle
    return d, local, cloud


@pytest.mark.parametrize("seed", range(12))
def test_the_pick_is_the_best_of_its_grid_and_no_threshold_beats_it(seed):
    d, local, cloud = probes(seed)
    search = best_threshold(d, local, cloud)
    brute = [rule_mean_s(t, d, local, cloud) for t in search.grid]
    assert search.means_s == pytest.approx(brute)
    assert search.mean_s == pytest.approx(min(brute))
    assert search.threshold == search.grid[int(np.argmin(brute))]
    # the grid is exhaustive: no threshold anywhere does better, always-local and always-cloud included
    for t in np.concatenate([np.linspace(-1, 6, 2001), np.unique(d)]):
        assert rule_mean_s(t, d, local, cloud) >= search.mean_s - 1e-12
    assert search.mean_s >= np.minimum(local, cloud).mean()
    assert search.cloud_share == pytest.approx(np.mean(d > search.threshold))


@pytest.mark.parametrize("cloud_wins", [True, False])
def test_always_one_side_is_on_the_grid(cloud_wins):
    d = np.array([0.5, 1.0, 2.0, 3.0])
    local, cloud = (d * 0 + 0.2, d * 0 + 0.1) if cloud_wins else (d * 0 + 0.1, d * 0 + 0.2)
    search = best_threshold(d, local, cloud)
    assert search.mean_s == pytest.approx(0.1)
    assert search.cloud_share == (1.0 if cloud_wins else 0.0)


def test_the_grid_cuts_between_every_pair_of_distinct_values():
    assert list(threshold_grid([2.0, 1.0, 2.0, 3.0])) == [0.0, 1.5, 2.5, 4.0]
    with pytest.raises(ValueError):
        threshold_grid([])
    with pytest.raises(ValueError):
        best_threshold([1.0, 2.0], [0.1, np.nan], [0.1, 0.2])


def test_the_gap_closed_is_one_at_the_oracle_and_zero_at_the_threshold():
    assert gap_closed(0.06, 0.04, 0.04) == pytest.approx(1.0)
    assert gap_closed(0.06, 0.06, 0.04) == pytest.approx(0.0)
    assert gap_closed(0.06, 0.05, 0.04) == pytest.approx(0.5)
    assert gap_closed(0.06, 0.08, 0.04) == pytest.approx(-1.0)
    assert gap_closed(0.04, 0.05, 0.04) is None and gap_closed(None, 0.05, 0.04) is None
