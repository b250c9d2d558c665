"""The issue's bar, checked on seeds that were never used to choose the hyperparameters. The full
five-seed report is the `sweep` command; these runs keep the suite short."""
import numpy as np
import pytest

from offload_learner_py.core.config import EXPERIMENT_SCHEDULE, DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.evaluation import accuracy, learned_cpu_threshold
from offload_learner_py.offline.simulation import run_online
from offload_learner_py.data.synthetic import generate_synthetic


def _online(kind, seed, trace, steps=1000):
    stream = generate_synthetic(kind, trace, steps, seed)
    agent = DQNAgent(DQNConfig(seed=seed, **EXPERIMENT_SCHEDULE))
    run = run_online(agent, stream)
    half = steps // 2
    return agent, stream, accuracy(run.greedy_action[half:], stream.slice(half, steps)), run


@pytest.mark.parametrize("kind,seed", [("local", 8675), ("local", 31337), ("cloud", 4242), ("cloud", 90210)])
def test_local_and_cloud_reach_99_percent_over_the_last_half(bundled_trace, kind, seed):
    _, _, greedy_accuracy, run = _online(kind, seed, bundled_trace)
    assert greedy_accuracy >= 0.99
    # Taken actions include 10 % exploration, half of it towards the wrong action.
    assert np.mean(run.table.action_propensity[500:] < 0.5) == pytest.approx(0.05, abs=0.03)


def test_cpu_threshold_is_learned_near_0_6(bundled_trace):
    agent, stream, greedy_accuracy, _ = _online("cpu", 2718, bundled_trace)
    assert greedy_accuracy >= 0.95
    assert learned_cpu_threshold(agent.q_values, stream.states) == pytest.approx(0.6, abs=0.03)
