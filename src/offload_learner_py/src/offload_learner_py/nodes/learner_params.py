"""The offload_learner node's parameters: each one a field of SessionConfig, RouterConfig, BreakerConfig,
CostWeights, FleetConfig (`~fleet_*`), GuardConfig (`~guard_*`) or the node's own LearnerNodeConfig, whose default
is the parameter's. launch/config/learner.yaml
holds only what a deployment overrides; the README's table is checked against PARAMETERS."""
import math
from dataclasses import dataclass, field
from typing import NamedTuple

from offload_learner_py.core.reward import CostWeights
from offload_learner_py.nodes import params
from offload_learner_py.online.breaker import BreakerConfig
from offload_learner_py.online.fleet_link import FleetConfig
from offload_learner_py.online.model_guard import GuardConfig
from offload_learner_py.online.router_types import RouterConfig
from offload_learner_py.online.session import SessionConfig, dqn_settings


@dataclass(frozen=True)
class LearnerNodeConfig:
    """The node's own settings: its planners, topics and CPU source, and the RViz goals."""
    torch_threads: int = 1
    """torch threads: one is fastest for this network, leaves the robot's other cores to the planner and keeps
    the learning thread's CPU time whole."""
    deployed_dqn: dict = field(default_factory=dict)
    """DQNConfig fields over ~dqn in deployed mode only."""
    local_service: str = "/planner/plan"
    local_cancel_topic: str = "/planner/cancel"
    """the local planner's ~cancel ("": its plans are never cancelled)."""
    cloud_service: str = "/cloud_bridge/plan"
    latency_topic: str = "/cloud_bridge/latency"
    plan_rate_weight: float = 0.2
    """EWMA weight of the newest timed local plan in p_t, d_t per second of local planning (online/plan_rate.py)."""
    service_wait_s: float = 60.0
    """wait for both planners, the map metadata and a first round trip."""
    cpu_cgroup: str = ""
    cpu_cores: str = ""
    recorder_node: str = "offload_record"
    wait_for_recorder_s: float = 0.0
    goal_tolerance: float = 0.5
    """tolerance of RViz goals (m)."""
    start_x: float = math.nan
    start_y: float = math.nan
    base_frame: str = "base_link"
    stats_period_s: float = 1.0
    """~stats at most this often (s), after a request; 0: after every request. Each publish wakes the topic's
    writer thread, a cost per request the robot pays for a message an operator reads once a second."""

    def __post_init__(self):
        if not (math.isfinite(self.stats_period_s) and self.stats_period_s >= 0):
            raise ValueError(f"stats_period_s must be finite and >= 0, got {self.stats_period_s}")


# ~name -> (dataclass, field). ~seed also seeds the router's probe draws (RouterConfig.seed, the same default).
PARAMETERS = {
    **{name: (SessionConfig, name) for name in (
        "policy", "model", "checkpoint", "checkpoint_every", "learn", "explore", "seed", "dqn",
        "threshold_input_size", "replay_actions", "progress_every", "stats_window")},
    **{name: (RouterConfig, name) for name in (
        "mode", "probe_rate", "probe_after_delivery", "cloud_timeout_s", "map_wait_s", "hedge", "hedge_deadline_s", "hedge_quantile",
        "hedge_min_s", "hedge_max_s")},
    "breaker_failures": (BreakerConfig, "failures_to_open"),
    "breaker_max_round_trip_s": (BreakerConfig, "max_round_trip_s"),
    "breaker_retry_s": (BreakerConfig, "retry_after_s"),
    "breaker_slow_call_s": (BreakerConfig, "slow_call_s"),
    "alpha": (CostWeights, "alpha"),
    **{spec: (LearnerNodeConfig, spec) for spec in LearnerNodeConfig.__dataclass_fields__},
    # Fleet mode (deployed DQN with a fleet learner): the robot decides, the cloud learns.
    **{f"fleet_{spec}": (FleetConfig, spec) for spec in FleetConfig.__dataclass_fields__},
    **{f"guard_{spec}": (GuardConfig, spec) for spec in GuardConfig.__dataclass_fields__},
}


class LearnerParameters(NamedTuple):
    session: SessionConfig
    router: RouterConfig
    node: LearnerNodeConfig
    fleet: FleetConfig
    guard: GuardConfig


def read_learner_parameters(get: params.Getter) -> LearnerParameters:
    """Every parameter from `get(name, default)`; a value a config refuses raises ValueError."""
    values = params.read(get, PARAMETERS)
    node = LearnerNodeConfig(**params.for_class(values, PARAMETERS, LearnerNodeConfig))
    session = params.for_class(values, PARAMETERS, SessionConfig)
    session["dqn"] = dqn_settings(values["mode"], values["dqn"], node.deployed_dqn)
    alpha = values["alpha"]
    router = RouterConfig(**params.for_class(values, PARAMETERS, RouterConfig), seed=values["seed"],
                          weights=CostWeights(alpha, 1.0 - alpha),
                          breaker=BreakerConfig(**params.for_class(values, PARAMETERS, BreakerConfig)))
    return LearnerParameters(SessionConfig(**session), router, node,
                             FleetConfig(**params.for_class(values, PARAMETERS, FleetConfig)),
                             GuardConfig(**params.for_class(values, PARAMETERS, GuardConfig)))
