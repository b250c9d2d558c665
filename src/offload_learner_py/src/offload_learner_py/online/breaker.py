"""Link-health circuit breaker: stop offloading into a cloud the robot already knows is down or too slow.

Closed (normal): cloud calls go ahead. It opens after `failures_to_open` cloud failures in a row (a timeout,
a link error, or an answer slower than `slow_call_s`: a cloud that pings fine but plans slowly; never a request
the planner refused), or when a heartbeat says the cloud is unreachable or its round trip exceeds
`max_round_trip_s` (a link that cannot beat the deadline; a cloud answer's measured round trip counts too, as the
bridge rests its heartbeat while plans measure the link). While open, the router plans locally without
touching the link, so no request pays the cloud timeout. Opened by a heartbeat, it closes on the first heartbeat
(the bridge's periodic ping, a few bytes) that is reachable and within `max_round_trip_s`. Opened by failed
calls, a healthy ping proves nothing about planning (an erroring cloud that pings fine re-closed it at every
heartbeat), so only a trial closes it: every `retry_after_s` one request is let through as a probe (both sides
at once, the caller gets the first good path, so a trial into a dead link costs the caller nothing) and a
timely cloud answer closes it. Only a timely cloud answer resets the count of failures.
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
    slow_call_s: float = 2.0
    """a cloud answer slower than this counts as a failure (a cloud that pings fine but plans slowly); inf: never."""

    def __post_init__(self):
        if self.failures_to_open < 0:
            raise ValueError(f"failures_to_open must be >= 0, got {self.failures_to_open}")
        if not self.max_round_trip_s > 0:
            raise ValueError(f"max_round_trip_s must be > 0, got {self.max_round_trip_s}")
        if not (self.retry_after_s > 0 and math.isfinite(self.retry_after_s)):
            raise ValueError(f"retry_after_s must be positive and finite, got {self.retry_after_s}")
        if not self.slow_call_s > 0:
            raise ValueError(f"slow_call_s must be > 0, got {self.slow_call_s}")


class LinkBreaker:
    """Thread-safe: the router records call results from side threads, the node records heartbeats."""

    def __init__(self, config: BreakerConfig = BreakerConfig(), clock: Callable[[], float] = time.monotonic):
        self.config = config
        self.clock = clock
        self._lock = threading.Lock()
        self._failures = 0
        self._open = False
        self._opened_by_calls = False
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

    def record_call(self, succeeded: bool, seconds: float = 0.0) -> None:
        """A cloud call's result: succeeded means the cloud answered (any planner status) and `seconds` is how
        long it took; failed means a timeout or link error. An answer slower than slow_call_s is a failure."""
        if not self.enabled:
            return
        with self._lock:
            slow = succeeded and not seconds <= self.config.slow_call_s
            if succeeded and not slow:
                self._failures = 0
                self._close_locked()
                return
            self._failures += 1
            if self._failures >= self.config.failures_to_open:
                what = "slow or failed cloud calls" if slow else "cloud failures"
                self._open_locked(f"{self._failures} {what} in a row", by_calls=True)

    def record_round_trip(self, heartbeat: bool, reachable: bool, round_trip_s: float) -> None:
        """A measured link round trip: the heartbeat's, or a cloud answer's (the bridge skips its heartbeat while
        plans measure the link, so the round-trip rule reads both). A request the cloud did not answer is
        record_call's failure, not a heartbeat's."""
        if heartbeat or reachable:
            self.record_heartbeat(reachable, round_trip_s)

    def record_heartbeat(self, reachable: bool, round_trip_s: float) -> None:
        if not self.enabled:
            return
        with self._lock:
            if not reachable:
                self._open_locked("heartbeat: cloud unreachable", by_calls=False)
            elif not round_trip_s <= self.config.max_round_trip_s:
                self._open_locked(f"link round trip {round_trip_s:.3f} s over {self.config.max_round_trip_s:g} s",
                                  by_calls=False)
            elif self._open and not self._opened_by_calls:
                self._close_locked()

    def _open_locked(self, reason: str, by_calls: bool) -> None:
        if not self._open:
            self._open = True
            self._last_trial = self.clock()
            self.trips += 1
            self._opened_by_calls = by_calls
        elif not by_calls:
            self._opened_by_calls = False   # the heartbeat finds the link down: its return may close the breaker
        self.reason = reason

    def _close_locked(self) -> None:
        self._open = False
        self._opened_by_calls = False
        self.reason = ""
