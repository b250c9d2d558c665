"""What off-policy evaluation needs of each logged request (LoggedSteps), read from a RequestLog."""
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.data.records import RequestLog
from offload_learner_py.online.breaker import OPEN, SLOW
from offload_learner_py.offline.off_policy_estimators import cross_fitted_latencies

# Routing (the decision's `breaker` field) that sends a request to the local planner whatever the policy chose.
FORCED_LOCAL = (OPEN, SLOW)


@dataclass
class LoggedSteps:
    """What off-policy evaluation needs of each logged request."""
    states: np.ndarray          # N x len(STATE_SCHEMA): d, u, b
    action: np.ndarray
    propensity: np.ndarray
    latency_s: np.ndarray       # measured latency of the taken side
    probe: np.ndarray           # both sides measured on a probe step
    local_s: np.ndarray         # NaN where not measured
    cloud_s: np.ndarray
    censored: int = 0           # requests at a lower bound: the taken side was cancelled (a hedge's other side won)

    def __len__(self):
        return len(self.action)

    @classmethod
    def from_log(cls, log: RequestLog, rows: Optional[np.ndarray] = None) -> "LoggedSteps":
        pick = (lambda name: np.asarray(log[name])) if rows is None else (lambda name: np.asarray(log[name])[rows])
        # The behaviour is what the router did: the side it called first (the decided action unless the circuit
        # breaker kept a cloud decision local). Where the breaker was open, or the hedge's slow-link guard applied,
        # the router would have called the local planner whatever the policy drew: that side's propensity is 1,
        # not the drawn decision's.
        action = pick("routed" if "routed" in log.columns else "action").astype(np.int64)
        forced = np.isin(np.asarray(pick("breaker"), dtype=object), FORCED_LOCAL) if "breaker" in log.columns \
            else np.zeros(len(action), dtype=bool)
        local_s, cloud_s = pick("outcome_local_s").astype(np.float64), pick("outcome_cloud_s").astype(np.float64)
        both = np.isfinite(local_s) & np.isfinite(cloud_s) & (local_s > 0) & (cloud_s > 0)
        probe = pick("probe").astype(bool) & both
        latency_s = np.where(action == CLOUD, cloud_s, local_s)
        # A hedged request whose other side answered first had its taken side cancelled then: that side would
        # have taken longer than the request's delivery time, which enters as its latency (a lower bound, so the
        # estimate errs low by less than leaving the slow request out would).
        delivered_s = pick("outcome_delivered_s").astype(np.float64)
        censored = ~np.isfinite(latency_s) & np.isfinite(delivered_s)
        latency_s = np.where(censored, delivered_s, latency_s)
        steps = cls(states=STATE_SCHEMA.stack(pick),
                    action=action, propensity=np.where(forced, 1.0, pick("action_propensity").astype(np.float64)),
                    latency_s=latency_s, probe=probe, local_s=local_s, cloud_s=cloud_s, censored=int(censored.sum()))
        known = np.isfinite(latency_s)
        return steps if known.all() else steps.slice(known)   # nothing known of it at all: left out

    def slice(self, rows) -> "LoggedSteps":
        return LoggedSteps(**{name: getattr(self, name)[rows] for name in
                              ("states", "action", "propensity", "latency_s", "probe", "local_s", "cloud_s")},
                           censored=self.censored)

    def sides(self) -> Tuple[np.ndarray, np.ndarray]:
        """Each side's measured latency per request, NaN where not measured; the taken side's is latency_s
        (a censored request's delivery time included)."""
        taken = np.isfinite(self.latency_s) & (self.latency_s > 0)
        local_s = np.where((self.action == LOCAL) & taken, self.latency_s, self.local_s)
        cloud_s = np.where((self.action == CLOUD) & taken, self.latency_s, self.cloud_s)
        measured = lambda values: np.where(np.isfinite(values) & (values > 0), values, np.nan)  # noqa: E731
        return measured(local_s), measured(cloud_s)

    def largest_latency_s(self) -> float:
        """The largest latency measured on either side: no mean latency can be above it by the data."""
        values = np.concatenate(self.sides())
        values = values[np.isfinite(values)]
        return float(values.max()) if len(values) else 0.0

    def latency_model(self, folds: int = 2) -> np.ndarray:
        """N x 2 cross-fitted predicted latency of each side (off_policy_estimators.cross_fitted_latencies)
        from every measured latency: a probe's two sides, a non-probe's taken side."""
        return cross_fitted_latencies(self.states, *self.sides(), folds=folds)
