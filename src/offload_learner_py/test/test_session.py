"""The learner's session settings without ROS: policy choice and resume order, the DQN settings of a mode, a
loaded model's training schedule. What the learner does with them (checkpoint cadence, statistics) is
test_learning.py's."""
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.checkpoint import save_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.state import State
from offload_learner_py.online.session import SessionConfig, dqn_settings, make_policy


def saved_agent(path, steps):
    agent = DQNAgent(DQNConfig(learning_starts=0, seed=2))
    agent.steps = steps
    save_checkpoint(agent, str(path))
    return str(path)


def test_a_restarted_node_resumes_from_its_checkpoint_before_the_model(tmp_path):
    checkpoint, model = saved_agent(tmp_path / "own.pt", 70), saved_agent(tmp_path / "model.pt", 30)
    _, agent = make_policy(SessionConfig(checkpoint=checkpoint, model=model))
    assert agent.steps == 70
    _, agent = make_policy(SessionConfig(checkpoint=str(tmp_path / "new.pt"), model=model))
    assert agent.steps == 30
    _, agent = make_policy(SessionConfig(checkpoint=str(tmp_path / "new.pt")))
    assert agent.steps == 0


@pytest.mark.parametrize("name, action", [("local", LOCAL), ("cloud", CLOUD)])
def test_fixed_policies_keep_the_node_names_and_never_learn(name, action):
    policy, agent = make_policy(SessionConfig(policy=name))
    assert policy.name == name and agent is None and not policy.learns
    assert policy.decide(State(1.0, 0.5, 0.05, 2e7)).action == action


def test_an_unknown_policy_or_a_bad_dqn_block_is_refused():
    with pytest.raises(ValueError, match="~policy"):
        SessionConfig(policy="fastest")
    with pytest.raises(ValueError, match="~dqn"):
        SessionConfig(dqn=[1, 2])


def test_deployed_mode_takes_the_deployed_dqn_settings_over_the_common_ones():
    common, deployed = {"train_frequency": 1, "gamma": 0.0}, {"train_frequency": 8}
    assert dqn_settings("deployed", common, deployed) == {"train_frequency": 8, "gamma": 0.0}
    assert dqn_settings("learning", common, deployed) == common
    assert dqn_settings("deployed", common, None) == common
    with pytest.raises(ValueError, match="~deployed_dqn must be a dictionary"):
        dqn_settings("deployed", common, "train_frequency: 8")


def test_a_loaded_model_trains_on_the_nodes_schedule_and_keeps_its_network(tmp_path):
    saved = DQNAgent(DQNConfig(learning_starts=0, seed=2, train_frequency=5))
    saved.steps = 30
    model = str(tmp_path / "model.pt")
    save_checkpoint(saved, model)
    _, agent = make_policy(SessionConfig(model=model, dqn={"train_frequency": 8, "epsilon": 0.0,
                                                           "learning_rate": 0.5}))
    assert agent.config.train_frequency == 8 and agent.config.epsilon == 0.0
    assert agent.config.learning_rate == DQNConfig().learning_rate and agent.config.seed == 2   # the model's own
    assert agent.steps == 30
    _, agent = make_policy(SessionConfig(model=model))     # nothing set: the node's defaults, the robot's schedule
    assert agent.config.train_frequency == DQNConfig().train_frequency != 5
    assert agent.config.learning_starts == 0                # not a training-schedule field: the model's own
