"""Link-health circuit breaker: stop offloading into a cloud the robot already knows is down or too slow.

Closed (normal): cloud calls go ahead. It opens after `failures_to_open` cloud failures in a row (a timeout
or a link error, never a request the planner refused), or when a heartbeat says the cloud is unreachable or
its round trip exceeds `max_round_trip_s` (a link that cannot beat the deadline). While open, the router
plans locally without touching the link, so no request pays the cloud timeout. It closes again on the first
heartbeat (the bridge's periodic ping, a few bytes) that is reachable and within `max_round_trip_s`, or on a
trial: every `retry_after_s` one request is let through as a probe (both sides at once, the caller gets the
first good path, so a trial into a dead link costs the caller nothing) and a cloud answer closes it.
"""
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

CLOSED, OPEN, TRIAL = "closed", "open", "trial"
SLOW = "slow"   # not a breaker state: the router's hedge kept one cloud choice local (its round trip too long)


@dataclass(frozen=True)
class BreakerConfig:
    failures_to_open: int = 3
    """consecutive cloud failures that open the breaker (0 disables the breaker)."""
    max_round_trip_s: float = 1.0
    """a heartbeat round trip above this opens it (the hedge's longest deadline is a good value; inf: never)."""
    retry_after_s: float = 5.0
    """while open, one request this often is a trial probe."""

    def __post_init__(self):
        if self.failures_to_open < 0:
            raise ValueError(f"failures_to_open must be >= 0, got {self.failures_to_open}")
        if not self.max_round_trip_s > 0:
            raise ValueError(f"max_round_trip_s must be > 0, got {self.max_round_trip_s}")
        if not (self.retry_after_s > 0 and math.isfinite(self.retry_after_s)):
            raise ValueError(f"retry_after_s must be positive and finite, got {self.retry_after_s}")


class LinkBreaker:
    """Thread-safe: the router records call results from side threads, the node records heartbeats."""

    def __init__(self, config: BreakerConfig = BreakerConfig(), clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.clock = clock
        self._lock = threading.Lock()
        self._failures = 0
        self._open = False
        self._last_trial = 0.0
        self.reason = ""
        self.trips = 0

    @property
    def enabled(self) -> bool:
        return self.config.failures_to_open > 0

    @property
    def is_open(self) -> bool:
        with self._lock:
            return self._open

    def admit(self) -> str:
        """CLOSED: call the cloud as the policy says; OPEN: plan locally only; TRIAL: the breaker is open but
        a trial is due, so run the request as a probe."""
        if not self.enabled:
            return CLOSED
        with self._lock:
            if not self._open:
                return CLOSED
            now = self.clock()
            if now - self._last_trial >= self.config.retry_after_s:
                self._last_trial = now
                return TRIAL
            return OPEN

    def record_call(self, succeeded: bool) -> None:
        """A cloud call's result: succeeded means the cloud answered (any planner status), failed means a
        timeout or link error."""
        if not self.enabled:
            return
        with self._lock:
            if succeeded:
                self._failures = 0
                self._close_locked()
                return
            self._failures += 1
            if self._failures >= self.config.failures_to_open:
                self._open_locked(f"{self._failures} cloud failures in a row")

    def record_heartbeat(self, reachable: bool, round_trip_s: float) -> None:
        if not self.enabled:
            return
        with self._lock:
            if not reachable:
                self._open_locked("heartbeat: cloud unreachable")
            elif not round_trip_s <= self.config.max_round_trip_s:
                self._open_locked(f"heartbeat: round trip {round_trip_s:.3f} s over {self.config.max_round_trip_s:g} s")
            else:
                self._failures = 0
                self._close_locked()

    def _open_locked(self, reason: str) -> None:
        if not self._open:
            self._open = True
            self._last_trial = self.clock()
            self.trips += 1
        self.reason = reason

    def _close_locked(self) -> None:
        self._open = False
        self.reason = ""
