"""The router's vocabulary and settings: its two modes, the status codes it must tell apart, what one planner
call and one request came to (the Outcome the router hands the learner, learning.py), and RouterConfig. No
logic beyond checking the settings."""
import math
from dataclasses import dataclass, field
from typing import Any, Optional

from offload_learner_py.core.policies import Decision
from offload_learner_py.core.reward import DEFAULT_CLOUD_TIMEOUT_S, CostWeights
from offload_learner_py.core.state import State
from offload_learner_py.online.breaker import CLOSED, BreakerConfig
from offload_learner_py.online.latency_model import LatencyModelConfig

LEARNING, DEPLOYED = "learning", "deployed"
MODES = (LEARNING, DEPLOYED)



@dataclass(frozen=True)
class Statuses:
    """The PlanPath status codes the router must tell apart (the node passes the message's constants)."""
    ok: int
    cloud_timeout: int
    cloud_error: int
    stale_map: Optional[int] = None   # a path only on an older map; None: delivered as OK with a note
    cancelled: Optional[int] = None   # a call the router cancelled (None: the sides cannot be cancelled)
    refusals: tuple = ()              # a planner's verdicts that the request has no path (NO_PATH, START/GOAL_BLOCKED):
                                      # from the cloud alone, checked by the local planner before they are final

    def cloud_failed(self, status: int) -> bool:
        """The cloud could not answer; the request itself may be fine, so plan it locally."""
        return status in (self.cloud_timeout, self.cloud_error)


@dataclass
class SideResult:
    """One planner call as the learner saw it: status, response, call-to-reply seconds."""
    status: int
    response: Any
    seconds: float
    raised: Optional[str] = None    # no usable answer (planner node down, a stale map): why
    note: Optional[str] = None      # a usable answer with a caveat (planned on the last map the planner took)
    link_failed: bool = False       # the call itself failed (timeout, link error, planner node gone), not a stale map
    cpu_s: float = 0.0              # robot CPU-seconds the serving node spent on it (the response says)
    bytes_sent: int = 0             # link bytes robot -> cloud for it (cloud side)
    bytes_received: int = 0
    cancelled: bool = False         # a background call dropped before it started or cancelled while it ran
                                    # (a newer request took the side); seconds: how long it had run
    started_after_s: float = 0.0    # from the request's arrival to the call (a busy side, or a hedge)


@dataclass(frozen=True)
class Routing:
    """What the router did with a decision, handed to on_decision before any side is called."""
    request_id: int
    state: State
    decision: "Decision"
    probe: bool
    action: int                     # side called first: the policy's action unless the breaker (or SLOW) overrode it
    mode: str
    breaker: str = CLOSED           # CLOSED, OPEN (cloud skipped), TRIAL (a probe to test the link) or SLOW (the
                                    # hedge kept a cloud choice local: its round trip alone is too long)
    deadline_s: float = float("nan")   # hedge deadline of the first side; NaN when not hedged
    request: Any = field(default=None, compare=False, repr=False)   # the caller's request, for its records


@dataclass
class Outcome:
    """One routed request. The router fills in the decision, the sides' results and the costs; the learner
    (learning.py) the measured latencies, the reward and what it learned."""
    request_id: int
    state: Optional[State]
    decision: Decision
    probe: bool
    delivered: int                  # LOCAL, CLOUD or NO_PATH_DELIVERED
    delivered_s: float              # arrival of the request to its path, as the caller saw it
    local: Optional[SideResult] = None
    cloud: Optional[SideResult] = None
    local_s: Optional[float] = None     # l_local when measured
    cloud_s: Optional[float] = None     # l_cloud when measured (timeout when the cloud failed)
    cloud_timeout: bool = False
    reward: Optional[float] = None  # eq. 10 of the decided action, from measured (or imputed) latencies
    loss: Optional[float] = None
    learned: bool = False           # a transition went to the learner
    transitions: int = 0            # how many: 2 with both latencies (full information), else 0
    imputed: Optional[int] = None   # the side whose latency the reward imputed (LOCAL or CLOUD), None if measured
    hedged: bool = False            # the other side was started after the first missed its deadline
    routing: Optional[Routing] = None
    robot_cpu_s: float = 0.0        # robot planning CPU: the local planner node's own, for this request
    bridge_cpu_s: float = 0.0       # the cloud bridge's CPU on the robot for this request (serialising, waiting)
    learner_cpu_s: float = 0.0      # the learner's CPU learning from it (latency models, transitions, training)
    bytes_sent: int = 0
    bytes_received: int = 0
    local_lower_bound_s: Optional[float] = None   # a local call cancelled after running this long (l_local
                                                  # was at least that); None when none was cancelled running


@dataclass
class RouterConfig:
    mode: str = DEPLOYED
    """learning (probe every request, full-information learning) or deployed (the chosen side alone)."""
    probe_rate: float = 0.05
    """deployed: share of requests on which both sides run (learning mode probes every request)."""
    probe_while_warming_up: bool = True
    """deployed: a learning policy probes every request while it is still warming up (an untrained DQN) or
    while either side's latency model lacks its first samples (a warm-started DQN on a fresh node: a
    one-sided request would teach nothing, there being nothing to impute with, and the hedge would have no
    deadline); then, as a fixed policy always does, it probes at probe_rate only."""
    probe_after_delivery: bool = True
    """deployed: a probe's other side starts once the chosen side has answered, so the caller waits for the chosen
    side alone and each side is measured without the other loading the robot; False: both at once, as learning
    mode's probes and the breaker's link tests always run."""
    cloud_timeout_s: float = DEFAULT_CLOUD_TIMEOUT_S
    """l_cloud of a request the cloud did not answer (the paper's 5 s). This and `weights` (eq. 10's alpha and
    beta) are the learner's settings (learning.py); the node passes them on with `latency_model`."""
    weights: CostWeights = field(default_factory=CostWeights)
    seed: int = 1
    """seed of the probe draws."""
    map_wait_s: float = 2.0
    """how long a side that answers from a map older than the one in force is asked again before its
    answer counts as a failure (a planner gets a new map a moment after the learner hears of it)."""
    map_retry_s: float = 0.02
    """pause between those calls."""
    hedge: bool = False
    """start the other side when the chosen one has not answered by the deadline."""
    hedge_deadline_s: float = 0.0
    """a fixed deadline; 0: the hedge_quantile of the chosen side's latency model for the state."""
    hedge_quantile: float = 0.95
    hedge_min_s: float = 0.05
    hedge_max_s: float = 1.0
    """the model's deadline is clamped to [min, max]; max also serves while the model is not ready."""
    breaker: BreakerConfig = field(default_factory=BreakerConfig)
    latency_model: LatencyModelConfig = field(default_factory=LatencyModelConfig)

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if not 0.0 <= self.probe_rate <= 1.0:
            raise ValueError(f"probe_rate must be in [0, 1], got {self.probe_rate}")
        if not (self.cloud_timeout_s > 0 and math.isfinite(self.cloud_timeout_s)):
            raise ValueError(f"cloud_timeout_s must be positive, got {self.cloud_timeout_s}")
        if not (self.map_wait_s >= 0 and math.isfinite(self.map_wait_s)):
            raise ValueError(f"map_wait_s must be finite and >= 0, got {self.map_wait_s}")
        if not (self.map_retry_s > 0 and math.isfinite(self.map_retry_s)):
            raise ValueError(f"map_retry_s must be positive, got {self.map_retry_s}")
        if not (self.hedge_deadline_s >= 0 and math.isfinite(self.hedge_deadline_s)):
            raise ValueError(f"hedge_deadline_s must be finite and >= 0, got {self.hedge_deadline_s}")
        if not 0.5 <= self.hedge_quantile < 1.0:
            raise ValueError(f"hedge_quantile must be in [0.5, 1), got {self.hedge_quantile}")
        if not (0 < self.hedge_min_s <= self.hedge_max_s and math.isfinite(self.hedge_max_s)):
            raise ValueError(f"need 0 < hedge_min_s <= hedge_max_s < inf, got {self.hedge_min_s}, {self.hedge_max_s}")

    @property
    def probes_every_request(self) -> bool:
        return self.mode == LEARNING or self.probe_rate >= 1.0
