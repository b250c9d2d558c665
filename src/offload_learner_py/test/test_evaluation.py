import numpy as np
import pytest

from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.evaluation import (accuracy, confusion_matrix, evaluate, learned_cpu_threshold,
                                           oracle_actions)
from statetools import raw_states


def _table(local_s, cloud_s, cpu=None):
    n = len(local_s)
    return TransitionTable(t=np.arange(n), input_size=np.full(n, 0.1),
                           cpu_availability=np.full(n, 0.6) if cpu is None else cpu, round_trip_s=np.full(n, 0.03),
                           local_s=local_s, cloud_s=cloud_s, action=np.zeros(n, np.int64),
                           action_propensity=np.ones(n), reward=np.zeros(n))


def test_oracle_accuracy_and_confusion():
    table = _table([0.1, 0.2, 0.3, 0.4], [0.2, 0.1, 0.3, 0.1])
    assert oracle_actions(table).tolist() == [0, 1, 0, 1]  # the tie goes to local by default
    actions = np.array([0, 0, 1, 1])
    assert accuracy(actions, table) == 0.75  # the tie (row 2) is right either way
    assert confusion_matrix(actions, table).tolist() == [[1, 0], [1, 2]]


def test_latency_savings_and_regret():
    table = _table([0.1, 0.2, 0.4, 0.4], [0.2, 0.1, 0.1, 0.5])
    result = evaluate(np.array([0, 1, 0, 0]), table)
    assert result["mean_latency_s"] == pytest.approx((0.1 + 0.1 + 0.4 + 0.4) / 4)
    assert result["cumulative_latency_s"] == pytest.approx(1.0)
    assert result["mean_latency_always_local_s"] == pytest.approx(0.275)
    assert result["mean_latency_always_cloud_s"] == pytest.approx(0.225)
    assert result["savings_vs_local_pct"] == pytest.approx(100 * (0.275 - 0.25) / 0.275)
    assert result["savings_vs_cloud_pct"] == pytest.approx(100 * (0.225 - 0.25) / 0.225)
    assert result["regret_s"] == pytest.approx(0.3)
    assert result["accuracy"] == 0.75 and result["cloud_share"] == 0.25


def test_learned_threshold_of_a_step_shaped_q_function():
    states = raw_states(np.full(200, 0.1), np.linspace(0.5, 0.7, 200), np.full(200, 0.03))

    def q_values(probe):
        return np.stack([np.zeros(len(probe)), np.tanh((0.61 - probe[:, 1]) * 50)], 1)

    assert learned_cpu_threshold(q_values, states) == pytest.approx(0.61, abs=1e-3)


def test_learned_threshold_picks_the_main_switch_and_reports_nan_without_one():
    states = raw_states(np.full(200, 0.1), np.linspace(0.5, 0.7, 200), np.full(200, 0.03))

    def wiggly(probe):  # cloud below 0.6 except a narrow dip at 0.52
        u = probe[:, 1]
        diff = np.where(u < 0.6, 1.0, -1.0) - 2.5 * (np.abs(u - 0.52) < 0.003)
        return np.stack([np.zeros(len(u)), diff], 1)

    assert learned_cpu_threshold(wiggly, states) == pytest.approx(0.6, abs=1e-3)
    assert np.isnan(learned_cpu_threshold(lambda p: np.tile([0.0, 1.0], (len(p), 1)), states))
