"""The learner's session settings without ROS: which policy serves and the checkpoint it resumes from (its own,
else ~model), the DQN settings of the mode, and the checkpoint cadence and statistics window the online learner
(learning.py) keeps. The node reads its parameters into a SessionConfig; `make_policy` builds the policy."""
import logging
import os
from dataclasses import dataclass, field, replace
from typing import Optional, Tuple

from offload_learner_py.core.checkpoint import load_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal, DQNPolicy, InputSizeThreshold, LatencyBound, \
    Policy, RandomPolicy
from offload_learner_py.core.replay_policy import ReplayPolicy
from offload_learner_py.online.router_types import DEPLOYED

POLICIES = ("dqn", "local", "cloud", "random", "threshold", "latency_bound", "replay")
LOG = logging.getLogger("offload_learner_py.online.session")


@dataclass
class SessionConfig:
    policy: str = "dqn"
    checkpoint: str = ""              # written every checkpoint_every learned steps and at close; resumed from
    model: str = ""                   # the start when the checkpoint does not exist yet
    checkpoint_every: int = 50
    learn: bool = True
    explore: bool = False             # epsilon-greedy actions; off: learning mode runs both sides anyway and
                                      # deployed mode explores with its probes, so it would only cost time
    seed: int = 1
    dqn: dict = field(default_factory=dict)   # DQNConfig overrides
    threshold_input_size: float = 1.1
    replay_actions: str = ""          # the replay policy's file: one action per request, in arrival order
    stats_window: int = 50
    progress_every: int = 25

    def __post_init__(self):
        if self.policy not in POLICIES:
            raise ValueError(f"~policy must be one of {', '.join(POLICIES)}, got {self.policy!r}")
        if not isinstance(self.dqn, dict):
            raise ValueError(f"~dqn must be a dictionary of DQNConfig fields, got {self.dqn!r}")
        if self.policy == "replay" and not self.replay_actions:
            raise ValueError("~policy replay needs ~replay_actions, a file of one action (0 local, 1 cloud) per line")
        self.checkpoint, self.model = os.path.expanduser(self.checkpoint), os.path.expanduser(self.model)


# DQNConfig fields a loaded model takes from the node's settings: how training goes on. The rest (the network's
# shape, its input encoding, the optimizer and the replay memory it was built with, the seed) stay the model's.
TRAINING_SCHEDULE = ("gamma", "batch_size", "train_frequency", "gradient_steps", "target_update_interval", "epsilon",
                     "huber_delta", "max_grad_norm", "round_trip_variants")


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
    if config.policy == "latency_bound":
        return LatencyBound(), None
    if config.policy == "replay":
        return ReplayPolicy.from_file(os.path.expanduser(config.replay_actions)), None
    dqn = DQNConfig.from_dict({"seed": config.seed, **config.dqn})
    source = config.checkpoint if config.checkpoint and os.path.exists(config.checkpoint) else config.model
    if source:
        agent = load_checkpoint(source, dqn)
        log.info("loaded %s: %d steps, %d gradient steps", source, agent.steps, agent.gradient_steps)
        # The network comes from the checkpoint; how it goes on training is this node's to say (a robot deployed
        # from a learning run's model trains on the deployed schedule, not the learning run's): DQNConfig's
        # defaults, which are the robot's, with ~dqn over them.
        agent.config = replace(agent.config, **{name: getattr(dqn, name) for name in TRAINING_SCHEDULE})
    else:
        agent = DQNAgent(dqn)
        log.warning("no checkpoint at %r and no ~model: the DQN starts untrained", config.checkpoint)
    return DQNPolicy(dqn, agent=agent, learn=config.learn, seed=config.seed + agent.steps,
                     explore=config.explore), agent
