"""What the robot's nodes tell an operator (ROS /diagnostics, built by nodes/diagnostics.py): a level, a message and
key values per node, from what the node already measures. No ROS here, so the rules are testable without a master.

Levels are diagnostic_msgs/DiagnosticStatus's. A link is judged with hysteresis: it goes down after `down_after`
heartbeats in a row found it unreachable and comes back after `up_after` in a row answered, so a link that drops one
heartbeat in three does not flood /diagnostics with flips (ROS's diagnostic aggregators latch nothing: every flip
reaches the operator's monitor)."""
from collections import deque
from dataclasses import dataclass, field
from typing import Dict, Optional

OK, WARN, ERROR = 0, 1, 2


@dataclass
class Status:
    level: int
    message: str
    values: Dict[str, str] = field(default_factory=dict)


class Hysteresis:
    """A two-state judgement that needs `set_after` bad observations in a row to turn bad and `clear_after` good
    ones in a row to turn good again."""

    def __init__(self, set_after: int, clear_after: int):
        if set_after < 1 or clear_after < 1:
            raise ValueError(f"hysteresis counts must be >= 1, got {set_after} and {clear_after}")
        self.set_after, self.clear_after = set_after, clear_after
        self.bad = False
        self._run = 0                # observations in a row that disagree with the current state

    def observe(self, bad: bool) -> bool:
        if bad == self.bad:
            self._run = 0
        else:
            self._run += 1
            if self._run >= (self.set_after if bad else self.clear_after):
                self.bad, self._run = bad, 0
        return self.bad


class LinkHealth:
    """The cloud bridge's status: the link by its heartbeats (ERROR while down), the round trip against
    `slow_round_trip_s` (WARN while the last heartbeat was slower), the plans the bridge carried and how they ended,
    and the map: the bridge's last refused map (WARN: the cloud plans on the previous one)."""

    def __init__(self, down_after: int = 2, up_after: int = 2, slow_round_trip_s: float = 1.0):
        self.down = Hysteresis(down_after, up_after)
        self.slow_round_trip_s = slow_round_trip_s
        self.heartbeats = self.missed = self.rested = 0
        self.round_trip_s: Optional[float] = None
        self.plans = {"ok": 0, "timeout": 0, "failed": 0}
        self.map_refused = ""
        self.map_cells = 0

    def heartbeat(self, reachable: bool, round_trip_s: float, pinged: bool = True) -> None:
        """One heartbeat period's measure of the link: a ping's, or (pinged False) a plan's answer within the period,
        which the bridge lets stand for the ping (counted apart: an operator reading "heartbeats" counts pings)."""
        if pinged:
            self.heartbeats += 1
        else:
            self.rested += 1
        self.missed = 0 if reachable else self.missed + 1
        if reachable:
            self.round_trip_s = round_trip_s
        self.down.observe(not reachable)

    def plan(self, outcome: str) -> None:
        """outcome: "ok" (any answer from the cloud planner), "timeout" or "failed" (a link error)."""
        self.plans[outcome] += 1

    def status(self) -> Status:
        rtt = self.round_trip_s
        values = {"heartbeats": str(self.heartbeats), "heartbeats missed in a row": str(self.missed),
                  "heartbeats rested (a plan measured the link)": str(self.rested),
                  "round trip (ms)": "n/a" if rtt is None else f"{rtt * 1e3:.1f}",
                  "plans answered": str(self.plans["ok"]), "plans timed out": str(self.plans["timeout"]),
                  "plans failed": str(self.plans["failed"]), "map cells": str(self.map_cells),
                  "map refused": self.map_refused or "no"}
        if self.down.bad:
            return Status(ERROR, f"cloud unreachable: {self.missed} heartbeats in a row unanswered", values)
        if self.heartbeats + self.rested == 0:
            return Status(WARN, "no heartbeat yet", values)
        if self.map_refused:
            return Status(WARN, f"map refused, the cloud plans on the previous one: {self.map_refused}", values)
        if rtt is not None and rtt > self.slow_round_trip_s:
            return Status(WARN, f"slow link: round trip {rtt * 1e3:.0f} ms", values)
        return Status(OK, "link up" + ("" if rtt is None else f", round trip {rtt * 1e3:.1f} ms"), values)


class LearnerHealth:
    """The learner node's status: WARN while the breaker keeps requests off the cloud (the robot plans everything
    itself) and for `rollback_warn_s` after the robot's guard rolled a model back; the values an operator checks
    first (mode, policy, model version, cloud share of the last `window` decisions, probes, the learner's own CPU
    per request, the fleet rows)."""

    def __init__(self, mode: str, policy: str, window: int = 100, rollback_warn_s: float = 60.0):
        self.mode, self.policy, self.rollback_warn_s = mode, policy, rollback_warn_s
        self.decisions = self.probes = 0
        self._routed = deque(maxlen=window)
        self._cpu_s = deque(maxlen=window)
        self._rollbacks, self._rolled_back_at = 0, None

    def decision(self, routed_to_cloud: bool, probe: bool) -> None:
        self.decisions += 1
        self.probes += probe
        self._routed.append(routed_to_cloud)

    def outcome(self, learner_cpu_s: float) -> None:
        self._cpu_s.append(learner_cpu_s)

    def status(self, breaker_open: bool, breaker_reason: str, fleet: Optional[dict], now: float) -> Status:
        routed, cpu = list(self._routed), list(self._cpu_s)
        values = {"mode": self.mode, "policy": self.policy, "decisions": str(self.decisions),
                  "probes": str(self.probes), "breaker": "open" if breaker_open else "closed",
                  "cloud share (recent)": f"{sum(routed) / len(routed):.2f}" if routed else "n/a",
                  "learner CPU per request (ms)": f"{1e3 * sum(cpu) / len(cpu):.2f}" if cpu else "n/a"}
        if fleet:
            rolled_back = fleet["rolled_back"]
            if len(rolled_back) > self._rollbacks:
                self._rollbacks, self._rolled_back_at = len(rolled_back), now
            values.update({"model version": fleet["model_version"][:12] or "none",
                           "models rolled back": str(len(rolled_back)),
                           "fleet rows sent": str(fleet["fleet_rows_sent"]),
                           "fleet rows dropped": str(fleet["fleet_rows_dropped"]),
                           "fleet rows pending": str(fleet["fleet_rows_pending"])})
        if breaker_open:
            return Status(WARN, f"breaker open, planning locally: {breaker_reason}", values)
        if self._rolled_back_at is not None and now - self._rolled_back_at < self.rollback_warn_s:
            return Status(WARN, f"model {fleet['rolled_back'][-1][:12]} rolled back by the robot's guard", values)
        return Status(OK, f"{self.mode} {self.policy}", values)
