"""The learner's session without ROS: which policy serves (and the checkpoint it resumes from), when the
model is saved, and the recent figures a node reports (loss, accuracy against the oracle, delivered
latency). The node reads its parameters into a SessionConfig, hands every outcome to `record`, and
publishes what `stats` returns; tests drive it with the router's outcomes and no master."""
import logging
import os
import threading
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Optional, Tuple

import numpy as np

from offload_learner_py.core.checkpoint import load_checkpoint, remove_orphaned_temps, save_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.evaluation import faster_actions
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal, DQNPolicy, InputSizeThreshold, Policy, \
    RandomPolicy
from offload_learner_py.online.router_types import DEPLOYED

POLICIES = ("dqn", "local", "cloud", "random", "threshold")
LOG = logging.getLogger("offload_learner_py.online.session")


@dataclass
class SessionConfig:
    policy: str = "dqn"
    checkpoint: str = ""              # written every checkpoint_every learned steps and at close; resumed from
    model: str = ""                   # the start when the checkpoint does not exist yet
    checkpoint_every: int = 50
    learn: bool = True
    explore: bool = False             # epsilon-greedy actions (probes explore instead)
    seed: int = 1
    dqn: dict = field(default_factory=dict)   # DQNConfig overrides
    threshold_input_size: float = 1.1
    stats_window: int = 50
    progress_every: int = 25

    def __post_init__(self):
        if self.policy not in POLICIES:
            raise ValueError(f"~policy must be one of {', '.join(POLICIES)}, got {self.policy!r}")
        if not isinstance(self.dqn, dict):
            raise ValueError(f"~dqn must be a dictionary of DQNConfig fields, got {self.dqn!r}")
        self.checkpoint, self.model = os.path.expanduser(self.checkpoint), os.path.expanduser(self.model)


# DQNConfig fields a loaded model takes from the node's settings: how training goes on. The rest (the network's
# shape, its input encoding, the optimizer and the replay memory it was built with, the seed) stay the model's.
TRAINING_SCHEDULE = ("gamma", "batch_size", "train_frequency", "gradient_steps", "target_update_interval", "epsilon",
                     "huber_delta", "max_grad_norm")


def dqn_settings(mode: str, dqn: dict, deployed_dqn: dict) -> dict:
    """The DQNConfig fields for a mode: ~dqn, and in deployed mode ~deployed_dqn over it (there the robot's CPU
    pays for every gradient step, so a robot may train less often; learner.yaml ships none)."""
    for name, value in (("~dqn", dqn), ("~deployed_dqn", deployed_dqn)):
        if value is not None and not isinstance(value, dict):
            raise ValueError(f"{name} must be a dictionary of DQNConfig fields, got {value!r}")
    return {**(dqn or {}), **((deployed_dqn or {}) if mode == DEPLOYED else {})}


def make_policy(config: SessionConfig, log: logging.Logger = LOG) -> Tuple[Policy, Optional[DQNAgent]]:
    """The policy and, for the DQN, its agent. A restarted node resumes from its own checkpoint; a new
    one starts from the model it was given, else untrained."""
    if config.policy == "local":
        return AlwaysLocal("local"), None
    if config.policy == "cloud":
        return AlwaysCloud("cloud"), None
    if config.policy == "random":
        return RandomPolicy(config.seed), None
    if config.policy == "threshold":
        return InputSizeThreshold(config.threshold_input_size, name="threshold"), None
    dqn = DQNConfig.from_dict({"seed": config.seed, **config.dqn})
    source = config.checkpoint if config.checkpoint and os.path.exists(config.checkpoint) else config.model
    if source:
        agent = load_checkpoint(source, dqn)
        log.info("loaded %s: %d steps, %d gradient steps", source, agent.steps, agent.gradient_steps)
        # The network comes from the checkpoint; how it goes on training is this node's to say (a robot deployed
        # from a learning run's model trains on the deployed schedule, not the learning run's).
        schedule = {name: value for name, value in config.dqn.items() if name in TRAINING_SCHEDULE}
        if schedule:
            agent.config = replace(agent.config, **schedule)
    else:
        agent = DQNAgent(dqn)
        log.warning("no checkpoint at %r and no ~model: the DQN starts untrained", config.checkpoint)
    return DQNPolicy(dqn, agent=agent, learn=config.learn, seed=config.seed + agent.steps,
                     explore=config.explore), agent


def correct_choice(action: int, local_s: float, cloud_s: float) -> bool:
    """Whether the action was the faster side (a tie is never a mistake)."""
    return bool(faster_actions(local_s, cloud_s, action) == action)


class LearnerSession:
    def __init__(self, config: SessionConfig, log: logging.Logger = LOG):
        self.config, self.log = config, log
        if config.checkpoint:
            for name in remove_orphaned_temps(config.checkpoint):
                log.warning("removed %s, left by a checkpoint save that was killed mid-write", name)
        self.policy, self.agent = make_policy(config, log)
        self.checkpoint_failures = 0
        self.count = 0                                    # outcomes of decisions recorded
        self._lock = threading.Lock()
        self._recent = deque(maxlen=config.stats_window)  # (loss or nan, correct or nan)
        self._delivered_ms = deque(maxlen=config.stats_window)
        self._learned_since_checkpoint = 0

    @property
    def learns(self) -> bool:
        return bool(self.config.learn and self.policy.learns)

    def record(self, outcome) -> Optional[str]:
        """Count one decision's outcome, save the model when due; the progress line when one is due."""
        correct = float("nan")
        if outcome.reward is not None and outcome.imputed is None:
            correct = float(correct_choice(outcome.decision.action, outcome.local_s, outcome.cloud_s))
        with self._lock:
            self._recent.append((outcome.loss if outcome.loss is not None else float("nan"), correct))
            self._delivered_ms.append(1000.0 * outcome.delivered_s)
            self.count += 1
            self._learned_since_checkpoint += bool(outcome.learned)
            due = self.config.checkpoint_every > 0 and self._learned_since_checkpoint >= self.config.checkpoint_every
        if due:
            self.save()
        if self.config.progress_every <= 0 or self.count % self.config.progress_every:
            return None
        stats = self.stats()
        with self._lock:
            delivered = float(np.mean(self._delivered_ms))
        return (f"request {self.count}: last {stats['recent_window']} mean {delivered:.1f} ms to path, accuracy "
                f"{100 * stats['recent_accuracy']:.0f}% vs oracle, model steps {self.policy.steps}")

    def stats(self) -> dict:
        """The policy's counters with the recent window's mean loss and accuracy, and checkpoint failures."""
        with self._lock:
            recent = np.array(self._recent, dtype=np.float64).reshape(-1, 2)

        def mean(column: int) -> float:
            finite = recent[:, column][np.isfinite(recent[:, column])]
            return float(finite.mean()) if len(finite) else float("nan")
        return {**self.policy.stats(), "recent_window": len(recent), "recent_loss": mean(0),
                "recent_accuracy": mean(1), "checkpoint_failures": self.checkpoint_failures}

    def save(self) -> bool:
        """Write the checkpoint; a failure (a full disk, a diverged network) is logged at error level every
        time, counted in stats(), and the next learned step tries again."""
        if not self.config.checkpoint or self.agent is None or not self.policy.learns:
            return False
        try:
            with self.policy.lock:
                save_checkpoint(self.agent, self.config.checkpoint)
        except (OSError, ValueError) as error:
            self.checkpoint_failures += 1
            self.log.error("checkpoint %s not written (%d failures so far): %s", self.config.checkpoint,
                           self.checkpoint_failures, error)
            return False
        with self._lock:
            self._learned_since_checkpoint = 0
        self.log.debug("checkpoint %s at %d steps", self.config.checkpoint, self.agent.steps)
        return True

    def close(self) -> bool:
        """Store the last pending transition and save; whether a checkpoint was written."""
        self.policy.flush()
        if self.save():
            self.log.info("checkpoint %s: %d steps", self.config.checkpoint, self.agent.steps)
            return True
        return False

