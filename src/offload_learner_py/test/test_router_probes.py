"""A deployed probe runs its sides in turn: the caller waits for the chosen side alone and the other side is
measured after it, not beside it on the robot's CPU. Learning mode's probes and the breaker's link tests still
run both sides at once. Fake planners on a virtual clock; the order of calls is what is checked."""
import threading

from pytest import approx

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal
from offload_learner_py.online.router_types import RouterConfig

from routertools import ERROR, OK, STATE, STATUSES, FakePlanner, Recorder, VirtualClock, finish, wired_router

# How long the first side waits for the other to start before it answers: long enough for a worker thread to
# start it when the router runs both at once; in turn, the other starts only after this wait.
OVERLAP_WAIT_S = 0.5


class Journal:
    """Starts and ends of the fake planners' calls, in the order they happened."""

    def __init__(self):
        self.events, self.lock = [], threading.Lock()
        self.started = {LOCAL: threading.Event(), CLOUD: threading.Event()}

    def log(self, event):
        with self.lock:
            self.events.append(event)
        if event[0] == "start":
            self.started[event[1]].set()

    def index(self, event):
        return self.events.index(event)


class JournalPlanner(FakePlanner):
    def __init__(self, journal, side, clock, cost_s, status=OK, waits=False):
        super().__init__(clock, cost_s, status)
        self.journal, self.side, self.waits = journal, side, waits

    def __call__(self, request):
        self.journal.log(("start", self.side))
        if self.waits:   # still running when the router would start the other side beside it
            self.journal.started[CLOUD if self.side == LOCAL else LOCAL].wait(OVERLAP_WAIT_S)
        try:
            return super().__call__(request)
        finally:
            self.journal.log(("end", self.side))


def probe_once(policy, config, local_status=OK, cloud_status=OK):
    clock, journal, recorder = VirtualClock(), Journal(), Recorder()
    local = JournalPlanner(journal, LOCAL, clock, 0.1, local_status, waits=True)
    cloud = JournalPlanner(journal, CLOUD, clock, 0.05, cloud_status)
    router = wired_router(policy, local, cloud, STATUSES, config, on_decision=recorder.decision,
                          on_outcome=recorder.outcome, clock=clock)
    router.route("req", STATE)
    finish(router)
    assert recorder.routings[0].probe
    return journal, recorder.outcomes[0], local, cloud


DEPLOYED_PROBE = RouterConfig(mode="deployed", probe_rate=1.0, probe_while_warming_up=False)


def test_a_deployed_probe_measures_the_cloud_after_the_chosen_local_plan_answered():
    journal, outcome, local, cloud = probe_once(AlwaysLocal("local"), DEPLOYED_PROBE)
    assert journal.index(("end", LOCAL)) < journal.index(("start", CLOUD))
    assert outcome.delivered == LOCAL and outcome.delivered_s == approx(0.1)   # the local side's cost alone
    assert outcome.local.status == OK and outcome.cloud.status == OK   # both sides measured: a full-information row
    assert outcome.cloud.seconds == approx(0.05) and outcome.cloud.started_after_s == approx(0.1)
    assert outcome.local_s == approx(0.1) and outcome.cloud_s == approx(0.05)   # the learner has both


def test_a_deployed_probe_plans_locally_after_the_chosen_cloud_answered():
    journal, outcome, local, cloud = probe_once(AlwaysCloud("cloud"), DEPLOYED_PROBE)
    assert journal.index(("end", CLOUD)) < journal.index(("start", LOCAL))
    assert outcome.delivered == CLOUD and outcome.delivered_s == approx(0.05)
    assert outcome.local.status == OK and outcome.local_s == approx(0.1)


def test_a_probe_whose_chosen_cloud_failed_gets_its_path_from_the_local_side_it_runs_next():
    journal, outcome, local, cloud = probe_once(AlwaysCloud("cloud"), DEPLOYED_PROBE, cloud_status=ERROR)
    assert outcome.delivered == LOCAL and len(local.calls) == 1 and len(cloud.calls) == 1
    assert outcome.delivered_s == approx(0.05 + 0.1)   # the failed cloud call, then the local plan
    assert outcome.cloud.status == ERROR


def test_learning_mode_probes_run_both_sides_at_once():
    journal, outcome, _, _ = probe_once(AlwaysLocal("local"), RouterConfig(mode="learning"))
    assert journal.index(("start", CLOUD)) < journal.index(("end", LOCAL))
    assert outcome.cloud.started_after_s == 0.0


def test_a_deployed_probe_runs_both_sides_at_once_when_told_to():
    config = RouterConfig(mode="deployed", probe_rate=1.0, probe_while_warming_up=False, probe_after_delivery=False)
    journal, _, _, _ = probe_once(AlwaysLocal("local"), config)
    assert journal.index(("start", CLOUD)) < journal.index(("end", LOCAL))


def test_the_breakers_link_test_runs_both_sides_at_once():
    """A trial of a link the breaker opened is a probe where the caller gets the local path at worst: the local
    plan cannot wait for a cloud that may still be down."""
    clock, journal, recorder = VirtualClock(), Journal(), Recorder()
    local = JournalPlanner(journal, LOCAL, clock, 0.1)
    cloud = JournalPlanner(journal, CLOUD, clock, 0.05, waits=True)   # the cloud chosen, called first
    now = [0.0]
    router = wired_router(AlwaysCloud("cloud"), local, cloud, STATUSES,
                          RouterConfig(mode="deployed", probe_rate=0.0, probe_while_warming_up=False),
                          on_decision=recorder.decision, on_outcome=recorder.outcome, clock=clock)
    router.breaker.clock = lambda: now[0]
    router.breaker.record_heartbeat(False, 5.0)
    now[0] = 100.0
    router.route("req", STATE)
    finish(router)
    assert recorder.routings[0].breaker == "trial" and recorder.routings[0].probe
    assert journal.index(("start", LOCAL)) < journal.index(("end", CLOUD))
