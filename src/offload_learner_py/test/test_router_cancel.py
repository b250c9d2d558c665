"""Cancelling the local planner's abandoned calls, and the cloud side serving calls concurrently: the slower
side of an earlier request never holds up the next one, its CPU is still accounted, and a cancelled plan's
running time teaches the learner only as the lower bound it is."""
import threading

import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal
from offload_learner_py.core.reward import reward
from offload_learner_py.online.router import OffloadRouter
from offload_learner_py.online.routing import RouterConfig
from routertools import CANCELLABLE, CANCELLED, OK, STATE, CancellablePlanner, FakePlanner, Recorder, \
    VirtualClock, finish


def router_for(policy, local, cloud, clock, **config):
    recorder = Recorder()
    config.setdefault("probe_while_warming_up", False)
    router = OffloadRouter(policy, local, cloud, CANCELLABLE, RouterConfig(**config), on_decision=recorder.decision,
                           on_outcome=recorder.outcome, clock=clock,
                           account=lambda response: (response.get("cpu", 0.0), 0, 0))
    return router, recorder


def test_a_newer_request_cancels_the_local_plan_of_a_request_already_served():
    """A probe's local plan still runs after the cloud served it; the next probe cancels it instead of waiting
    behind it. The cancelled plan's CPU counts for the request that started it, its latency is not measured."""
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.3, ran_s=0.12, held=1, cpu_s=0.02), FakePlanner(clock, 0.1)
    router, recorder = router_for(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=1.0)
    assert router.route("first", STATE).response["side"] is cloud     # its local plan is still running
    router.route("second", STATE)
    assert local.cancelled == [local.call_ids[0]], "the first request's local plan was cancelled"
    finish(router)
    first, later = sorted(recorder.outcomes, key=lambda o: o.request_id)
    assert first.local is None and first.local_s is None                 # cancelled: not a measurement
    assert first.robot_cpu_s == pytest.approx(0.02)                       # but its CPU was spent
    assert first.local_lower_bound_s == pytest.approx(0.12)
    assert later.local_s == pytest.approx(0.3) and later.local_lower_bound_s is None
    assert len(set(local.call_ids)) == 2 and all(local.call_ids), "each call has its own non-zero id"


def test_a_local_plan_someone_still_waits_for_is_never_cancelled():
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.3, held=1), FakePlanner(clock, 0.05)
    router, recorder = router_for(AlwaysLocal("local"), local, cloud, clock, probe_rate=0.0)
    first = threading.Thread(target=router.route, args=("first", STATE))
    first.start()
    while not local.calls:
        threading.Event().wait(0.001)
    second = threading.Thread(target=router.route, args=("second", STATE))
    second.start()
    threading.Event().wait(0.05)
    assert not local.cancelled
    local.release()
    first.join(10)
    second.join(10)
    finish(router)
    assert [o.local_s for o in sorted(recorder.outcomes, key=lambda o: o.request_id)] == [0.3, 0.3]


def test_cloud_calls_run_concurrently_so_a_slow_one_holds_up_nobody():
    """The first request's cloud call hangs; the second request's cloud call is answered meanwhile."""
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.05), CancellablePlanner(clock, 0.08, held=1)
    router, recorder = router_for(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0)
    first = threading.Thread(target=router.route, args=("first", STATE))
    first.start()
    while not cloud.calls:
        threading.Event().wait(0.001)
    assert router.route("second", STATE).response["request"] == "second"   # while the first still hangs
    assert first.is_alive() and not cloud.cancelled and not local.calls
    cloud.release()
    first.join(10)
    finish(router)
    assert len(cloud.calls) == 2


def test_a_cancelled_local_plan_that_had_outrun_the_cloud_teaches_its_lower_bound():
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.5, ran_s=0.25, held=1), FakePlanner(clock, 0.1)
    policy = _Recording(CLOUD)
    router, recorder = router_for(policy, local, cloud, clock, probe_rate=1.0)
    router.route("first", STATE)
    router.route("second", STATE)
    finish(router)
    first = min(recorder.outcomes, key=lambda o: o.request_id)
    assert first.imputed == LOCAL and first.transitions == 2
    assert first.reward == pytest.approx(reward(CLOUD, 0.25, 0.1))
    assert (LOCAL, pytest.approx(reward(LOCAL, 0.25, 0.1))) in policy.taught


def test_a_cancelled_local_plan_shorter_than_the_cloud_teaches_nothing_about_local():
    """Cancelled after 0.05 s while the cloud took 0.1 s: the local plan might have won, the bound says
    nothing about which side was better, so with no model to impute from nothing is learned."""
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.5, ran_s=0.05, held=1), FakePlanner(clock, 0.1)
    policy = _Recording(CLOUD)
    router, recorder = router_for(policy, local, cloud, clock, probe_rate=1.0)
    router.route("first", STATE)
    router.route("second", STATE)
    finish(router)
    first = min(recorder.outcomes, key=lambda o: o.request_id)
    assert first.local_lower_bound_s == pytest.approx(0.05)
    assert first.reward is None and first.transitions == 0


class _Recording(AlwaysCloud):
    learns = True

    def __init__(self, action):
        super().__init__("recording")
        self.taught = []

    def learn(self, state, action, reward_value):
        self.taught.append((action, reward_value))
        return None


def test_without_a_cancelled_status_the_sides_are_called_as_before():
    """Sides without cancel() get no call id (the fakes of every other test, a planner that cannot cancel)."""
    clock = VirtualClock()
    calls = []

    def plain(request):
        calls.append(request)
        clock.advance(0.01)
        return OK, {}

    router, _ = router_for(AlwaysLocal("local"), plain, FakePlanner(clock, 0.1), clock)
    router.route("req", STATE)
    finish(router)
    assert calls == ["req"] and CANCELLED != OK
