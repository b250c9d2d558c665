import numpy as np
import pytest

from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.evaluation import accuracy
from offload_learner_py.core.lstm_baseline import LSTMConfig, LSTMPolicy
from offload_learner_py.core.policies import (AlwaysCloud, AlwaysLocal, DQNPolicy, InputSizeThreshold, OraclePolicy,
                                         Policy, RandomPolicy)
from offload_learner_py.data.synthetic import generate_synthetic


ALL = [AlwaysLocal(), AlwaysCloud(), RandomPolicy(3), InputSizeThreshold(), OraclePolicy(),
       LSTMPolicy(LSTMConfig(epochs=3)), DQNPolicy(DQNConfig(learning_starts=20, batch_size=16))]


@pytest.mark.parametrize("policy", ALL, ids=lambda p: p.name)
def test_every_policy_shares_one_interface(policy, size_split_table):
    train, test = size_split_table(120, 1), size_split_table(40, 2)
    assert isinstance(policy, Policy)
    actions = policy.fit(train).choose(test)
    assert actions.shape == (40,) and set(actions.tolist()) <= {0, 1}


def test_fixed_policies(size_split_table):
    table = size_split_table(50, 0)
    assert np.all(AlwaysLocal().choose(table) == 0) and np.all(AlwaysCloud().choose(table) == 1)
    assert np.array_equal(RandomPolicy(4).choose(table), RandomPolicy(4).choose(table))
    # The table is built so that the cloud is faster exactly above d = 0.01 (conftest): the oracle must
    # say so, and accuracy must score that answer 1 and its opposite 0.
    by_construction = (table.input_size > 0.01).astype(np.int64)
    assert 0 < by_construction.sum() < len(table)
    assert np.array_equal(OraclePolicy().choose(table), by_construction)
    assert accuracy(by_construction, table) == 1.0 and accuracy(1 - by_construction, table) == 0.0


def test_threshold_on_input_size_is_fitted_from_training_data(size_split_table):
    policy = InputSizeThreshold().fit(size_split_table(400, 1))
    assert policy.cloud_above and policy.threshold == pytest.approx(0.01, rel=0.3)
    test = size_split_table(400, 2)
    assert accuracy(policy.choose(test), test) > 0.97
    flipped = size_split_table(400, 3)
    flipped.local_s, flipped.cloud_s = flipped.cloud_s, flipped.local_s
    assert not InputSizeThreshold().fit(flipped).cloud_above
    with pytest.raises(RuntimeError):
        InputSizeThreshold().choose(test)


def test_threshold_all_one_side_means_a_fixed_policy(small_trace):
    table = generate_synthetic("cloud", small_trace, 200, seed=1)
    policy = InputSizeThreshold().fit(table)
    assert np.all(policy.choose(table) == 1)


def test_dqn_policy_learns_offline_from_a_table(small_trace):
    train = generate_synthetic("cloud", small_trace, 400, seed=2)
    test = generate_synthetic("cloud", small_trace, 200, seed=3)
    policy = DQNPolicy(DQNConfig(seed=2, learning_starts=100)).fit(train)
    assert accuracy(policy.choose(test), test) > 0.95
    assert len(policy.online_run.table) == 400


@pytest.mark.parametrize("make", [lambda: AlwaysLocal(), lambda: AlwaysCloud(), lambda: InputSizeThreshold(0.01),
                                  lambda: InputSizeThreshold(), lambda: DQNPolicy(DQNConfig(learning_starts=20,
                                                                                           batch_size=16))],
                         ids=["local", "cloud", "threshold_fixed", "threshold_fitted", "dqn"])
def test_an_online_decision_is_the_offline_choice_for_the_same_state(make, size_split_table):
    """One policy, two uses: the router's per-request decide and the offline batch choose agree on every
    state (the DQN greedy: its numpy snapshot decides as the torch network chooses)."""
    from offload_learner_py.core.state import State
    policy = make().fit(size_split_table(120, 1))
    policy.explore = False
    test = size_split_table(60, 2)
    decided = [policy.decide(State(*row)) for row in test.states]
    assert [d.action for d in decided] == policy.choose(test).tolist()
    assert all(d.propensity == 1.0 for d in decided)


def test_the_oracle_and_the_lstm_are_offline_only():
    from offload_learner_py.core.state import State
    for policy in (OraclePolicy(), LSTMPolicy(LSTMConfig(epochs=1))):
        with pytest.raises(NotImplementedError, match="offline only"):
            policy.decide(State(1.0, 0.5, 0.05, 2e7))


def test_a_fixed_threshold_is_not_refitted_and_must_be_finite(size_split_table):
    policy = InputSizeThreshold(5.0, name="threshold").fit(size_split_table(120, 1))
    assert policy.threshold == 5.0 and policy.name == "threshold"
    with pytest.raises(ValueError, match="threshold"):
        InputSizeThreshold(float("nan"))
