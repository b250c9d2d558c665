import numpy as np
import pytest

from offload_learner_py.core.reward import CostWeights
from offload_learner_py.data.synthetic import generate_synthetic


def _ratios(table):
    return np.round(table.cloud_s / table.local_s, 6)


def test_local_dataset_never_has_a_faster_cloud(small_trace):
    table = generate_synthetic("local", small_trace, 2000, seed=1)
    assert set(_ratios(table)) == {round(1.0 + k / 10, 6) for k in range(10)}
    assert np.all(table.cloud_s >= table.local_s)


def test_cloud_dataset_follows_eq_14(small_trace):
    table = generate_synthetic("cloud", small_trace, 2000, seed=1)
    assert set(_ratios(table)) == {round(0.1 + k / 10, 6) for k in range(10)}
    assert np.all(table.cloud_s <= table.local_s)


def test_cpu_dataset_follows_eq_15_with_u_on_both_sides(small_trace):
    table = generate_synthetic("cpu", small_trace, 2000, seed=1)
    below = table.cpu_availability < 0.6
    assert np.all(table.cloud_s[below] < table.local_s[below])
    assert np.all(table.cloud_s[~below] > table.local_s[~below])
    assert 0.4 < below.mean() < 0.6
    assert table.cpu_availability.min() >= 0.5 and table.cpu_availability.max() <= 0.7


def test_rows_come_from_the_trace_with_uniform_logging(small_trace):
    table = generate_synthetic("cpu", small_trace, 500, seed=2)
    assert set(table.local_s) <= set(small_trace.local_s)
    index = {v: i for i, v in enumerate(small_trace.local_s)}
    assert np.array_equal(table.input_size, small_trace.input_size[[index[v] for v in table.local_s]])
    assert np.all(table.action_propensity == 0.5) and 0.4 < table.action.mean() < 0.6
    # Eq. 10 with alpha = beta and l_cloud = m * l_local: offloading earns (1 - m) / (1 + m), local 0.
    m = table.cloud_s / table.local_s
    assert np.allclose(table.reward, np.where(table.action == 1, (1.0 - m) / (1.0 + m), 0.0), rtol=0, atol=1e-12)
    assert np.all(np.abs(table.round_trip_s / 0.03 - 1) <= 0.05 + 1e-12)


def test_same_seed_same_dataset(small_trace):
    a, b = (generate_synthetic("local", small_trace, 100, seed=5) for _ in range(2))
    assert np.array_equal(a.cloud_s, b.cloud_s) and np.array_equal(a.cpu_availability, b.cpu_availability)
    assert not np.array_equal(a.cloud_s, generate_synthetic("local", small_trace, 100, seed=6).cloud_s)


def test_bad_arguments(small_trace):
    with pytest.raises(ValueError):
        generate_synthetic("edge", small_trace, 10, seed=1)
    with pytest.raises(ValueError):
        generate_synthetic("local", small_trace, 0, seed=1)


def test_rewards_are_eq_10_of_the_drawn_multipliers(small_trace):
    # local (eq. 13): m in {1.0, ..., 1.9}, so an offloaded step earns one of ten known rewards, none positive.
    table = generate_synthetic("local", small_trace, 400, seed=3)
    offloaded = table.reward[table.action == 1]
    known = {round((1.0 - m) / (1.0 + m), 9) for m in (1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6, 1.7, 1.8, 1.9)}
    assert {round(r, 9) for r in offloaded} == known
    assert np.all(table.reward[table.action == 0] == 0.0)
    # alpha = 0.3, beta = 0.7: r = -(0.7 m l - 0.3 l) / (0.3 l + 0.7 m l) = (0.3 - 0.7 m) / (0.3 + 0.7 m).
    weighted = generate_synthetic("cloud", small_trace, 400, seed=3, weights=CostWeights(0.3, 0.7))
    m = weighted.cloud_s / weighted.local_s
    assert np.allclose(weighted.reward, np.where(weighted.action == 1, (0.3 - 0.7 * m) / (0.3 + 0.7 * m), 0.0),
                       rtol=0, atol=1e-12)
    assert weighted.metadata["alpha"] == 0.3 and weighted.metadata["beta"] == 0.7
