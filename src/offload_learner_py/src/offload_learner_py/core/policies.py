"""One policy interface for the DQN and its baselines: fit on a training table, then choose an action
for every row of another. Only the oracle reads latencies, which is why it is offline only."""
from abc import ABC, abstractmethod
from typing import Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.evaluation import oracle_actions
from offload_learner_py.core.reward import CostWeights


class Policy(ABC):
    name = "policy"

    def fit(self, train: TransitionTable) -> "Policy":
        """Learn from a table with both latencies per row. Fixed policies ignore it."""
        return self

    @abstractmethod
    def choose(self, table: TransitionTable) -> np.ndarray:
        """Action (0 local, 1 cloud) per row, from the states only (except the oracle)."""


class AlwaysLocal(Policy):
    name = "always_local"

    def choose(self, table):
        return np.full(len(table), LOCAL, dtype=np.int64)


class AlwaysCloud(Policy):
    name = "always_cloud"

    def choose(self, table):
        return np.full(len(table), CLOUD, dtype=np.int64)


class RandomPolicy(Policy):
    name = "random"

    def __init__(self, seed: int = 1):
        self.seed = seed

    def choose(self, table):
        return np.random.default_rng(self.seed).integers(0, 2, len(table)).astype(np.int64)


class OraclePolicy(Policy):
    """The faster action of each row, known only after both were measured."""
    name = "oracle"

    def choose(self, table):
        return oracle_actions(table).astype(np.int64)


class InputSizeThreshold(Policy):
    """Offload when d_t is above (or below) a threshold, both picked to maximise training accuracy:
    the rule the paper's real-data policy ended up resembling (offload above d of about 1.1)."""
    name = "threshold_d"

    def __init__(self):
        self.threshold: Optional[float] = None
        self.cloud_above = True

    def fit(self, train):
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

    def choose(self, table):
        if self.threshold is None:
            raise RuntimeError("fit the threshold policy on training data first")
        above = table.input_size > self.threshold
        return np.where(above == self.cloud_above, CLOUD, LOCAL).astype(np.int64)


class DQNPolicy(Policy):
    """fit runs Algorithm 1 online over the training rows in order (epsilon-greedy, replay, target
    copies), with rewards from the rows' measured latencies; choose is the greedy policy."""
    name = "dqn"

    def __init__(self, config: DQNConfig = DQNConfig(), weights: CostWeights = CostWeights(),
                 agent: Optional[DQNAgent] = None):
        self.config = config
        self.weights = weights
        self.agent = agent
        self.online_run = None

    def fit(self, train):
        from offload_learner_py.offline.simulation import run_online

        self.agent = DQNAgent(self.config)
        self.online_run = run_online(self.agent, train, self.weights)
        return self

    def choose(self, table):
        if self.agent is None:
            raise RuntimeError("fit the DQN policy (or pass a trained agent) first")
        q = self.agent.q_values(table.states)
        return np.where(q[:, CLOUD] > q[:, LOCAL], CLOUD, LOCAL).astype(np.int64)
