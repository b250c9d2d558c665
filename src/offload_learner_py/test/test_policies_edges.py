"""The policies' edges that the end-to-end tests pass through without looking (found by `make mutate` over
core/policies.py, #31): what a fixed or random policy reports, where a threshold may sit, how a fitted threshold
treats equal input sizes and one-sided tables, and that a learning DQN's decisions always read its latest network."""
import dataclasses
import math

import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal, Decision, DQNPolicy, InputSizeThreshold, \
    RandomPolicy
from offload_learner_py.core.state import State
from offload_learner_py.data.dataset import TransitionTable

STATE = State(1.0, 0.5, 0.05, 2e7)


def table(d, local_s, cloud_s):
    n = len(d)
    return TransitionTable(t=np.arange(n), input_size=np.asarray(d, float), cpu_availability=np.full(n, 0.5),
                           round_trip_s=np.full(n, 0.05), local_s=np.asarray(local_s, float),
                           cloud_s=np.asarray(cloud_s, float), action=np.zeros(n, np.int64),
                           action_propensity=np.full(n, 0.5), reward=np.zeros(n))


def test_a_decision_cannot_be_changed_after_it_was_made():
    with pytest.raises(dataclasses.FrozenInstanceError):
        Decision(LOCAL, 1.0).action = CLOUD


@pytest.mark.parametrize("policy", [AlwaysLocal(), AlwaysCloud(), RandomPolicy(), InputSizeThreshold(1.0)])
def test_a_baseline_never_learns_and_reports_nothing_learned(policy):
    assert policy.learns is False and policy.warming_up is False and policy.steps == 0
    assert policy.stats() == {"steps": 0, "gradient_steps": 0, "replay_size": 0, "epsilon": 0.0}
    assert policy.learn(STATE, LOCAL, 0.5) is None and policy.flush() is None


def test_a_fixed_policy_keeps_its_name_unless_given_one():
    assert AlwaysLocal().name == "always_local" and AlwaysCloud(name="cloud").name == "cloud"


def test_a_random_policy_takes_both_sides_evenly_with_propensity_one_half():
    policy = RandomPolicy(seed=3)
    decisions = [policy.decide(STATE) for _ in range(2000)]
    actions = np.array([d.action for d in decisions])
    assert set(actions) == {LOCAL, CLOUD} and 900 < int((actions == CLOUD).sum()) < 1100
    assert {d.propensity for d in decisions} == {0.5}
    rows = table(np.linspace(0, 2, 2000), np.ones(2000), np.ones(2000))
    chosen = policy.choose(rows)
    assert set(chosen) == {LOCAL, CLOUD} and 900 < int(chosen.sum()) < 1100
    assert np.array_equal(chosen, policy.choose(rows))             # the same table, the same actions


@pytest.mark.parametrize("threshold", [0.0, 1e-12, 5.0])
def test_any_finite_threshold_from_zero_up_is_accepted(threshold):
    policy = InputSizeThreshold(threshold)
    assert policy.decide(State(threshold + 1.0, 0.5, 0.05, 2e7)).action == CLOUD
    assert policy.decide(State(threshold, 0.5, 0.05, 2e7)).action == LOCAL   # at the threshold: not above it


@pytest.mark.parametrize("threshold", [-1e-9, -1.0, math.inf, math.nan])
def test_a_negative_or_non_finite_threshold_is_refused(threshold):
    with pytest.raises(ValueError, match="finite and >= 0"):
        InputSizeThreshold(threshold)


def test_a_fitted_threshold_never_splits_equal_input_sizes():
    # d = 1 rows disagree (two cloud-faster, one local-faster); d = 2 rows are cloud-faster. Cutting between the
    # d = 1 rows would score best if it were allowed; equal states must get one action.
    policy = InputSizeThreshold().fit(table([1, 1, 1, 2, 2], [2, 2, 1, 2, 2], [1, 1, 2, 1, 1]))
    actions = policy.choose(table([1, 1, 1, 2, 2], np.ones(5), np.ones(5)))
    assert actions[0] == actions[1] == actions[2]
    assert policy.threshold in (-math.inf, 1.5) or policy.threshold < 1


def test_one_sided_tables_fit_an_always_rule():
    cloud_faster = InputSizeThreshold().fit(table([0.5, 1, 2], [3, 3, 3], [1, 1, 1]))
    assert cloud_faster.threshold == -math.inf and cloud_faster.cloud_above
    assert list(cloud_faster.choose(table([0.0, 0.5, 9.0], np.ones(3), np.ones(3)))) == [CLOUD] * 3
    local_faster = InputSizeThreshold().fit(table([0.5, 1, 2], [1, 1, 1], [3, 3, 3]))
    assert list(local_faster.choose(table([0.0, 0.5, 9.0], np.ones(3), np.ones(3)))) == [LOCAL] * 3


def test_a_learning_dqn_decides_with_its_latest_network_after_every_step():
    config = DQNConfig.from_dict({"hidden_sizes": [8], "learning_starts": 3, "train_frequency": 1, "batch_size": 4,
                                  "seed": 5})
    policy = DQNPolicy(config)
    policy.fit(table(np.linspace(0.1, 2, 8), np.linspace(1, 2, 8), np.full(8, 1.5)))
    rng = np.random.default_rng(0)
    for step in range(30):
        state = State(float(rng.uniform(0, 2)), float(rng.uniform(0, 1)), 0.05, 2e7)
        policy.learn(state, int(rng.integers(0, 2)), float(rng.uniform(-1, 1)))
        _, q_local, q_cloud = policy.agent.fast_decision().decide(*STATE.as_tuple())
        decided = policy.decide(STATE)
        assert (decided.q_local, decided.q_cloud) == (q_local, q_cloud), f"a stale network after step {step}"
    assert policy.agent.gradient_steps > 0


def test_a_dqn_policy_without_an_agent_has_taken_no_steps():
    assert DQNPolicy().steps == 0
