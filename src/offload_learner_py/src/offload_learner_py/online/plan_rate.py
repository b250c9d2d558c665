"""The robot's own local planning rate p_t (a state field, core/state.py): the input size d_t (eq. 11-12,
core/state.input_size) the local planner gets through per second of planning, an exponentially weighted mean
over its recent plans. It tells robots apart for one pooled model: a slow robot (a weak CPU, a tight budget)
plans the same request slower than a fast one, so the same d_t and u_t favour the cloud more on it.

Why d_t per second and not cells settled per second: what the robot must know is how long a request of a given
size takes, whatever its planner does inside. Cells settled depend on the search (jump points settle a few
hundred where the two waves settle a million for the same request), so a faster search would read as a slower
robot. d_t is the request's own size, the same whichever search runs.

Why from the router's outcomes and not from the planner's ~timing topic: only a routed request has both its d_t
(its state) and, when its local side ran to a path, that side's planner-core time (PlanPath's planning_time_s):
the pair is exact, no matching by time. No ROS: the learner node feeds it each outcome.

A plan too short to time (under `min_seconds`, 10 us: jump points plan small maps in tens of us) or of d_t 0 (a goal beside the start) says more about the timer
and the planner's fixed costs than about its rate and is ignored, as is a local side that was cancelled or
found no path. Until the first plan is timed the rate is `initial` (the schema's value for older records, p_t's
`missing`)."""
import math
import threading


class PlanRateEstimator:
    def __init__(self, initial: float, weight: float = 0.2, min_seconds: float = 1e-5):
        if not (math.isfinite(initial) and initial >= 0):
            raise ValueError(f"the initial planning rate must be finite and >= 0, got {initial}")
        if not 0.0 < weight <= 1.0:
            raise ValueError(f"the rate's EWMA weight must be in (0, 1], got {weight}")
        self.weight, self.min_seconds = weight, min_seconds
        self._rate = float(initial)
        self.plans = 0                    # plans the rate was measured on
        self._lock = threading.Lock()

    def observe(self, input_size: float, planning_time_s: float) -> bool:
        """One timed local plan of a request of input size d_t; whether it counted."""
        if not (math.isfinite(planning_time_s) and planning_time_s >= self.min_seconds
                and math.isfinite(input_size) and input_size > 0.0):
            return False
        rate = input_size / planning_time_s
        if not math.isfinite(rate):
            return False
        with self._lock:
            self._rate = rate if self.plans == 0 else (1.0 - self.weight) * self._rate + self.weight * rate
            self.plans += 1
        return True

    def observe_outcome(self, outcome, ok: int) -> bool:
        """A routed request (online/router_types.Outcome): its d_t and its local side's planner-core time, when
        the local side ran to a path (status `ok`, PlanPath's OK)."""
        local = outcome.local
        if outcome.state is None or local is None or local.cancelled or local.status != ok \
                or local.response is None:
            return False
        return self.observe(outcome.state.input_size, float(getattr(local.response, "planning_time_s", math.nan)))

    @property
    def value(self) -> float:
        """d_t per second: the current estimate (`initial` before the first counted plan)."""
        return self._rate
