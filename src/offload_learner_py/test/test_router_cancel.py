"""Cancelling the local planner's abandoned calls, and the cloud side serving calls concurrently: the slower
side of an earlier request never holds up the next one, its CPU is still accounted, and a cancelled plan's
running time teaches the learner only as the lower bound it is."""
import dataclasses
import threading

import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal
from offload_learner_py.core.reward import reward
from offload_learner_py.online.router_types import RouterConfig
from routertools import CANCELLABLE, CANCELLED, OK, STATE, CancellablePlanner, FakePlanner, Recorder, \
    VirtualClock, finish, wired_router


def router_for(policy, local, cloud, clock, **config):
    """Its probes run both sides at once, so a probe's local plan is running when the next request cancels it
    (a deployed probe in turn starts its other side only after the first answered: test_router_probes.py)."""
    recorder = Recorder()
    config.setdefault("probe_while_warming_up", False)
    config.setdefault("probe_after_delivery", False)
    router = wired_router(policy, local, cloud, CANCELLABLE, RouterConfig(**config), on_decision=recorder.decision,
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


def first_of_two_probes(local_ran_s):
    """Two probes; the first one's local plan (0.5 s) is cancelled by the second after `local_ran_s`, while its
    cloud side took 0.1 s. The first outcome and what the policy was taught."""
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.5, ran_s=local_ran_s, held=1), FakePlanner(clock, 0.1)
    policy = _Recording(CLOUD)
    router, recorder = router_for(policy, local, cloud, clock, probe_rate=1.0)
    router.route("first", STATE)
    router.route("second", STATE)
    finish(router)
    return min(recorder.outcomes, key=lambda o: o.request_id), policy


def test_a_cancelled_local_plan_that_had_outrun_the_cloud_teaches_its_lower_bound():
    first, policy = first_of_two_probes(0.25)
    assert first.imputed == LOCAL and first.transitions == 2
    assert first.reward == pytest.approx(reward(CLOUD, 0.25, 0.1))
    assert (LOCAL, pytest.approx(reward(LOCAL, 0.25, 0.1))) in policy.taught


def test_a_cancelled_local_plan_shorter_than_the_cloud_teaches_nothing_about_local():
    """Cancelled after 0.05 s while the cloud took 0.1 s: the local plan might have won, the bound says
    nothing about which side was better, so with no model to impute from nothing is learned."""
    first, _ = first_of_two_probes(0.05)
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


def test_a_hedges_local_plan_is_cancelled_as_soon_as_the_cloud_delivers():
    """Deployed, cloud chosen, hedged into the local planner: when the late cloud answer comes first the local
    plan is cancelled at once (it frees the robot's CPU); a probe's local side is kept (it is a measurement)."""
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.5, ran_s=0.05, held=1), CancellablePlanner(clock, 0.2, held=1)
    router, recorder = router_for(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0, hedge=True,
                                  hedge_deadline_s=0.01)
    caller = threading.Thread(target=router.route, args=("req", STATE))
    caller.start()
    while not local.calls:                  # the deadline passed: the local planner was hedged into
        threading.Event().wait(0.001)
    cloud.release()                         # the cloud answers first
    caller.join(10)
    assert router.wait_idle(10)
    assert local.cancelled == local.call_ids[:1], "the hedge's local plan was cancelled when the cloud delivered"
    (outcome,) = recorder.outcomes
    assert outcome.hedged and outcome.delivered == CLOUD and outcome.local is None


def test_the_local_planner_is_not_hedged_into_when_it_cannot_win_until_hedge_max():
    """The local latency model says about 0.9 s for this state, the cloud's 95th percentile is about 0.3 s: a
    local plan started at the deadline would only burn the robot's CPU, so it is not; but by hedge_max_s the
    cloud call is as good as failed (a dead link the breaker has not caught yet), and the local plan starts."""
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.9), CancellablePlanner(clock, 0.4, held=1)
    router, recorder = router_for(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0, hedge=True,
                                  hedge_deadline_s=0.05, hedge_max_s=2.0)
    for k in range(60):
        router.models[LOCAL].observe((1.2, 0.6, 0.05), 0.9 + 0.01 * (k % 3))
        router.models[CLOUD].observe((1.2, 0.6, 0.05), 0.3 + 0.01 * (k % 3))
    caller = threading.Thread(target=router.route, args=("req", STATE))
    caller.start()
    threading.Event().wait(0.2)             # well past the deadline, well before hedge_max_s
    assert not local.calls
    caller.join(10)                         # the local plan starts at hedge_max_s and serves the request
    assert local.calls == ["req"]
    cloud.release()
    finish(router)
    assert recorder.outcomes[0].hedged and recorder.outcomes[0].delivered == LOCAL


def test_the_local_planner_is_hedged_into_when_it_can_win():
    clock = VirtualClock()
    # (a local plan slower than the round trip: a faster one would keep the cloud choice local from the start)
    # hedge_max_s far away: the local plan must start at the deadline because it can win, not at hedge_max_s
    router, recorder = router_for(AlwaysCloud("cloud"), FakePlanner(clock, 0.08), CancellablePlanner(clock, 0.4, held=1),
                                  clock, probe_rate=0.0, hedge=True, hedge_deadline_s=0.05, hedge_max_s=60.0)
    for k in range(60):
        router.models[LOCAL].observe((1.2, 0.6, 0.05), 0.08)
        router.models[CLOUD].observe((1.2, 0.6, 0.05), 0.3 + 0.01 * (k % 3))
    answers = []
    caller = threading.Thread(target=lambda: answers.append(router.route("req", STATE)), daemon=True)
    caller.start()
    caller.join(20)
    assert answers and answers[0].response["request"] == "req", "the local plan waited for hedge_max_s"
    router.sides[CLOUD].release()
    finish(router)
    assert recorder.outcomes[0].hedged and recorder.outcomes[0].delivered == LOCAL


def test_a_late_cloud_call_is_hedged_once_the_local_plan_would_have_finished():
    clock = VirtualClock()
    router, _ = router_for(AlwaysCloud("cloud"), FakePlanner(clock, 0.1), FakePlanner(clock, 0.1), clock,
                           hedge=True, hedge_min_s=0.02, hedge_max_s=0.9)
    for k in range(60):
        router.models[CLOUD].observe((1.2, 0.6, 0.05), 0.1 * (1.0 + 0.5 * (k % 3 - 1)))
    assert router.hedge.deadline_s(CLOUD, STATE) > 0.12                 # the cloud's own 95th percentile
    for k in range(60):
        router.models[LOCAL].observe((1.2, 0.6, 0.05), 0.08)
    assert router.hedge.deadline_s(CLOUD, STATE) == pytest.approx(router.models[CLOUD].impute_s((1.2, 0.6, 0.05)))
    # (never before the cloud's own median, though the local median is lower)


def test_a_hedges_local_plan_still_queued_when_the_cloud_delivers_never_starts():
    """The first request (local, no deadline reached) holds the local planner; the second (cloud) is hedged into
    it and waits in line. The cloud delivers the second request first: its local plan then never starts."""
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.3, held=1), _GatedPerRequest(clock, 0.1)
    router, recorder = router_for(_Alternating(), local, cloud, clock, probe_rate=0.0, hedge=True,
                                  hedge_deadline_s=0.01)
    first = threading.Thread(target=router.route, args=("first", STATE))
    first.start()
    while not local.calls or "first" not in cloud.calls:   # local running, its hedged cloud call held
        threading.Event().wait(0.001)
    second = threading.Thread(target=router.route, args=("second", STATE))
    second.start()
    while "second" not in cloud.calls:
        threading.Event().wait(0.001)
    threading.Event().wait(0.05)                            # the second's hedge is queued behind the first
    cloud.release("second")
    second.join(10)
    local.release()
    cloud.release("first")
    first.join(10)
    finish(router)
    assert local.calls == ["first"], "the second request's local plan never started: its caller had the cloud path"


class _GatedPerRequest:
    """A cloud whose answer to each request waits until that request is released."""

    def __init__(self, clock, cost_s):
        self.clock, self.cost_s, self.calls, self.gates = clock, cost_s, [], {}

    def __call__(self, request):
        gate = self.gates.setdefault(request, threading.Event())
        self.calls.append(request)
        assert gate.wait(10)
        self.clock.advance(self.cost_s)
        return OK, {"side": self, "request": request}

    def release(self, request):
        self.gates.setdefault(request, threading.Event()).set()


class _Alternating(AlwaysCloud):
    """Local for the first request, then cloud."""

    def __init__(self):
        super().__init__("alternating")
        self.count = 0

    def decide(self, state):
        decision = super().decide(state)
        self.count += 1
        return dataclasses.replace(decision, action=LOCAL) if self.count == 1 else decision


def test_a_probes_slower_local_side_is_measured_when_the_cloud_answers_first():
    """A probe is there to measure both sides: when the cloud delivers first, its local plan runs on to the end
    (only a newer request may cancel it), so l_local is measured (#31: a mutant cancelling it at the cloud's
    answer survived, and with it every probe's local latency)."""
    clock = VirtualClock()
    local, cloud = CancellablePlanner(clock, 0.3, held=1), FakePlanner(clock, 0.1)
    router, recorder = router_for(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=1.0)
    assert router.route("only", STATE).response["side"] is cloud
    threading.Event().wait(0.05)
    assert not local.cancelled, "the probe's local plan was cancelled when the cloud answered"
    local.release()
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.local_s == pytest.approx(0.3) and outcome.cloud_s == pytest.approx(0.1)
    assert outcome.reward == pytest.approx(reward(CLOUD, 0.3, 0.1))
