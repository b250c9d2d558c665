"""The learner session without ROS: policy choice and resume order, checkpoint cadence and failures, the
recent figures the node publishes."""
import logging
import os

import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.checkpoint import save_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.policies import Decision
from offload_learner_py.core.state import State
from offload_learner_py.online.router_types import Outcome
from offload_learner_py.online.session import LearnerSession, SessionConfig, correct_choice, make_policy


def outcome(action=CLOUD, local_s=0.2, cloud_s=0.1, learned=True, loss=0.5, imputed=None):
    return Outcome(request_id=1, state=State(1.0, 0.5, 0.05), decision=Decision(action, 1.0), probe=True,
                   delivered=action, delivered_s=min(local_s, cloud_s), local_s=local_s, cloud_s=cloud_s,
                   reward=-0.1, loss=loss, learned=learned, imputed=imputed)


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
    assert policy.decide(State(1.0, 0.5, 0.05)).action == action


def test_an_unknown_policy_or_a_bad_dqn_block_is_refused():
    with pytest.raises(ValueError, match="~policy"):
        SessionConfig(policy="fastest")
    with pytest.raises(ValueError, match="~dqn"):
        SessionConfig(dqn=[1, 2])


def test_the_checkpoint_is_saved_every_n_learned_outcomes(tmp_path):
    path = tmp_path / "checkpoint.pt"
    session = LearnerSession(SessionConfig(checkpoint=str(path), checkpoint_every=3, progress_every=0))
    for k in range(2):
        session.record(outcome())
        session.record(outcome(learned=False))
    assert not path.exists()
    session.record(outcome())
    assert path.exists()
    before = os.stat(path).st_mtime_ns
    for k in range(2):
        session.record(outcome())
    assert os.stat(path).st_mtime_ns == before       # 2 of the next 3 learned outcomes


def test_a_failed_save_is_logged_as_an_error_and_counted_each_time(tmp_path, caplog):
    blocked = tmp_path / "not_a_dir"
    blocked.write_text("")
    session = LearnerSession(SessionConfig(checkpoint=str(blocked / "checkpoint.pt"), checkpoint_every=1,
                                           progress_every=0))
    with caplog.at_level(logging.ERROR):
        session.record(outcome())
        session.record(outcome())
    assert session.stats()["checkpoint_failures"] == 2
    assert sum("not written" in record.message for record in caplog.records) == 2


def test_recent_accuracy_counts_the_faster_side_and_ties_and_skips_imputed_rewards():
    session = LearnerSession(SessionConfig(progress_every=0))
    session.record(outcome(action=CLOUD, local_s=0.2, cloud_s=0.1))       # right
    session.record(outcome(action=LOCAL, local_s=0.2, cloud_s=0.1))       # wrong
    session.record(outcome(action=LOCAL, local_s=0.1, cloud_s=0.1))       # a tie: right
    session.record(outcome(action=LOCAL, local_s=0.2, cloud_s=0.1, imputed=CLOUD))   # not scored
    stats = session.stats()
    assert stats["recent_window"] == 4 and stats["recent_accuracy"] == pytest.approx(2 / 3)
    assert stats["recent_loss"] == pytest.approx(0.5)
    assert correct_choice(CLOUD, 0.3, 0.1) and not correct_choice(CLOUD, 0.1, 0.3)


def test_the_progress_line_comes_every_n_outcomes():
    session = LearnerSession(SessionConfig(progress_every=2, stats_window=10))
    lines = [session.record(outcome(local_s=0.3, cloud_s=0.1)) for _ in range(4)]
    assert lines[0] is None and lines[2] is None
    assert lines[1].startswith("request 2: last 2 mean 100.0 ms to path, accuracy 100% vs oracle")
    assert lines[3].startswith("request 4: last 4")


def test_close_stores_the_last_transition_and_saves(tmp_path):
    path = tmp_path / "checkpoint.pt"
    session = LearnerSession(SessionConfig(checkpoint=str(path), checkpoint_every=0, progress_every=0))
    session.policy.learn(State(1.0, 0.5, 0.05), CLOUD, -0.2)
    assert session.agent.steps == 0                   # pending until its successor (or close) arrives
    assert session.close() and path.exists() and session.agent.steps == 1


def test_deployed_mode_takes_the_deployed_dqn_settings_over_the_common_ones():
    from offload_learner_py.online.session import dqn_settings
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
    _, agent = make_policy(SessionConfig(model=model))     # nothing set: the model's own schedule
    assert agent.config.train_frequency == 5
