"""Fakes for the router's tests: planners with scripted costs on a per-thread virtual clock (no sleeps, no
timing assertions), a recorder of what the router publishes, and the router built around them with its
learner, wired as the node wires them."""
import contextvars
import threading


from offload_learner_py.online.learning import OnlineLearner
from offload_learner_py.online.router import OffloadRouter
from offload_learner_py.online.router_types import RouterConfig, Statuses
from offload_learner_py.core.state import State

OK, NO_PATH, TIMEOUT, ERROR, CANCELLED = 0, 7, 9, 10, 13
STATUSES = Statuses(ok=OK, cloud_timeout=TIMEOUT, cloud_error=ERROR, refusals=(NO_PATH,))
CANCELLABLE = Statuses(ok=OK, cloud_timeout=TIMEOUT, cloud_error=ERROR, cancelled=CANCELLED, refusals=(NO_PATH,))
STATE = State(1.2, 0.6, 0.05, 2e7)


class VirtualClock:
    """Each side call has its own time, from its starter's when it was started (the router's workers run a call in
    a copy of its starter's context); a fake planner advances the calling side's time by its cost."""

    def __init__(self):
        self.now = contextvars.ContextVar("virtual_now", default=0.0)

    def __call__(self):
        return self.now.get()

    def advance(self, seconds):
        self.now.set(self() + seconds)


class FakePlanner:
    def __init__(self, clock, cost_s, status=OK, raises=None, gate=None):
        self.clock, self.cost_s, self.status, self.raises, self.gate = clock, cost_s, status, raises, gate
        self.calls = []

    def __call__(self, request):
        self.calls.append(request)
        if self.gate is not None:
            assert self.gate.wait(10), "test gate never opened"
        self.clock.advance(self.cost_s)
        if self.raises:
            raise self.raises
        return self.status, {"side": self, "request": request}


class CancellablePlanner:
    """A planner the router may cancel, as the planner node through ~cancel: a call holds until `release()`
    (all calls) or until its call id is cancelled, then answers CANCELLED after `ran_s` of virtual time.
    `held`: how many calls may hold (later ones answer at once); None: all."""

    def __init__(self, clock, cost_s, ran_s=0.0, held=None, cpu_s=0.0):
        self.clock, self.cost_s, self.ran_s, self.held, self.cpu_s = clock, cost_s, ran_s, held, cpu_s
        self.calls, self.call_ids, self.cancelled = [], [], []
        self._released = False
        self._cond = threading.Condition()

    def __call__(self, request, call_id=0):
        with self._cond:
            self.calls.append(request)
            self.call_ids.append(call_id)
            holds = self.held is None or len(self.calls) <= self.held
            assert self._cond.wait_for(lambda: not holds or self._released or call_id in self.cancelled, 10), \
                "neither released nor cancelled"
            if call_id in self.cancelled:
                self.clock.advance(self.ran_s)
                return CANCELLED, {"side": self, "request": request, "cpu": self.cpu_s}
        self.clock.advance(self.cost_s)
        return OK, {"side": self, "request": request, "cpu": self.cpu_s}

    def cancel(self, call_id):
        with self._cond:
            self.cancelled.append(call_id)
            self._cond.notify_all()

    def release(self):
        with self._cond:
            self._released = True
            self._cond.notify_all()


class Recorder:
    def __init__(self):
        self.decisions, self.outcomes, self.routings = [], [], []

    def decision(self, routing):
        self.decisions.append((routing.request_id, routing.state, routing.decision, routing.probe))
        self.routings.append(routing)

    def outcome(self, outcome):
        self.outcomes.append(outcome)


def wired_router(policy, local, cloud, statuses, config=RouterConfig(), **router):
    """The router and its learner for `policy`, the learner's settings taken from `config` as the node does."""
    learner = OnlineLearner(policy, statuses, weights=config.weights, cloud_timeout_s=config.cloud_timeout_s,
                            latency_model=config.latency_model)
    return OffloadRouter(learner, local, cloud, statuses, config, **router)


def make_router(policy, local, cloud, clock, probe_rate=0.0, timeout_s=5.0):
    """Its probes run both sides at once (learning mode's and the link tests' way; deployed probes in turn are
    test_router_probes.py's)."""
    recorder = Recorder()
    router = wired_router(policy, local, cloud, STATUSES, RouterConfig(probe_rate=probe_rate, cloud_timeout_s=timeout_s,
                                                                       probe_while_warming_up=False,
                                                                       probe_after_delivery=False),
                          on_decision=recorder.decision, on_outcome=recorder.outcome, clock=clock)
    return router, recorder


def finish(router):
    # A liveness bound, not a timing: the learning behind a burst of routed requests (a gradient step per transition)
    # outlasted 10 s on a loaded machine (load average 4.5 on 2 cores).
    assert router.wait_idle(120)
    router.close()
