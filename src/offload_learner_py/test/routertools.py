"""Fakes for the router's tests: planners with scripted costs on a per-thread virtual clock (no sleeps, no
timing assertions), a recorder of what the router publishes, and the router built around them."""
import threading


from offload_learner_py.online.router import OffloadRouter
from offload_learner_py.online.routing import RouterConfig, Statuses
from offload_learner_py.core.state import State

OK, NO_PATH, TIMEOUT, ERROR = 0, 7, 9, 10
STATUSES = Statuses(ok=OK, cloud_timeout=TIMEOUT, cloud_error=ERROR)
STATE = State(1.2, 0.6, 0.05)


class VirtualClock:
    """Each thread has its own time; a fake planner advances the calling thread's time by its cost."""

    def __init__(self):
        self.local = threading.local()

    def __call__(self):
        return getattr(self.local, "now", 0.0)

    def advance(self, seconds):
        self.local.now = self() + seconds


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


class Recorder:
    def __init__(self):
        self.decisions, self.outcomes, self.routings = [], [], []

    def decision(self, routing):
        self.decisions.append((routing.request_id, routing.state, routing.decision, routing.probe))
        self.routings.append(routing)

    def outcome(self, outcome):
        self.outcomes.append(outcome)


def make_router(policy, local, cloud, clock, probe_rate=0.0, timeout_s=5.0):
    recorder = Recorder()
    router = OffloadRouter(policy, local, cloud, STATUSES, RouterConfig(probe_rate=probe_rate, cloud_timeout_s=timeout_s,
                                                                            probe_while_warming_up=False),
                           on_decision=recorder.decision, on_outcome=recorder.outcome, clock=clock)
    return router, recorder


def finish(router):
    assert router.wait_idle(10)
    router.close()
