"""More of the policies' edges `make mutate` found unchecked over core/policies.py (#31): a fitted threshold's
side and cut where cloud wins small inputs, a cut between equal sizes later in the table, ties that keep the
always-local rule, a fixed rule with cloud below; the DQN's exploration schedule, its seed, and its last
transition."""
import math

import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.policies import DQNPolicy, InputSizeThreshold, Policy
from offload_learner_py.core.state import State
from test_policies_edges import table

STATE = State(1.0, 0.5, 0.05, 2e7)


def sizes(*d):
    return table(list(d), np.ones(len(d)), np.ones(len(d)))


def test_cloud_faster_on_small_inputs_fits_cloud_below_the_cut():
    policy = InputSizeThreshold().fit(table([1, 2, 3], [2, 2, 1], [1, 1, 2]))
    assert policy.cloud_above is False and policy.threshold == 2.5
    assert list(policy.choose(sizes(1, 2, 3))) == [CLOUD, CLOUD, LOCAL]


def test_no_cut_between_equal_sizes_anywhere_in_the_table():
    # The d = 2 rows disagree, and a cut between them would classify all four rows right.
    policy = InputSizeThreshold().fit(table([1, 2, 2, 3], [1, 1, 2, 2], [2, 2, 1, 1]))
    assert policy.threshold in (1.5, 2.5)


def test_a_tie_keeps_the_first_rule_that_scores_best_among_allowed_cuts():
    """Local faster on two of three rows, cloud on the middle one whose size equals the first's: always-local
    (a cut above every size) is the best allowed rule; the cut between the equal sizes is not allowed."""
    policy = InputSizeThreshold().fit(table([1, 1, 2], [1, 2, 1], [2, 1, 2]))
    assert policy.cloud_above and policy.threshold == math.inf
    assert list(policy.choose(sizes(1, 2))) == [LOCAL, LOCAL]


def test_a_fixed_rule_with_cloud_below_keeps_large_inputs_local():
    policy = InputSizeThreshold(1.0, cloud_above=False)
    assert policy.decide(State(2.0, 0.5, 0.05, 2e7)).action == LOCAL
    assert policy.decide(State(0.5, 0.5, 0.05, 2e7)).action == CLOUD


def test_a_policy_must_say_how_it_chooses():
    with pytest.raises(TypeError):
        Policy()


def _learning(learning_starts=3, seed=None):
    config = DQNConfig.from_dict({"hidden_sizes": [8], "learning_starts": learning_starts, "train_frequency": 1,
                                  "batch_size": 2, "seed": 5, "epsilon": 0.1})
    return DQNPolicy(config, agent=DQNAgent(config), seed=seed)


def test_a_learning_dqn_explores_fully_during_warm_up_then_at_epsilon():
    policy = _learning()
    assert policy.warming_up is True and policy.epsilon() == 1.0
    assert policy.decide(STATE).propensity == 0.5
    for _ in range(4):
        policy.learn(STATE, LOCAL, 0.5)
    assert policy.agent.steps == 3
    assert policy.warming_up is False and policy.epsilon() == 0.1
    assert min(abs(policy.decide(STATE).propensity - p) for p in (0.05, 0.95)) < 1e-12


def test_the_exploration_draws_follow_the_seed_given():
    def draws(seed):
        policy = _learning(learning_starts=1000, seed=seed)
        return [policy.decide(STATE).action for _ in range(40)]
    assert draws(7) == draws(7)
    assert draws(7) != draws(8)


def test_flush_stores_the_last_transition_with_its_own_state():
    policy = _learning(learning_starts=1000)
    policy.learn(STATE, CLOUD, 0.25)
    assert policy.agent.steps == 0           # stored when its successor arrives
    policy.flush()
    assert policy.agent.steps == 1
    assert policy.flush() is None and policy.agent.steps == 1
