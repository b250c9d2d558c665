import ast
import inspect

import numpy as np
import pytest
import torch
from torch import nn

from offload_learner_py import CLOUD, LOCAL

from offload_learner_py.core import config as config_module
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent, QNetwork
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.state import STATE_SCHEMA, STATE_SIZE

D, U, B, P = (STATE_SCHEMA.index(name) for name in ("input_size", "cpu_availability", "round_trip_s",
                                                     "local_plan_rate"))


def _states(n, seed=0):
    """Raw states in schema order: d_t over four decades, u_t 50-70 %, b_t about 30 ms, p_t over one decade."""
    rng = np.random.default_rng(seed)
    columns = {"input_size": 10.0 ** rng.uniform(-4, -0.5, n), "cpu_availability": rng.uniform(0.5, 0.7, n),
               "round_trip_s": rng.uniform(0.028, 0.032, n), "local_plan_rate": 10.0 ** rng.uniform(6.5, 7.5, n)}
    return STATE_SCHEMA.stack(columns.__getitem__)


def _state(d, u, b, p=2e7):
    state = np.zeros(STATE_SIZE)
    state[[D, U, B, P]] = d, u, b, p
    return state


def test_network_is_the_papers_256_256_256_2_with_relu_on_the_schemas_inputs():
    layers = list(QNetwork().layers)
    linears = [m for m in layers if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(STATE_SIZE, 256), (256, 256), (256, 256),
                                                                  (256, 2)]
    assert [type(m) for m in layers] == [nn.Linear, nn.ReLU] * 3 + [nn.Linear]


def test_paper_defaults_and_validation():
    config = DQNConfig()
    assert config.hidden_sizes == (256, 256, 256) and config.replay_capacity == 1000 and config.epsilon == 0.1
    for bad in [dict(gamma=1.0), dict(gamma=-0.1), dict(epsilon=1.5), dict(batch_size=0),
                dict(batch_size=2000), dict(hidden_sizes=())]:
        with pytest.raises(ValueError):
            DQNConfig(**bad)
    assert DQNConfig.from_dict(DQNConfig(gamma=0.9).to_dict()) == DQNConfig(gamma=0.9)
    with pytest.raises(ValueError):
        DQNConfig.from_dict({"gama": 0.9})


def test_every_config_field_has_a_one_line_doc():
    tree = ast.parse(inspect.getsource(config_module))
    body = next(node for node in tree.body if isinstance(node, ast.ClassDef) and node.name == "DQNConfig").body
    fields = [node.target.id for node in body if isinstance(node, ast.AnnAssign)]
    documented = [body[i].target.id for i in range(len(body) - 1)
                  if isinstance(body[i], ast.AnnAssign) and isinstance(body[i + 1], ast.Expr)
                  and isinstance(body[i + 1].value, ast.Constant) and isinstance(body[i + 1].value.value, str)]
    assert fields and fields == documented


def _train(config, steps=150, seed=0):
    agent = DQNAgent(config)
    states = _states(steps + 1, seed)
    rng = np.random.default_rng(seed)
    losses = []
    for t in range(steps):
        action, _ = agent.act(states[t])
        r = float(rng.uniform(-1, 1)) if action == CLOUD else 0.0
        loss = agent.observe(states[t], action, r, states[t + 1])
        if loss is not None:
            losses.append(loss)
    return agent, losses


@pytest.mark.parametrize("gamma", [0.0, 0.9])
def test_same_seed_same_run_for_both_gamma_readings(gamma):
    config = DQNConfig(seed=7, gamma=gamma, learning_starts=20, batch_size=16)
    a, losses_a = _train(config)
    b, losses_b = _train(config)
    assert losses_a == losses_b and len(losses_a) > 0
    probe = _states(20, 5)
    assert np.array_equal(a.q_values(probe), b.q_values(probe))
    c, _ = _train(DQNConfig(seed=8, gamma=gamma, learning_starts=20, batch_size=16))
    assert not np.array_equal(a.q_values(probe), c.q_values(probe))


def test_seeding_leaves_torch_global_generator_alone():
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    DQNAgent(DQNConfig(seed=5))
    assert torch.equal(torch.rand(3), expected)


def test_target_network_is_copied_every_k_steps():
    config = DQNConfig(learning_starts=5, batch_size=4, target_update_interval=10, train_frequency=1, gamma=0.5)
    agent = DQNAgent(config)
    states = _states(30)

    def same():
        return all(torch.equal(p, q) for p, q in zip(agent.q_network.parameters(), agent.target_network.parameters()))

    for t in range(9):
        agent.observe(states[t], CLOUD, 1.0, states[t + 1])
    assert not same()  # trained since step 5, not yet copied
    agent.observe(states[9], CLOUD, 1.0, states[10])
    assert same()      # step 10: copied


def test_warm_up_is_uniform_then_epsilon_greedy_with_propensities():
    agent = DQNAgent(DQNConfig(learning_starts=50, epsilon=0.1))
    state = _states(1)[0]
    action, propensity = agent.act(state)
    assert propensity == 0.5
    agent.steps = 50
    greedy = agent.greedy_action(state)
    draws = [agent.act(state) for _ in range(2000)]
    for action, propensity in draws:
        assert propensity == pytest.approx(0.95 if action == greedy else 0.05)
    assert np.mean([a != greedy for a, _ in draws]) == pytest.approx(0.05, abs=0.02)


def test_normalisation_is_fitted_on_warm_up_states_then_frozen():
    agent = DQNAgent(DQNConfig(learning_starts=40, batch_size=8, normalisation_refit_interval=0))
    states = _states(100)
    for t in range(40):
        agent.observe(states[t], LOCAL, 0.0, states[t + 1])
    fitted = agent.normalisation
    assert fitted == StateNormalisation.fit(states[:40].astype(np.float32))  # replay keeps float32
    for t in range(40, 99):
        agent.observe(states[t], LOCAL, 0.0, states[t + 1])
    assert agent.normalisation is fitted


def _handover_states(n, warm_up, seed=0):
    """_states whose round trip is the edge's (about 30 ms) for the first `warm_up`, then swings over the WAN's."""
    states = _states(n, seed)
    states[warm_up:, B] = np.random.default_rng(seed + 1).uniform(0.02, 0.2, n - warm_up)
    return states


def test_normalisation_refits_over_replay_after_the_warm_up_without_changing_a_q_value():
    agent = DQNAgent(DQNConfig(learning_starts=40, batch_size=8, normalisation_refit_interval=150))
    states = _handover_states(201, 40)
    probe = _handover_states(64, 0, seed=5)
    for t in range(149):
        agent.observe(states[t], CLOUD, float(t % 3 - 1), states[t + 1])
    warm_up_scale = agent.normalisation.scale[B]
    assert warm_up_scale < 0.02                      # fitted on the edge's round trips alone
    before = agent.q_values(probe)
    target_before = agent.target_network(torch.from_numpy(agent.normalisation.apply(probe))).detach().numpy()
    agent.memory.add(states[149], CLOUD, 0.0, states[150])   # the 150th state, stored as observe() would
    agent.steps += 1
    assert agent.refit_due()
    agent.refit_normalisation()
    assert agent.normalisation == StateNormalisation.fit(agent.memory.states[:len(agent.memory)])
    assert agent.normalisation.scale[B] > 2 * warm_up_scale
    np.testing.assert_allclose(agent.q_values(probe), before, rtol=1e-4, atol=1e-5)
    target_after = agent.target_network(torch.from_numpy(agent.normalisation.apply(probe))).detach().numpy()
    np.testing.assert_allclose(target_after, target_before, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(agent.fast_decision().decide(*probe[0])[1:], before[0], rtol=1e-4, atol=1e-5)


def test_observe_refits_on_its_cadence_and_never_from_a_near_empty_memory():
    agent = DQNAgent(DQNConfig(learning_starts=40, batch_size=8, normalisation_refit_interval=50))
    states = _handover_states(120, 40)
    for t in range(99):
        agent.observe(states[t], LOCAL, 0.0, states[t + 1])
    at_50 = agent.normalisation
    assert at_50 == StateNormalisation.fit(states[:50].astype(np.float32))
    agent.observe(states[99], LOCAL, 0.0, states[100])
    assert agent.normalisation == StateNormalisation.fit(states[:100].astype(np.float32))
    # Resumed (a checkpoint holds no replay): no re-fit before the memory holds a warm-up's worth of states.
    resumed = DQNAgent(agent.config, agent.normalisation)
    resumed.steps = 199
    resumed.observe(states[0], LOCAL, 0.0, states[1])
    assert resumed.normalisation == agent.normalisation


def test_learns_the_sign_of_a_reward_that_depends_on_cpu_availability():
    agent = DQNAgent(DQNConfig(seed=3, learning_starts=100, train_frequency=1))
    states = _states(800, 1)
    for t in range(799):
        action, _ = agent.act(states[t])
        r = (0.5 if states[t, U] < 0.6 else -0.5) if action == CLOUD else 0.0
        agent.observe(states[t], action, r, states[t + 1])
    probe = _states(200, 9)
    chosen = np.array([agent.greedy_action(s) for s in probe])
    clear = np.abs(probe[:, U] - 0.6) > 0.02
    assert np.mean(chosen[clear] == (probe[clear, U] < 0.6)) > 0.95


def test_fast_path_matches_torch_eager():
    agent, _ = _train(DQNConfig(seed=2, learning_starts=20, batch_size=16))
    fast = agent.fast_decision()
    for state in _states(200, 4):
        action, q_local, q_cloud = fast.decide(*state)
        expected = agent.q_values(state)
        assert np.allclose([q_local, q_cloud], expected, atol=1e-5)
        if abs(expected[1] - expected[0]) > 1e-5:
            assert action == agent.greedy_action(state)


class _NextStateQ(nn.Module):
    """A target network whose Q'(s') is known by construction: (d', u') of the normalised next state."""

    def forward(self, x):
        return x[:, [D, U]]


def _agent_with_constant_q(gamma, q_local, q_cloud, huber_delta=100.0):
    """An agent whose online network answers (q_local, q_cloud) for every state (zero weights, known
    output bias) and whose inputs are the raw states (identity normalisation, no log)."""
    config = DQNConfig(gamma=gamma, batch_size=8, learning_starts=0, huber_delta=huber_delta, log_input_size=False)
    agent = DQNAgent(config, StateNormalisation.identity(log_input_size=False))
    with torch.no_grad():
        for parameter in agent.q_network.parameters():
            parameter.zero_()
        agent.q_network.layers[-1].bias.copy_(torch.tensor([q_local, q_cloud]))
    agent.target_network = _NextStateQ()
    return agent


@pytest.mark.parametrize("gamma,action,expected_target", [
    # r + gamma * max_a' Q'(s', a') with Q'(s') = (0.25, 0.75): the max, of the next state, added.
    (0.5, CLOUD, 0.125 + 0.5 * 0.75),
    (0.5, LOCAL, 0.125 + 0.5 * 0.75),
    (0.0, CLOUD, 0.125),  # contextual bandit: the reward alone, whatever the target network says
])
def test_td_target_is_reward_plus_gamma_max_next_q(gamma, action, expected_target):
    agent = _agent_with_constant_q(gamma, q_local=-1.0, q_cloud=0.5)
    state, next_state = _state(0.5, 0.0, 0.0, 0.0), _state(0.25, 0.75, 0.0, 0.0)
    for _ in range(8):
        agent.memory.add(state, action, 0.125, next_state)
    q = (-1.0, 0.5)[action]
    # Huber loss in its quadratic zone (|error| < delta): 0.5 * error^2 / delta, the same on every sample.
    expected_loss = 0.5 * (q - expected_target) ** 2 / agent.config.huber_delta
    assert agent.train_step() == pytest.approx(expected_loss, rel=1e-5)
    # One gradient step moves Q(s, a) towards the target and leaves the other action alone.
    after = agent.q_values(state)
    assert np.sign(after[action] - q) == np.sign(expected_target - q)
    assert after[1 - action] == pytest.approx((-1.0, 0.5)[1 - action], abs=1e-6)


def _learn_state_rule(seed, cloud_is_better, steps=800):
    """Online learning where offloading pays +0.5 exactly where cloud_is_better(states) and -0.5
    elsewhere; returns the greedy action on held-out states and the right one."""
    agent = DQNAgent(DQNConfig(seed=seed, learning_starts=100, train_frequency=1))
    states = _states(steps, seed)
    right = cloud_is_better(states)
    for t in range(steps - 1):
        action, _ = agent.act(states[t])
        r = (0.5 if right[t] else -0.5) if action == CLOUD else 0.0
        agent.observe(states[t], action, r, states[t + 1])
    probe = _states(300, seed + 1000)
    greedy = np.array([agent.greedy_action(s) for s in probe])
    return greedy, cloud_is_better(probe).astype(np.int64), probe


# The right action depends on one feature of the state at a time, and each side of the boundary holds
# about half of the states: a policy that ignores the state scores about 50 %.
STATE_RULES = {
    "input_size": (lambda s: s[:, D] > 10 ** -2.25, lambda s: np.abs(np.log10(s[:, D]) + 2.25) > 0.2),
    "cpu_availability": (lambda s: s[:, U] < 0.6, lambda s: np.abs(s[:, U] - 0.6) > 0.02),
    "round_trip_s": (lambda s: s[:, B] < 0.030, lambda s: np.abs(s[:, B] - 0.030) > 0.0004),
    # a robot that plans slowly offloads: the same request on a faster robot stays on board
    "local_plan_rate": (lambda s: s[:, P] < 10 ** 7, lambda s: np.abs(np.log10(s[:, P]) - 7) > 0.1),
}


@pytest.mark.parametrize("seed", [11, 23, 37])
@pytest.mark.parametrize("feature", sorted(STATE_RULES))
def test_greedy_action_follows_each_state_feature(feature, seed):
    cloud_is_better, clear_of_boundary = STATE_RULES[feature]
    greedy, right, probe = _learn_state_rule(seed, cloud_is_better)
    clear = clear_of_boundary(probe)
    assert 0.3 < right[clear].mean() < 0.7  # neither action is right everywhere
    assert np.mean(greedy[clear] == right[clear]) > 0.9


def test_train_frequency_sets_when_gradient_steps_run():
    agent = DQNAgent(DQNConfig(learning_starts=6, batch_size=4, train_frequency=3, gradient_steps=2))
    assert agent.gradient_steps == 0
    states = _states(31)
    trained_at = [t + 1 for t in range(30) if agent.observe(states[t], CLOUD, 0.5, states[t + 1]) is not None]
    assert trained_at == [6, 9, 12, 15, 18, 21, 24, 27, 30]  # from learning_starts on, every 3rd step
    assert agent.gradient_steps == 2 * len(trained_at) and agent.steps == 30


def test_a_tie_between_the_q_values_stays_local():
    agent = DQNAgent(DQNConfig(learning_starts=0))
    with torch.no_grad():
        agent.q_network.layers[-1].weight.zero_()
        agent.q_network.layers[-1].bias.fill_(0.25)
    state = _states(1)[0]
    assert agent.q_values(state)[LOCAL] == agent.q_values(state)[CLOUD]
    assert agent.greedy_action(state) == LOCAL
    assert agent.fast_decision().decide(*state)[0] == LOCAL


def test_exploration_stays_epsilon_long_after_warm_up():
    agent = DQNAgent(DQNConfig(learning_starts=50, epsilon=0.1))
    state = _states(1)[0]
    for steps in (49, 51, 500):
        agent.steps = steps
        expected = 0.5 if steps < 50 else None
        _, propensity = agent.act(state)
        if expected is not None:
            assert propensity == expected
        else:
            assert propensity in (pytest.approx(0.95), pytest.approx(0.05))


def test_fast_path_clamps_the_input_size_like_the_normalisation():
    # d = 0 (goal beside the start) sits on the log floor; a rounding error below 0 is clamped to 0 by
    # both paths rather than taking the log of a negative number in one of them.
    agent, _ = _train(DQNConfig(seed=2, learning_starts=20, batch_size=16))
    fast = agent.fast_decision()
    for d in (0.0, -1e-9, -0.5):
        _, q_local, q_cloud = fast.decide(*_state(d, 0.6, 0.03))
        assert np.allclose([q_local, q_cloud], agent.q_values(_state(d, 0.6, 0.03)), atol=1e-5)
        assert np.allclose([q_local, q_cloud], agent.q_values(_state(0.0, 0.6, 0.03)), atol=1e-5)


def test_propensities_when_the_greedy_action_is_cloud():
    agent = DQNAgent(DQNConfig(learning_starts=0, epsilon=0.1))
    with torch.no_grad():
        agent.q_network.layers[-1].weight.zero_()
        agent.q_network.layers[-1].bias.copy_(torch.tensor([0.0, 1.0]))  # Q(cloud) > Q(local) everywhere
    state = _states(1)[0]
    assert agent.greedy_action(state) == CLOUD
    draws = [agent.act(state) for _ in range(400)]
    assert {action for action, _ in draws} == {LOCAL, CLOUD}
    for action, propensity in draws:
        assert propensity == pytest.approx(0.95 if action == CLOUD else 0.05)


def test_without_warm_up_training_starts_at_the_first_step():
    agent = DQNAgent(DQNConfig(learning_starts=0, batch_size=1, train_frequency=1))
    states = _states(3)
    assert agent.observe(states[0], CLOUD, 0.5, states[1]) is not None
    assert agent.gradient_steps == 1
