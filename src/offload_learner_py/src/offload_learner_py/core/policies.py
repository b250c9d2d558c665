"""One policy interface for the DQN and its baselines, offline and online.

Offline: fit on a training table, then choose an action for every row of another (`choose`). Online (the
router): decide one request from its state (`decide`, with the action's propensity and Q-values), and
learn from its eq. 10 reward (`learn`); baselines never learn. Only the oracle reads latencies, which is
why it is offline only."""
import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent, epsilon_greedy
from offload_learner_py.core.evaluation import oracle_actions
from offload_learner_py.core.reward import CostWeights
from offload_learner_py.core.state import State
from offload_learner_py.data.dataset import TransitionTable


@dataclass(frozen=True)
class Decision:
    """One online decision: the action, the probability the policy had of taking it, its Q-values, and the
    version of the model file that decided ("" for a model that is not from a file: a robot learning itself,
    a fixed policy)."""
    action: int
    propensity: float
    q_local: float = float("nan")
    q_cloud: float = float("nan")
    model_version: str = ""


class Policy(ABC):
    name = "policy"
    learns = False

    def fit(self, train: TransitionTable) -> "Policy":
        """Learn from a table with both latencies per row. Fixed policies ignore it."""
        return self

    @abstractmethod
    def choose(self, table: TransitionTable) -> np.ndarray:
        """Action (0 local, 1 cloud) per row, from the states only (except the oracle)."""

    def decide(self, state: State) -> Decision:
        """The action for one request (online), with the probability the policy had of taking it."""
        raise NotImplementedError(f"the {self.name} policy is offline only")

    def learn(self, state: State, action: int, reward_value: float) -> Optional[float]:
        """One online transition; the training loss when a gradient step ran. Baselines never learn."""
        return None

    def remember(self, state: State, action: int, reward_value: float) -> None:
        """A transition for replay only (a round-trip variant); baselines keep none."""

    def flush(self) -> Optional[float]:
        return None

    def observe(self, state: State, local_s: Optional[float], cloud_s: Optional[float]) -> None:
        """The measured latencies of a routed request (None for a side not run or not plannable). Only a rule
        that predicts latencies reads them."""

    @property
    def warming_up(self) -> bool:
        """Still collecting its first transitions: a deployed router probes every request meanwhile."""
        return False

    @property
    def steps(self) -> int:
        return 0

    def stats(self) -> dict:
        return {"steps": self.steps, "gradient_steps": 0, "replay_size": 0, "epsilon": 0.0}


class FixedPolicy(Policy):
    """The same action for every request."""
    action = LOCAL

    def __init__(self, name: Optional[str] = None):
        self.name = name or self.name

    def choose(self, table):
        return np.full(len(table), self.action, dtype=np.int64)

    def decide(self, state):
        return Decision(self.action, 1.0)


class AlwaysLocal(FixedPolicy):
    name, action = "always_local", LOCAL


class AlwaysCloud(FixedPolicy):
    name, action = "always_cloud", CLOUD


class RandomPolicy(Policy):
    """Uniform actions. `choose` draws the same actions for the same table each time (seeded); `decide`
    goes on drawing from one stream."""
    name = "random"

    def __init__(self, seed: int = 1):
        self.seed = seed
        self.rng = np.random.default_rng(seed)

    def choose(self, table):
        return np.random.default_rng(self.seed).integers(0, 2, len(table)).astype(np.int64)

    def decide(self, state):
        return Decision(int(self.rng.integers(0, 2)), 0.5)


class OraclePolicy(Policy):
    """The faster action of each row, known only after both were measured."""
    name = "oracle"

    def choose(self, table):
        return oracle_actions(table).astype(np.int64)


class InputSizeThreshold(Policy):
    """Offload when d_t is above (or below) a threshold: the rule the paper's real-data policy ended up
    resembling (offload above d of about 1.1). Given a threshold, it is fixed (the node's `threshold`
    policy); without one, `fit` picks the threshold and its side to maximise training accuracy."""
    name = "threshold_d"

    def __init__(self, threshold: Optional[float] = None, cloud_above: bool = True, name: Optional[str] = None):
        if threshold is not None and not (threshold >= 0 and math.isfinite(threshold)):
            raise ValueError(f"input-size threshold must be finite and >= 0, got {threshold}")
        self.threshold = threshold
        self.cloud_above = cloud_above
        self.fixed = threshold is not None
        self.name = name or self.name

    def fit(self, train):
        if self.fixed:
            return self
        d = train.input_size
        # +1 for rows where cloud is strictly faster, -1 where local is, 0 on ties.
        gain = np.sign(train.local_s - train.cloud_s)
        order = np.argsort(d, kind="stable")
        d_sorted, gain_sorted = d[order], gain[order]
        # Score of "cloud above threshold" for a cut after position k: cloud gain summed above it.
        gain_above = np.concatenate([[gain_sorted.sum()], gain_sorted.sum() - np.cumsum(gain_sorted)])
        cuts = np.concatenate([[-np.inf], (d_sorted[:-1] + d_sorted[1:]) / 2.0, [np.inf]])
        # Only cut between distinct d values, otherwise equal states would get different actions.
        valid = np.concatenate([[True], d_sorted[:-1] < d_sorted[1:], [True]])
        above, below = np.where(valid, gain_above, -np.inf), np.where(valid, -gain_above + gain_sorted.sum(), -np.inf)
        if above.max() >= below.max():
            self.cloud_above, self.threshold = True, float(cuts[int(np.argmax(above))])
        else:
            self.cloud_above, self.threshold = False, float(cuts[int(np.argmax(below))])
        return self

    def _actions(self, input_size) -> np.ndarray:
        if self.threshold is None:
            raise RuntimeError("fit the threshold policy on training data first")
        return np.where((np.asarray(input_size) > self.threshold) == self.cloud_above, CLOUD, LOCAL).astype(np.int64)

    def choose(self, table):
        return self._actions(table.input_size)

    def decide(self, state):
        return Decision(int(self._actions(state.input_size)), 1.0)


class LatencyBound(Policy):
    """Offload when the predicted cloud latency is below the predicted local one, as FogROS2-LS routes each request
    to the side with the lowest latency bound. Cloud: the link's last round trip b_t plus the cloud's planning time;
    local: the robot's planning time, which its CPU budget stretches by 1 / u_t. Each side's planning time is
    modelled as a rate per unit of d_t (the planning work the state measures), an average over that side's recent
    measured plans (`observe`, the cloud's less its round trip), so it is the current map's: d_t is normalised by
    the map's cell count, and after a map change the recent plans are the new map's within a few requests. Until a
    side has `min_samples` plans it is tried (the one with fewer first): a bound needs a measurement."""
    name = "latency_bound"

    def __init__(self, recency: float = 0.2, min_samples: int = 3, d_floor: float = 0.05,
                 u_floor: float = 0.05, name: Optional[str] = None):
        if not (0.0 < recency <= 1.0 and min_samples >= 1 and d_floor > 0 and 0.0 < u_floor <= 1.0):
            raise ValueError("latency_bound needs recency in (0, 1], min_samples >= 1, d_floor > 0 and u_floor in "
                             f"(0, 1], got {recency}, {min_samples}, {d_floor}, {u_floor}")
        self.recency, self.min_samples, self.d_floor, self.u_floor = recency, min_samples, d_floor, u_floor
        self.name = name or self.name
        self.seconds_per_d = {LOCAL: None, CLOUD: None}   # planning s per unit d_t (local: at full CPU)
        self.samples = {LOCAL: 0, CLOUD: 0}
        self._lock = threading.Lock()

    def _work(self, input_size: float) -> float:
        return max(input_size, self.d_floor)

    def _speed(self, cpu_availability: float) -> float:
        return min(max(cpu_availability, self.u_floor), 1.0)

    def predicted_s(self, state: State) -> Tuple[Optional[float], Optional[float]]:
        """(local, cloud) predicted latency of a request; None for a side not measured yet."""
        local, cloud = self.seconds_per_d[LOCAL], self.seconds_per_d[CLOUD]
        work = self._work(state.input_size)
        return (None if local is None else local * work / self._speed(state.cpu_availability),
                None if cloud is None else state.round_trip_s + cloud * work)

    def observe(self, state, local_s, cloud_s):
        work = self._work(state.input_size)
        with self._lock:
            for side, rate in ((LOCAL, None if local_s is None else local_s * self._speed(state.cpu_availability)),
                               (CLOUD, None if cloud_s is None else max(cloud_s - state.round_trip_s, 0.0))):
                if rate is None or not math.isfinite(rate):
                    continue
                previous = self.seconds_per_d[side]
                value = rate / work
                self.seconds_per_d[side] = value if previous is None else previous + self.recency * (value - previous)
                self.samples[side] += 1

    def _action(self, state) -> int:
        with self._lock:
            if min(self.samples.values()) < self.min_samples:
                return LOCAL if self.samples[LOCAL] <= self.samples[CLOUD] else CLOUD
            local_s, cloud_s = self.predicted_s(state)
        return CLOUD if cloud_s < local_s else LOCAL

    def choose(self, table):
        """Offline: each row decided with the estimates of the rows before it, then its latencies observed."""
        actions = np.empty(len(table), dtype=np.int64)
        for k, (state, local_s, cloud_s) in enumerate(zip(table.states, table.local_s, table.cloud_s)):
            row = State(*state)
            actions[k] = self._action(row)
            self.observe(row, float(local_s), float(cloud_s))
        return actions

    def decide(self, state):
        return Decision(self._action(state), 1.0)


class DQNPolicy(Policy):
    """Algorithm 1. Offline, `fit` runs it over the training rows in order (epsilon-greedy, replay, target
    copies) with rewards from the rows' measured latencies, and `choose` is the greedy policy.

    Online, decisions read a compiled snapshot of the Q-network (FastDecision), rebuilt after each gradient
    step, so deciding never waits for training or takes the torch path. With learn false the greedy
    policy of the given agent is used and nothing is trained. With explore false (learning mode, where
    both sides run anyway, and deployed mode, where probes explore) the action is always the greedy one:
    epsilon-greedy would only cost the robot time."""
    name = "dqn"

    def __init__(self, config: DQNConfig = DQNConfig(), weights: CostWeights = CostWeights(),
                 agent: Optional[DQNAgent] = None, learn: bool = True, seed: Optional[int] = None,
                 explore: bool = True):
        self.config = config
        self.weights = weights
        self.agent = agent
        self.online_run = None
        self.learns = learn
        self.explore = explore
        self.lock = threading.Lock()     # held while training or saving the agent
        self._seed = seed
        self._pending: Optional[Tuple[np.ndarray, int, float]] = None
        self._rng = self._snapshot = None
        if agent is not None:
            self._online(agent)

    def _online(self, agent: DQNAgent) -> None:
        self.agent = agent
        self._rng = np.random.default_rng(agent.config.seed if self._seed is None else self._seed)
        self._snapshot = agent.fast_decision()

    def fit(self, train):
        from offload_learner_py.offline.simulation import run_online

        agent = DQNAgent(self.config)
        self.online_run = run_online(agent, train, self.weights)
        self._online(agent)
        return self

    def choose(self, table):
        if self.agent is None:
            raise RuntimeError("fit the DQN policy (or pass a trained agent) first")
        return self.agent.greedy_actions(table.states)

    # -- online ----------------------------------------------------------------------------------------
    def epsilon(self) -> float:
        if not (self.learns and self.explore):
            return 0.0
        return 1.0 if self.agent.in_warm_up() else self.agent.config.epsilon

    @property
    def warming_up(self) -> bool:
        return self.learns and self.agent.in_warm_up()

    def decide(self, state):
        if self.agent is None:
            raise RuntimeError("fit the DQN policy (or pass a trained agent) first")
        greedy, q_local, q_cloud = self._snapshot.decide(*state.as_tuple())
        action, propensity = epsilon_greedy(self._rng, self.epsilon(), greedy)
        return Decision(action, propensity, q_local, q_cloud)

    def learn(self, state, action, reward_value):
        """Store the transition and train on schedule. The next state of a transition is the state of
        the next learned request (it does not depend on the action), so each transition is stored
        when its successor arrives; flush() stores the last one with its own state."""
        if not self.learns:
            return None
        with self.lock:
            current = state.as_array()
            loss = None
            if self._pending is not None:
                loss = self._observe(*self._pending, current)
            self._pending = (current, action, reward_value)
            return loss

    def remember(self, state, action, reward_value) -> None:
        """A transition for replay only (DQNAgent.remember): no step, no training."""
        if self.learns:
            with self.lock:
                self.agent.remember(state.as_array(), action, reward_value)

    def flush(self) -> Optional[float]:
        with self.lock:
            if self._pending is None:
                return None
            state, action, reward_value = self._pending
            self._pending = None
            return self._observe(state, action, reward_value, state)

    def _observe(self, state, action, reward_value, next_state):
        steps_before = self.agent.gradient_steps
        loss = self.agent.observe(state, action, reward_value, next_state)
        if self.agent.gradient_steps != steps_before or self.agent.steps == 1:
            self._snapshot = self.agent.fast_decision()
        return loss

    @property
    def steps(self):
        return self.agent.steps if self.agent is not None else 0

    def stats(self):
        return {"steps": self.agent.steps, "gradient_steps": self.agent.gradient_steps,
                "replay_size": len(self.agent.memory), "epsilon": self.epsilon()}
