"""The router's deadline hedge without ROS: when the chosen side may take before the other starts, whether starting
the other is worth it, and which cloud choices the link's round trip alone rules out. It reads the learner's
per-side latency models (latency_model.py) for the request's state and the link breaker (breaker.py); the router
(router.py) acts on its answers."""
from typing import Dict

from offload_learner_py import CLOUD, LOCAL, OTHER
from offload_learner_py.core.state import State
from offload_learner_py.online.breaker import OPEN, LinkBreaker
from offload_learner_py.online.latency_model import LatencyModel
from offload_learner_py.online.learning import latency_features as _features
from offload_learner_py.online.router_types import RouterConfig


class DeadlineHedge:
    def __init__(self, config: RouterConfig, models: Dict[int, LatencyModel], breaker: LinkBreaker):
        self.config, self.models, self.breaker = config, models, breaker

    def round_trip_too_slow(self, state: State) -> bool:
        """The guard on a cloud choice: the measured round trip alone is longer than the local planner's
        hedge_quantile for this state, so the cloud cannot answer before a local plan would almost surely be done
        (a link on the slow end of its range, in a state the policy has seen too little of)."""
        local_q = self.models[LOCAL].quantile_s(_features(state), self.config.hedge_quantile)
        return local_q is not None and state.round_trip_s >= local_q

    def deadline_s(self, side: int, state: State) -> float:
        """How long the chosen side may take before the other starts: the hedge_quantile of its latency for
        this state, clamped to [hedge_min_s, hedge_max_s], and sooner:
        - a local plan, once the cloud's median for the state has passed: the cloud would most likely have
          been done already, and it costs the robot only the bridge;
        - a cloud call, once the local planner's median has passed (never before the cloud's own median): a
          late cloud call (a link slowing down) gets the local plan while it can still win, and the local
          plan is cancelled if the cloud answers first. Whether the local planner is hedged into at all is
          worth_hedging's call."""
        config = self.config
        if config.hedge_deadline_s > 0:
            return config.hedge_deadline_s
        features = _features(state)
        quantile = self.models[side].quantile_s(features, config.hedge_quantile)
        deadline = config.hedge_max_s if quantile is None else quantile
        other = self.models[OTHER[side]].impute_s(features)
        if other is not None:
            own = self.models[side].impute_s(features) if side == CLOUD else None
            deadline = min(deadline, other if own is None else max(other, own))
        return min(max(deadline, config.hedge_min_s), config.hedge_max_s)

    def worth_hedging(self, other: int, state: State) -> bool:
        """The cloud is hedged into unless the breaker says the link is down. The local planner is hedged into
        at the deadline only when its median latency for this state is below the cloud's 95th percentile: on a
        saturated robot a local plan would most likely lose, and its CPU would slow the cloud call's bridge and
        the learner that waits for it."""
        if other == CLOUD:
            return self.breaker.admit() != OPEN
        features = _features(state)
        local_s = self.models[LOCAL].impute_s(features)
        cloud_q = self.models[CLOUD].quantile_s(features, self.config.hedge_quantile)
        return local_s is None or cloud_q is None or local_s < cloud_q
