"""The robot's own local planning rate p_t (a state field, core/state.py): cells the local planner settles per
second of planning, an exponentially weighted mean over its recent plans. It tells robots apart for one pooled
model: a slow robot (a weak CPU, a tight budget) plans the same request slower than a fast one, so the same d_t
and u_t favour the cloud more on it. No ROS: the learner node feeds it each PlanTiming of its local planner
(`expansions`, `planning_time_s`) from the planner's ~timing topic.

Plans too small to time (below `min_expansions` cells or `min_seconds`) say more about the timer and the
planner's fixed costs than about its rate and are ignored. Until the first plan is timed the rate is `initial`
(the schema's value for older records, p_t's `missing`)."""
import math
import threading


class PlanRateEstimator:
    def __init__(self, initial: float, weight: float = 0.2, min_expansions: int = 1000, min_seconds: float = 1e-4):
        if not (math.isfinite(initial) and initial >= 0):
            raise ValueError(f"the initial planning rate must be finite and >= 0, got {initial}")
        if not 0.0 < weight <= 1.0:
            raise ValueError(f"the rate's EWMA weight must be in (0, 1], got {weight}")
        self.weight, self.min_expansions, self.min_seconds = weight, min_expansions, min_seconds
        self._rate = float(initial)
        self.plans = 0                    # plans the rate was measured on
        self._lock = threading.Lock()

    def observe(self, expansions: int, planning_time_s: float) -> bool:
        """One timed local plan; whether it counted."""
        if not (math.isfinite(planning_time_s) and planning_time_s >= self.min_seconds
                and expansions >= self.min_expansions):
            return False
        rate = expansions / planning_time_s
        if not math.isfinite(rate):
            return False
        with self._lock:
            self._rate = rate if self.plans == 0 else (1.0 - self.weight) * self._rate + self.weight * rate
            self.plans += 1
        return True

    @property
    def value(self) -> float:
        """Cells per second: the current estimate (`initial` before the first counted plan)."""
        return self._rate
