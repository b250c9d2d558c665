"""Offline retraining from bags: accuracy on the held-out split, determinism, a checkpoint the learner
loads, the command line."""
import json
import os

import numpy as np
import pytest
import torch

from bagtools import make_requests, write
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.data import bags
from offload_learner_py.offline import retrain
from offload_learner_py.core.checkpoint import load_checkpoint
from offload_learner_py.core.config import DQNConfig


@pytest.fixture(scope="module")
def run_bag(tmp_path_factory):
    # 500 requests, one in two a probe step: 250 table rows, 250 one-latency steps
    return write(tmp_path_factory.mktemp("bags") / "run.bag", make_requests(500, seed=7, probe_every=2))


def _weights(path):
    agent = load_checkpoint(path)
    return [p.detach().clone() for p in agent.q_network.parameters()]


def test_retraining_learns_the_split_and_reports_the_online_policy_beside_it(run_bag, tmp_path):
    data = bags.read_bags([run_bag])
    evaluation = retrain.retrain(data, str(tmp_path / "out"), DQNConfig(seed=3), gradient_steps=600)
    assert (evaluation["train_rows"], evaluation["test_rows"]) == (200, 50)
    # the logged actions were uniformly random; the retrained greedy policy is far better
    assert evaluation["retrained"]["accuracy"] >= 0.88
    assert evaluation["online_taken"]["accuracy"] < 0.75
    for name in ("always_local", "always_cloud", "retrained"):
        assert name in evaluation["off_policy"]
    written = json.load(open(tmp_path / "out" / "evaluation.json"))
    assert written["retrained"]["accuracy"] == evaluation["retrained"]["accuracy"]
    assert "retrained DQN (greedy)" in open(tmp_path / "out" / "evaluation.md").read()
    assert len(bags.TransitionTable.load_npz(str(tmp_path / "out" / "transitions.npz"))) == 250


def test_the_checkpoint_is_what_the_learner_node_loads(run_bag, tmp_path):
    data = bags.read_bags([run_bag])
    retrain.retrain(data, str(tmp_path), DQNConfig(seed=1), gradient_steps=200)
    agent = load_checkpoint(str(tmp_path / "checkpoint.pt"), DQNConfig())   # the node's check
    assert agent.steps >= agent.config.learning_starts and not agent.in_warm_up()
    assert agent.normalisation_frozen and len(agent.memory) == 0
    states = data.transition_table().states
    fast = agent.fast_decision()
    greedy = agent.greedy_actions(states)
    assert [fast.decide(*s)[0] for s in states[:50]] == list(greedy[:50])
    # it keeps learning online after loading: the optimizer state loads and steps
    for s in states[:70]:
        agent.observe(s, 1, 0.1, s)
    assert agent.gradient_steps > 0


def test_the_node_loads_it_through_model(run_bag, tmp_path):
    from offload_learner_py.online.session import SessionConfig, make_policy
    data = bags.read_bags([run_bag])
    retrain.retrain(data, str(tmp_path), DQNConfig(seed=1), gradient_steps=100)
    policy, agent = make_policy(SessionConfig(model=str(tmp_path / "checkpoint.pt"), learn=False))
    assert agent.steps >= 200 and policy.epsilon() == 0.0
    # and decides with it: the greedy action of the retrained network, propensity 1 (frozen, ~learn false)
    from offload_learner_py.core.state import State

    table = data.transition_table()
    greedy = agent.greedy_actions(table.states[:20])
    for state, expected in zip(table.states[:20], greedy):
        decision = policy.decide(State(*state))
        assert (decision.action, decision.propensity) == (expected, 1.0)


def test_same_seed_same_checkpoint_other_seed_other_weights(run_bag, tmp_path):
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        assert retrain.main([run_bag, "--out", str(tmp_path / name), "--seed", str(seed), "--steps", "150",
                             "--quiet", "--workers", "1"]) == 0
    a, b, c = (_weights(str(tmp_path / name / "checkpoint.pt")) for name in "abc")
    assert all(torch.equal(x, y) for x, y in zip(a, b))
    assert not all(torch.equal(x, y) for x, y in zip(a, c))
    ea, eb = (json.load(open(tmp_path / name / "evaluation.json")) for name in "ab")
    assert ea["retrained"] == eb["retrained"] and ea["final_loss"] == eb["final_loss"]


def test_taken_only_learns_from_the_logged_action_alone(run_bag, tmp_path):
    table = bags.read_bags([run_bag]).transition_table()
    result = retrain.train_offline(table, DQNConfig(seed=1), gradient_steps=50, taken_only=True)
    assert len(result.losses) == 50 and np.all(np.isfinite(result.losses))
    full = retrain.train_offline(table, DQNConfig(seed=1), gradient_steps=50)
    assert not np.array_equal(result.losses, full.losses)


def test_baselines_flag_scores_every_baseline(run_bag, tmp_path):
    data = bags.read_bags([run_bag])
    evaluation = retrain.retrain(data, str(tmp_path), DQNConfig(seed=1), gradient_steps=50, baselines=True)
    assert {"always_local", "always_cloud", "oracle", "lstm"} <= set(evaluation["baselines"])
    assert evaluation["baselines"]["oracle"]["accuracy"] == 1.0


def test_command_line_errors_are_one_line_and_status_2(tmp_path, capsys):
    empty = tmp_path / "nothing.bag"
    empty.write_bytes(b"#ROSBAG V2.0\n")
    assert retrain.main([str(empty), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "error: only 0 requests" in capsys.readouterr().err
    assert retrain.main([str(empty), "--out", str(tmp_path / "o"), "--set", "epsilon=7"]) == 2
    assert "epsilon" in capsys.readouterr().err
    assert retrain.main([str(empty), "--out", str(tmp_path / "o"), "--test-fraction", "1.5"]) == 2
    assert not os.path.exists(tmp_path / "o" / "checkpoint.pt")


def test_chronological_split_keeps_both_sides_non_empty():
    assert retrain.chronological_split(10, 0.2) == 8
    assert retrain.chronological_split(2, 0.01) == 1
    assert retrain.chronological_split(2, 0.99) == 1
    with pytest.raises(ValueError):
        retrain.chronological_split(10, 0.0)
    assert LOCAL != CLOUD


def test_a_reward_logged_with_another_alpha_is_caught(run_bag):
    from offload_learner_py.core.reward import CostWeights

    table = bags.read_bags([run_bag]).transition_table()
    assert retrain.logged_reward_mismatch(table, CostWeights()) < 1e-12
    assert retrain.logged_reward_mismatch(table, CostWeights(0.7, 0.3)) > 0.01


def _bag_with_configs(path, alphas):
    """A bag of requests and, per session, the learner's latched config with that alpha."""
    from offload_demos.bag_writer import CONFIG_TOPIC, CONFIG_TYPE, config_definition, installed_definitions, \
        typestore_for

    store = typestore_for(*installed_definitions(), extra={CONFIG_TYPE: config_definition()})
    sessions = iter(alphas)

    def extra(bag, index, time_ns):
        if index % 20 == 0:
            alpha = next(sessions, None)
            if alpha is not None:
                bag.write(CONFIG_TOPIC, CONFIG_TYPE, {"mode": "learning", "alpha": alpha, "beta": 1 - alpha,
                                                      "cloud_timeout_s": 5.0}, time_ns)
    return write(path, make_requests(40, probe_every=1), store=store, extra=extra)


def test_retraining_takes_alpha_from_the_learner_config_in_the_bag(tmp_path):
    data = bags.read_bags([_bag_with_configs(tmp_path / "a.bag", [0.7])])
    assert data.report.recorded("mode") == ["learning"]
    assert retrain.recorded_weights(data).alpha == pytest.approx(0.7)
    assert retrain.recorded_weights(bags.read_bags([write(tmp_path / "old.bag", make_requests(10))])).alpha == 0.5
    mixed = bags.read_bags([_bag_with_configs(tmp_path / "b.bag", [0.7, 0.3])])
    with pytest.raises(ValueError, match="different alphas"):
        retrain.recorded_weights(mixed)
