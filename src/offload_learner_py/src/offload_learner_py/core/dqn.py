"""The DQN of Algorithm 1: a Q-network STATE_SIZE (4) -> 256 -> 256 -> 256 -> 2 (ReLU), a target copy refreshed
every K steps, FIFO replay, epsilon-greedy actions. Plus a compiled copy of the network for the robot's
per-request decision (FastDecision), which must cost well under 100 us."""
from typing import Optional, Tuple

import numpy as np
import torch
from torch import nn

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.replay import ReplayMemory
from offload_learner_py.core.state import STATE_SCHEMA, STATE_SIZE
from offload_planner_cpp._core import QNetworkForward   # the robot's compiled module: the decision's forward pass

N_ACTIONS = 2


def greedy_actions(q: np.ndarray) -> np.ndarray:
    """The greedy action of each row of N x 2 Q-values: the cloud only when strictly better, so a tie (an
    untrained network) plans on board."""
    q = np.asarray(q)
    return np.where(q[..., CLOUD] > q[..., LOCAL], CLOUD, LOCAL).astype(np.int64)


def greedy_action(q_local: float, q_cloud: float) -> int:
    """greedy_actions' rule for one state's two Q-values."""
    return CLOUD if q_cloud > q_local else LOCAL


def epsilon_greedy(rng: np.random.Generator, epsilon: float, greedy: int) -> Tuple[int, float]:
    """Algorithm 1's action: uniform with probability epsilon, else the greedy one; and the probability it
    had of being chosen (its propensity, which off-policy evaluation of the log needs)."""
    action = int(rng.integers(0, N_ACTIONS)) if rng.random() < epsilon else int(greedy)
    return action, epsilon / N_ACTIONS + (1.0 - epsilon if action == greedy else 0.0)


class QNetwork(nn.Module):
    def __init__(self, hidden_sizes=(256, 256, 256), state_size: int = STATE_SIZE, n_actions: int = N_ACTIONS):
        super().__init__()
        layers = []
        width = state_size
        for hidden in hidden_sizes:
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        layers.append(nn.Linear(width, n_actions))
        self.layers = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)


def build_network(config: DQNConfig) -> QNetwork:
    """Weights drawn from the config's seed without disturbing torch's global generator."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        return QNetwork(config.hidden_sizes)


class DQNAgent:
    """Online learner of Algorithm 1. Feed it raw states (the schema's fields in order, `State.as_array()`): it
    normalises them itself."""

    def __init__(self, config: DQNConfig = DQNConfig(), normalisation: Optional[StateNormalisation] = None):
        self.config = config
        self.q_network = build_network(config)
        self.target_network = build_network(config)
        self.target_network.load_state_dict(self.q_network.state_dict())
        self.optimizer = torch.optim.AdamW(self.q_network.parameters(), lr=config.learning_rate,
                                           weight_decay=config.weight_decay)
        self.memory = ReplayMemory(config.replay_capacity)
        self.rng = np.random.default_rng(config.seed)
        self.normalisation_frozen = normalisation is not None
        self.normalisation = normalisation or StateNormalisation.identity(config.log_input_size)
        self.steps = 0
        self.gradient_steps = 0

    # --- deciding -------------------------------------------------------------------------------
    def q_values(self, state) -> np.ndarray:
        """Q(s, local), Q(s, cloud) for one raw state, or N x 2 for N states."""
        x = torch.from_numpy(self.normalisation.apply(state))
        with torch.no_grad():
            return self.q_network(x).numpy()

    def greedy_action(self, state) -> int:
        return int(greedy_actions(self.q_values(state)))

    def greedy_actions(self, states) -> np.ndarray:
        """The greedy action of each of N raw states (none for none)."""
        if len(states) == 0:
            return np.zeros(0, dtype=np.int64)
        return greedy_actions(self.q_values(states))

    def in_warm_up(self) -> bool:
        return self.steps < self.config.learning_starts

    def act(self, state) -> Tuple[int, float]:
        """Epsilon-greedy action and the probability with which it was chosen (its propensity),
        which off-policy evaluation of the logged table needs. Uniform during warm-up, as
        Algorithm 1 line 10 explores."""
        epsilon = 1.0 if self.in_warm_up() else self.config.epsilon
        return epsilon_greedy(self.rng, epsilon, self.greedy_action(state))

    # --- learning -------------------------------------------------------------------------------
    def observe(self, state, action: int, reward: float, next_state) -> Optional[float]:
        """Store (s_t, a_t, r_t, s_t+1) and train on schedule. Returns the loss when a gradient step
        ran this call, else None."""
        self.memory.add(state, action, reward, next_state)
        self.steps += 1
        loss = None
        if self.steps >= max(self.config.learning_starts, 1) and self.steps % self.config.train_frequency == 0:
            if not self.normalisation_frozen:
                self.normalisation = self._fit_to_replay()
                self.normalisation_frozen = True
            elif self.refit_due():   # the warm-up's fit is followed where the states moved since
                self.refit_normalisation()
            for _ in range(self.config.gradient_steps):
                loss = self.train_step()
        if self.steps % self.config.target_update_interval == 0:
            self.target_network.load_state_dict(self.q_network.state_dict())
        return loss

    def remember(self, state, action: int, reward: float) -> None:
        """Store a transition in replay without counting a step or training (a round-trip variant of a measured
        request, core/round_trip.py): it shapes what later gradient steps sample, not their schedule. Its next
        state is its own, as for a run's last transition."""
        self.memory.add(state, action, reward, state)

    def refit_due(self) -> bool:
        """A re-fit of the normalisation is due every normalisation_refit_interval steps after the warm-up, once
        the replay memory holds at least a warm-up's worth of states (an agent resumed from a checkpoint starts
        with an empty memory: a few states would give a normalisation of those few)."""
        interval = self.config.normalisation_refit_interval
        return bool(interval) and self.steps > self.config.learning_starts and self.steps % interval == 0 \
            and len(self.memory) >= max(self.config.learning_starts, self.config.batch_size)

    def _fit_to_replay(self) -> StateNormalisation:
        return StateNormalisation.fit(self.memory.states[:len(self.memory)], self.config.log_input_size)

    def refit_normalisation(self) -> None:
        """Fit the normalisation to the states in replay and re-express both networks' first layers in it, so
        every Q-value stays what it was: the inputs x = (f - m) / s become x' = (f - m') / s', and
        W x + c = (W s' / s) x' + c + W (m' - m) / s. Only the conditioning of later gradient steps changes."""
        new = self._fit_to_replay()
        old = self.normalisation
        old_scale = np.asarray(old.scale, dtype=np.float64)
        shift = torch.from_numpy(((np.asarray(new.mean) - np.asarray(old.mean)) / old_scale).astype(np.float32))
        stretch = torch.from_numpy((np.asarray(new.scale) / old_scale).astype(np.float32))
        with torch.no_grad():
            for network in (self.q_network, self.target_network):
                first = network.layers[0]
                first.bias.add_(first.weight @ shift)
                first.weight.mul_(stretch)
        self.normalisation = new

    def train_step(self) -> float:
        states, actions, rewards, next_states = self.memory.sample(self.config.batch_size, self.rng)
        x = torch.from_numpy(self.normalisation.apply(states))
        a = torch.from_numpy(actions).unsqueeze(1)
        r = torch.from_numpy(rewards)
        with torch.no_grad():
            if self.config.gamma > 0:
                next_q = self.target_network(torch.from_numpy(self.normalisation.apply(next_states)))
                td_target = r + self.config.gamma * next_q.max(dim=1).values
            else:
                td_target = r  # contextual bandit: no bootstrap, so no target network needed
        q = self.q_network(x).gather(1, a).squeeze(1)
        loss = nn.functional.smooth_l1_loss(q, td_target, beta=self.config.huber_delta)
        self.optimizer.zero_grad()
        loss.backward()
        nn.utils.clip_grad_norm_(self.q_network.parameters(), self.config.max_grad_norm)
        self.optimizer.step()
        self.gradient_steps += 1
        return float(loss.item())

    def fast_decision(self) -> "FastDecision":
        return FastDecision.from_network(self.q_network, self.normalisation)


class FastDecision:
    """The greedy policy, compiled: the network's weights handed once to the C++ core's QNetworkForward
    (offload_planner_cpp/q_network.h), so that one decision is one call with no autograd, dispatcher or numpy
    call per layer. A snapshot: rebuild it after more training.

    On a robot a decision meets cold caches (the planner and the robot's other work ran since the last one). There
    numpy's forward pass, two calls a hidden layer, cost 148-168 us at the p50 (bench-decision's paced run: caches
    flushed before each decision, the other core busy); the compiled one costs ~60 us, about half of it the call
    into the module and half the network's 530 KB of weights read from memory. The scaling is the normalisation's
    (log(max(x, 0) + floor) on its log fields, then (x - mean) / scale), in double precision before the float32
    network, as in normalisation.py."""

    def __init__(self, weights, biases, normalisation: StateNormalisation):
        self.weights = [np.ascontiguousarray(w, dtype=np.float32) for w in weights]
        self.biases = [np.ascontiguousarray(b, dtype=np.float32) for b in biases]
        log_floor = [0.0] * STATE_SIZE
        if normalisation.log_input_size:
            for i, floor in STATE_SCHEMA.log_columns:
                log_floor[i] = float(floor)
        scale = np.asarray(normalisation.scale, dtype=np.float64)
        self._q_values = QNetworkForward(self.weights, self.biases,
                                         np.asarray(normalisation.mean, dtype=np.float64).tolist(),
                                         (1.0 / scale).tolist(), log_floor).q_values

    @classmethod
    def from_network(cls, network: QNetwork, normalisation: StateNormalisation) -> "FastDecision":
        linears = [m for m in network.layers if isinstance(m, nn.Linear)]
        return cls([m.weight.detach().numpy().T for m in linears], [m.bias.detach().numpy() for m in linears],
                   normalisation)

    def decide(self, *state: float) -> Tuple[int, float, float]:
        """(action, Q(s, local), Q(s, cloud)) for one raw state, its fields in schema order
        (`*State.as_tuple()`); TypeError for a state of the wrong width."""
        q_local, q_cloud = self._q_values(*state)
        return greedy_action(q_local, q_cloud), q_local, q_cloud
