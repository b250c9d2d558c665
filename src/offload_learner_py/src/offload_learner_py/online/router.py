"""The online decision loop of the offloading learner, without ROS: per planning request, decide local
or cloud from s_t, call the chosen side (both on a probe step), hand the caller the first good path, and
once no side is running hand the request's Outcome to the learner (learning.py), which measures, imputes,
rewards (eq. 10) and learns (Algorithm 1) off the caller's path.

The ROS node injects the two planners as callables `plan(request) -> (status, response)` and the
PlanPath status codes, so this module never imports a message type; tests drive it with fakes.

Two modes. `learning`: every request is a probe, both sides run at once and the caller gets the first
good path; both latencies are measured over the same moment of CPU load and link state, and the taken
action is the greedy one (exploring would change nothing the caller gets). `deployed`: the chosen side
alone, so the robot saves its CPU or the link; a `probe_rate` share of requests (drawn independently of the
state, so they are an unbiased sample for off-policy evaluation) are probes, and every request while the
learner `needs_both_sides()`. A deployed probe runs its sides in turn (`probe_after_delivery`): the chosen one,
then the other once the caller has its path, so probing costs the caller no time and each side is measured
alone on the robot. A deployed request measures one side; the learner imputes the other.

The cloud side serves calls concurrently (the bridge borrows a socket per call and a call costs the robot
little CPU), so a cloud call still running in the background never holds up the next request. The local
planner shares the robot's CPU, so its calls run one at a time, and a newer request that needs it cancels
the local call of an earlier request whose caller already has its path (`cancel(call_id)` on the local
side, the planner node's ~cancel topic; the plan stops within a few thousand expansions with CANCELLED).
A cancelled call's CPU is still accounted; its latency is a lower bound (Outcome.local_lower_bound_s), which
the learner uses only where the other side was already faster. `delivered_s` runs from the request's arrival
(any wait for the local planner included) to the path the caller gets. sides.py: the lanes and the calls.

Deadline hedge (hedge.py): when the chosen side has not answered within a deadline (a quantile of the learner's latency
model of that side for this state, clamped, or a fixed bound), the other side starts and the first good path
is delivered. With the hedge on, a cloud choice whose measured round trip alone exceeds the local planner's
hedge quantile for the state is planned locally (routing `slow`): the cloud could not win it. Circuit breaker
(breaker.py): after repeated cloud failures or a heartbeat that says the link is down or too slow, requests
are planned locally without touching the link until the link is healthy again.
"""
import dataclasses
import itertools
import logging
import math
import os
import threading
import time
from contextlib import nullcontext
from typing import Any, Callable, Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL, OTHER
from offload_learner_py.core.policies import Decision
from offload_learner_py.core.state import State
from offload_learner_py.data.records import NO_PATH_DELIVERED
from offload_learner_py.online.breaker import OPEN, SLOW, TRIAL, LinkBreaker
from offload_learner_py.online.hedge import DeadlineHedge
from offload_learner_py.online.learning import OnlineLearner
from offload_learner_py.online.router_types import DEPLOYED, Outcome, RouterConfig, Routing, SideResult, Statuses
from offload_learner_py.online.sides import Accounting, Lane, PlanCall, SideCaller, Workers

LOG = logging.getLogger(__name__)
# How long the side that delivered waits for the caller to take its path before going on (a caller that never
# comes back from its wait, an exception): a bound, not a pace; the caller takes it within microseconds.
TAKEN_WAIT_S = 1.0


class _Request:
    """The state of one routed request, shared by the caller and its side threads."""

    def __init__(self, outcome: Outcome, began: float):
        self.outcome = outcome
        self.began = began
        self.lock = threading.Lock()
        self.delivered = threading.Event()
        self.taken = threading.Event()   # the caller has its path: the side that delivered may go on
        self.delivered_result: Optional[SideResult] = None
        self.started = set()
        self.results = {}
        self.checks_refusal = False   # the local planner runs to check the cloud's refusal
        self.then = None              # a probe's other side, started once the first has answered


class OffloadRouter:
    """Routes requests between `local` and `cloud` planners. `route()` returns the response the caller
    gets; `on_decision(routing)` is called before any side is called, in the caller's thread (its time is the
    caller's: keep it short). The `learner` (learning.py) decides through its policy, lends the hedge its latency
    models, and gets every request's Outcome (`learn`) once no side of it is running, from a side thread;
    `on_outcome(outcome)` is called after that. `on_delivered(routing)`: from the side thread that delivered a decided
    request's path, once the caller has taken it.

    `stale(response)` (optional) says why a good answer was planned on a map older than the one in
    force, or None. The side is asked again until it answers from the current map or `config.map_wait_s`
    has passed. Then the cloud counts as failed (CLOUD_ERROR, so the robot plans locally), while the
    local planner's answer is delivered with a note: it planned on the last map it accepted, so the
    announced map never reached it in a usable form (a malformed grid it refused, a lost message), and
    the last good map keeps serving rather than leaving a robot without a path. `account(response)`
    (optional) gives (robot CPU-seconds, link bytes sent, link bytes received) the serving node reported.

    A side that has a `cancel(call_id)` method is called as `side(request, call_id=...)`, each call with its
    own id, and answers `statuses.cancelled` once cancelled; other sides are called as `side(request)`."""

    def __init__(self, learner: OnlineLearner, local: PlanCall, cloud: PlanCall, statuses: Statuses,
                 config: RouterConfig = RouterConfig(), on_decision: Callable = None,
                 on_outcome: Callable = None, on_delivered: Callable = None,
                 clock: Callable[[], float] = time.perf_counter,
                 stale: Callable[[Any], Optional[str]] = None, sleep: Callable[[float], None] = time.sleep,
                 account: Accounting = None, breaker: LinkBreaker = None):
        self.learner, self.policy, self.models = learner, learner.policy, learner.models
        self.statuses = statuses
        self.sides = {LOCAL: local, CLOUD: cloud}
        self.config = config
        self.on_decision = on_decision or (lambda routing: None)
        self.on_outcome = on_outcome or (lambda outcome: None)
        self.on_delivered = on_delivered or (lambda routing: None)
        self.clock = clock
        self.rng = np.random.default_rng(config.seed)
        self.breaker = breaker or LinkBreaker(config.breaker)
        self.hedge = DeadlineHedge(config, self.models, self.breaker)
        self._lanes = {LOCAL: Lane(serial=True), CLOUD: Lane(serial=False)}
        self._caller = SideCaller(statuses, config, clock, sleep, stale, account)
        self._workers = Workers("offload-side")
        # Call ids start at a random point: a cancel meant for an earlier learner process never hits ours.
        self._call_ids = itertools.count(int.from_bytes(os.urandom(6), "little") + 1)
        self._ids = threading.Lock()
        self._deciding = threading.Lock()   # policy and probe draws share random generators across callers
        self._idle = threading.Condition()
        self._in_flight = 0
        self.next_request_id = 0

    def close(self) -> None:
        self.wait_idle()

    def wait_idle(self, timeout_s: Optional[float] = None) -> bool:
        """True once every request's outcome was handed over."""
        with self._idle:
            return self._idle.wait_for(lambda: self._in_flight == 0, timeout_s)

    # --- one request ----------------------------------------------------------------------------
    def route(self, request, state: Optional[State], arrived: Optional[float] = None):
        """The caller's response. `arrived`: when the request reached the node (clock time), so waits before
        routing count; default now. state None (no map yet, a malformed pose): the request goes to the
        local planner, which reports the exact status, and nothing is learned from it."""
        began = self.clock() if arrived is None else arrived
        with self._ids:
            request_id = self.next_request_id
            self.next_request_id += 1
        with self._idle:
            self._in_flight += 1
        try:
            if state is None:
                outcome = Outcome(request_id, None, Decision(LOCAL, 1.0), False, NO_PATH_DELIVERED, 0.0)
                return self._run(_Request(outcome, began), (LOCAL,), None, request)
            with self._deciding:
                decision = self.policy.decide(state)
                routing = self._route_decision(request_id, state, decision, request)
            self.on_decision(routing)
            outcome = Outcome(request_id, state, decision, routing.probe, NO_PATH_DELIVERED, 0.0, routing=routing)
            req = _Request(outcome, began)
            first = (LOCAL, CLOUD) if routing.probe else (routing.action,)
            if routing.probe and self._probes_in_turn(routing):
                first, req.then = (routing.action,), OTHER[routing.action]
            deadline = None if math.isnan(routing.deadline_s) else routing.deadline_s
            return self._run(req, first, deadline, request)
        except BaseException:
            self._done()
            raise

    def _route_decision(self, request_id: int, state: State, decision: Decision, request=None) -> Routing:
        config = self.config
        probe = config.probes_every_request or bool(self.rng.random() < config.probe_rate)
        if config.mode == DEPLOYED and config.probe_while_warming_up and not probe:
            probe = self.learner.needs_both_sides()
        admitted = self.breaker.admit()
        action = decision.action
        if admitted == OPEN:
            probe, action = False, LOCAL      # a link known to be down is not offloaded into
        elif admitted == TRIAL:
            probe = True                      # both sides: the caller gets local at worst, the link is tested
        elif config.hedge and not probe and action == CLOUD and self.hedge.round_trip_too_slow(state):
            admitted, action = SLOW, LOCAL
        deadline_s = float("nan")
        if config.hedge and not probe:
            # The local planner still busy with a call someone waits for would make this one wait for it: the
            # hedge then starts the other side at once. (A call nobody waits for is cancelled instead.)
            deadline_s = 0.0 if self._lanes[action].busy() else self.hedge.deadline_s(action, state)
        return Routing(request_id, state, decision, probe, action, config.mode, admitted, deadline_s, request)

    def _probes_in_turn(self, routing: Routing) -> bool:
        """A deployed probe runs its sides in turn (config.probe_after_delivery); learning mode's probes and the
        breaker's link tests (the caller gets the local path at worst) run both at once."""
        return self.config.probe_after_delivery and self.config.mode == DEPLOYED and routing.breaker != TRIAL

    def _run(self, req: _Request, first, deadline_s: Optional[float], request=None):
        self._start(req, first, request)
        if deadline_s is not None and not req.delivered.wait(deadline_s):
            other = OTHER[first[0]]
            if self.hedge.worth_hedging(other, req.outcome.state):
                self._hedge(req, other, request)
            elif other == LOCAL and not req.delivered.wait(max(0.0, self.config.hedge_max_s - deadline_s)):
                # By hedge_max_s a cloud call is as good as failed (a dead link the breaker has not caught
                # yet): the local plan starts whatever it costs, so no request waits for the cloud timeout.
                self._hedge(req, other, request)
        req.delivered.wait()
        req.taken.set()
        return req.delivered_result

    def _hedge(self, req: _Request, other: int, request) -> None:
        with req.lock:
            late = not req.delivered.is_set() and other not in req.started
        if late:
            req.outcome.hedged = True
            self._start(req, (other,), request)

    def _start(self, req: _Request, sides, request) -> None:
        """All of `sides` count as started before any runs, so the first to finish cannot finish the request."""
        with req.lock:
            sides = [side for side in sides if side not in req.started]
            req.started.update(sides)
        self._launch(req, sides, request)

    def _launch(self, req: _Request, sides, request) -> None:
        """Calls `sides`, already counted as started under req.lock."""
        for side in sides:
            self._lanes[side].want(req.outcome.request_id)
        for side in sides:
            self._workers.submit(self._side, req, side, request)

    def _side(self, req: _Request, side: int, request) -> None:
        lane = self._lanes[side]
        call_id = next(self._call_ids) & 0xFFFFFFFFFFFFFFFF
        if lane.serial:   # running calls of earlier requests that already have their path: this one won't wait
            self._cancel(side, lane.abandoned(req.outcome.request_id))
        with lane.lock if lane.serial else nullcontext():
            # A call whose caller has its path is not started when a newer request needs the side, nor, the
            # local planner's CPU being the robot's, when it is no probe's measurement.
            if lane.serial and req.delivered.is_set() and (lane.superseded(req.outcome.request_id)
                                                           or not req.outcome.probe):
                result = SideResult(self.statuses.cloud_error, None, 0.0, raised="cancelled: its caller had a path "
                                    "before it started", cancelled=True)
            else:
                started_after_s = self.clock() - req.began
                lane.begin(call_id, req)
                try:
                    result = self._caller.call(self.sides[side], request, stale_fails=side == CLOUD, call_id=call_id)
                except Exception as error:   # a broken stale() or account(): a failed side, never a lost request
                    result = SideResult(self.statuses.cloud_error, None, self.clock() - req.began - started_after_s,
                                        raised=f"{type(error).__name__}: {error}", link_failed=True)
                finally:
                    lane.end(call_id)
                result.started_after_s = started_after_s
        if side == CLOUD and not result.cancelled and req.outcome.state is not None \
                and not (result.status in self.statuses.refusals and LOCAL not in req.started and req.then != LOCAL):
            self.breaker.record_call(not result.link_failed, result.seconds)   # a refusal: when the local verdict is in
        self._settle(req, side, result, request)

    def _cancel(self, side: int, call_ids) -> None:
        """Cancels these calls of the side; a side without cancel() keeps running them, and a cancel that fails
        leaves the call to finish (whoever needs the side waits for it)."""
        cancel = getattr(self.sides[side], "cancel", None)
        if cancel is None:
            return
        for call_id in call_ids:
            try:
                cancel(call_id)
            except Exception:
                pass

    def _settle(self, req: _Request, side: int, result: SideResult, request) -> None:
        """Record one side's result; deliver the first good path; when no side is left running, finish."""
        fallback = False
        refusal = None
        then = None
        with req.lock:
            was_delivered = req.delivered.is_set()
            req.results[side] = result
            if req.then is not None and req.then not in req.started:
                then = req.then   # the probe's other side: a measurement, or the fallback if this one failed
                req.started.add(then)
            if side == LOCAL and req.checks_refusal:
                refusal = req.results[CLOUD]
                if result.status == self.statuses.ok and not result.cancelled:
                    # A path where the cloud said there is none: the cloud's answer was wrong, a cloud failure.
                    req.results[CLOUD] = dataclasses.replace(refusal, status=self.statuses.cloud_error,
                                                             raised=f"the cloud's refusal (status {refusal.status}) "
                                                                    f"contradicted: the local planner found a path")
            good = result.status == self.statuses.ok and result.note is None and not result.cancelled
            abandon = False
            if good and not req.delivered.is_set():
                self._deliver(req, side, result)
                # A hedge's local plan is not a measurement anyone asked for: its CPU is freed at once.
                abandon = side == CLOUD and not req.outcome.probe and LOCAL in req.started \
                    and LOCAL not in req.results
            all_done = req.started <= set(req.results)
            if all_done and not req.delivered.is_set():
                if LOCAL not in req.started and self.statuses.cloud_failed(result.status):
                    fallback = True           # the cloud failed: the robot still gets its path
                elif LOCAL not in req.started and result.status in self.statuses.refusals:
                    # The cloud alone says there is no path: a robot always gets a path when one exists, so the
                    # local planner checks before the refusal is final (a lying cloud said NO_PATH to reachable goals).
                    fallback = req.checks_refusal = True
                elif LOCAL in req.results:
                    self._deliver(req, LOCAL, req.results[LOCAL])
                else:
                    self._deliver(req, side, result)   # the planner's own verdict on the request (NO_PATH, ...)
            finish = all_done and not fallback
            delivered = req.delivered.is_set() and not was_delivered   # by this thread
        if delivered:
            # The caller first: this thread holds the interpreter, and what follows (the other side's call, the
            # learner, the node's records) would keep the woken caller waiting for it, 0.5 ms at the median and
            # 4-6 ms at the 90th percentile on a loaded robot, after delivered_s was taken.
            req.taken.wait(TAKEN_WAIT_S)
            try:
                if req.outcome.routing is not None:
                    self.on_delivered(req.outcome.routing)
            except Exception:   # a broken record never loses the request's outcome
                LOG.exception("on_delivered failed for request %d", req.outcome.request_id)
        if abandon:
            self._cancel(LOCAL, self._lanes[LOCAL].calls_of(req))
        if refusal is not None and req.outcome.state is not None:
            self.breaker.record_call(req.results[CLOUD] is refusal, refusal.seconds)
        if then is not None:
            self._launch(req, (then,), request)
        if fallback:
            self._start(req, (LOCAL,), request)
        elif finish:
            self._finish(req)

    def _deliver(self, req: _Request, side: int, result: SideResult) -> None:
        """Under req.lock."""
        req.outcome.delivered_s = self.clock() - req.began
        if result.status == self.statuses.ok and not result.cancelled:
            req.outcome.delivered = side
        req.delivered_result = result
        req.delivered.set()

    # --- after the caller has its path ------------------------------------------------------------
    def _finish(self, req: _Request) -> None:
        """No side is running: the request's costs and its sides' results into the Outcome, then the learner."""
        outcome = req.outcome
        try:
            for side, result in req.results.items():
                if side == LOCAL:
                    outcome.robot_cpu_s += result.cpu_s   # a cancelled plan's CPU was spent all the same
                else:
                    outcome.bridge_cpu_s += result.cpu_s
                outcome.bytes_sent += result.bytes_sent
                outcome.bytes_received += result.bytes_received
                if result.cancelled:
                    if side == LOCAL and result.response is not None:
                        outcome.local_lower_bound_s = result.seconds
                elif side == LOCAL:
                    outcome.local = result
                else:
                    outcome.cloud = result
            self.learner.learn(outcome)
            self.on_outcome(outcome)
        finally:
            self._done()

    def _done(self) -> None:
        with self._idle:
            self._in_flight -= 1
            self._idle.notify_all()
