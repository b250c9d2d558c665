"""The router's two modes, the deadline hedge, the link breaker and the robot's cost accounting, with fake
planners on a virtual clock."""
import threading

import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.reward import reward
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal, Decision, DQNPolicy, Policy
from offload_learner_py.online.router_types import RouterConfig, Statuses
from offload_learner_py.core.state import State

OK, NO_PATH, TIMEOUT, ERROR = 0, 7, 9, 10
STATUSES = Statuses(ok=OK, cloud_timeout=TIMEOUT, cloud_error=ERROR)
STATE = State(1.2, 0.6, 0.05, 2e7)


from routertools import ERROR, OK, STATE, STATUSES, TIMEOUT, FakePlanner, Recorder, VirtualClock, finish, \
    make_router, wired_router


class LearningRecorder(Policy):
    """A fixed policy that records what it is taught."""
    name = "recorder"
    learns = True

    def __init__(self, action):
        self.action = action
        self.taught = []

    def choose(self, table):
        raise NotImplementedError

    def decide(self, state):
        return Decision(self.action, 1.0)

    def learn(self, state, action, reward_value):
        self.taught.append((action, reward_value))
        return None


def configured_router(policy, local, cloud, clock, **config):
    """Its probes run both sides at once unless told otherwise: counts of warm-up probes assume a probe's outcome
    is learned as soon as both fake sides answered (deployed probes in turn: test_router_probes.py)."""
    config.setdefault("probe_after_delivery", False)
    recorder = Recorder()
    router = wired_router(policy, local, cloud, STATUSES, RouterConfig(**config), on_decision=recorder.decision,
                         on_outcome=recorder.outcome, clock=clock)
    return router, recorder


def test_learning_mode_probes_every_request_and_teaches_both_actions():
    clock = VirtualClock()
    policy = LearningRecorder(CLOUD)
    router, recorder = configured_router(policy, FakePlanner(clock, 0.2), FakePlanner(clock, 0.08), clock,
                                         mode="learning", probe_rate=0.0)
    for _ in range(3):
        router.route("req", STATE)
        assert router.wait_idle(30)   # the caller has its path before the other side answers: one at a time
    finish(router)
    assert all(routing.probe for routing in recorder.routings)
    assert policy.taught == [(LOCAL, reward(LOCAL, 0.2, 0.08)), (CLOUD, reward(CLOUD, 0.2, 0.08))] * 3
    assert all(o.transitions == 2 and o.imputed is None for o in recorder.outcomes)


def test_learning_mode_dqn_acts_greedily():
    policy = DQNPolicy(agent=DQNAgent(DQNConfig(learning_starts=100)), explore=False)
    decisions = [policy.decide(STATE) for _ in range(50)]
    assert {d.propensity for d in decisions} == {1.0} and len({d.action for d in decisions}) == 1


class WarmingRecorder(LearningRecorder):
    """Warming up until it has been taught `warm_up` transitions, as an untrained DQN."""

    def __init__(self, action, warm_up):
        super().__init__(action)
        self.warm_up = warm_up

    @property
    def warming_up(self):
        return len(self.taught) < self.warm_up


def test_deployed_mode_probes_while_warming_up_then_a_share_and_imputes_the_other_side():
    clock = VirtualClock()
    policy = WarmingRecorder(LOCAL, warm_up=2 * 20)   # two transitions per probe: 20 probes
    local, cloud = FakePlanner(clock, 0.2), FakePlanner(clock, 0.05)
    router, recorder = configured_router(policy, local, cloud, clock, mode="deployed", probe_rate=0.1)
    for _ in range(400):
        router.route("req", STATE)
    finish(router)
    probes = [r.probe for r in recorder.routings]
    min_samples = router.config.latency_model.min_samples
    assert all(probes[:min_samples])             # both latency models need their first samples
    later = probes[min_samples:]
    assert 0.05 < sum(later) / len(later) < 0.2  # then about probe_rate
    single = [o for o in recorder.outcomes if not o.probe]
    assert single and all(o.cloud is None and o.imputed == CLOUD and o.transitions == 2 for o in single)
    # the imputed cloud latency is the model's (the fake is deterministic, so it learned 0.05 s)
    imputed = [r for a, r in policy.taught if a == CLOUD]
    assert imputed == pytest.approx([reward(CLOUD, 0.2, 0.05)] * len(imputed), abs=1e-3)
    assert len(cloud.calls) == sum(probes)       # the cloud was called on probes only


def test_a_deployed_fixed_policy_never_probes_beyond_its_rate():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.2), FakePlanner(clock, 0.05)
    router, recorder = configured_router(AlwaysLocal("local"), local, cloud, clock, mode="deployed",
                                         probe_rate=0.0)
    for _ in range(30):
        router.route("req", STATE)
    finish(router)
    assert not any(r.probe for r in recorder.routings) and not cloud.calls


def test_deployed_request_before_the_models_are_ready_teaches_nothing():
    clock = VirtualClock()
    policy = LearningRecorder(LOCAL)
    router, recorder = configured_router(policy, FakePlanner(clock, 0.2), FakePlanner(clock, 0.05), clock,
                                         mode="deployed", probe_rate=0.0, probe_while_warming_up=False)
    router.route("req", STATE)
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.reward is None and not outcome.learned and policy.taught == []


def test_hedge_starts_the_other_side_when_the_chosen_one_misses_its_deadline():
    clock = VirtualClock()
    gate = threading.Event()
    local, cloud = FakePlanner(clock, 0.15), FakePlanner(clock, 0.4, gate=gate)
    policy = LearningRecorder(CLOUD)
    router, recorder = configured_router(policy, local, cloud, clock, probe_rate=0.0, probe_while_warming_up=False,
                                         hedge=True, hedge_deadline_s=0.01)
    result = router.route("req", STATE)          # the cloud never answers until the gate opens
    assert result.response["side"] is local
    gate.set()
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.hedged and outcome.delivered == LOCAL and recorder.routings[0].deadline_s == 0.01
    # both sides ran in the end, so both latencies are measured and both actions are taught
    assert outcome.local_s == pytest.approx(0.15) and outcome.cloud_s == pytest.approx(0.4)
    assert outcome.transitions == 2 and outcome.imputed is None


def test_hedge_starts_the_other_side_at_once_when_the_chosen_one_is_still_busy():
    """The planner cannot be interrupted: a request whose side is still planning an earlier request's path
    would wait for it, so the hedge does not wait for a deadline."""
    clock = VirtualClock()
    gate = threading.Event()
    local, cloud = FakePlanner(clock, 0.3, gate=gate), FakePlanner(clock, 0.05)
    router, recorder = configured_router(AlwaysLocal("local"), local, cloud, clock, probe_rate=0.0,
                                         probe_while_warming_up=False, hedge=True, hedge_deadline_s=10.0)
    first = threading.Thread(target=router.route, args=("first", STATE))
    first.start()
    while not router._lanes[LOCAL].busy():
        threading.Event().wait(0.001)
    second = router.route("second", STATE)      # the local planner is still on the first request
    assert second.response["side"] is cloud and recorder.routings[1].deadline_s == 0.0
    gate.set()
    first.join(10)
    finish(router)
    assert recorder.routings[0].deadline_s == 10.0


def test_no_hedge_when_the_chosen_side_answers_in_time():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.15), FakePlanner(clock, 0.05)
    router, recorder = configured_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0,
                                         probe_while_warming_up=False, hedge=True, hedge_deadline_s=5.0)
    router.route("req", STATE)
    finish(router)
    assert not recorder.outcomes[0].hedged and not local.calls


def test_hedge_deadline_follows_the_latency_model_within_its_bounds():
    clock = VirtualClock()
    router, _ = configured_router(AlwaysCloud("cloud"), FakePlanner(clock, 0.1), FakePlanner(clock, 0.1),
                                  clock, hedge=True, hedge_min_s=0.02, hedge_max_s=0.9)
    assert router.hedge.deadline_s(CLOUD, STATE) == 0.9          # no model yet: the upper bound
    for k in range(60):
        router.models[CLOUD].observe((1.2, 0.6, 0.05), 0.1 * (1.0 + 0.05 * (k % 3 - 1)))
    assert 0.1 < router.hedge.deadline_s(CLOUD, STATE) < 0.3      # a high quantile of about 0.1 s


def test_breaker_opens_after_cloud_failures_and_routes_locally_without_calling_the_cloud():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.1), FakePlanner(clock, 5.0, status=TIMEOUT)
    router, recorder = configured_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0,
                                         probe_while_warming_up=False)
    router.breaker.clock = lambda: 0.0          # no trial falls due
    for _ in range(6):
        assert router.route("req", STATE).response["side"] is local
    finish(router)
    failures = router.config.breaker.failures_to_open
    assert len(cloud.calls) == failures
    assert [r.breaker for r in recorder.routings] == ["closed"] * failures + ["open"] * (6 - failures)
    assert all(r.action == LOCAL and r.decision.action == CLOUD for r in recorder.routings[failures:])
    router.breaker.record_heartbeat(True, 0.05)  # a ping alone says nothing of the calls that timed out
    assert router.breaker.is_open
    router.breaker.record_heartbeat(False, 5.0)  # the link was down, then a ping says it is back
    router.breaker.record_heartbeat(True, 0.05)
    router.route("req", STATE)
    finish(router)
    assert recorder.routings[-1].breaker == "closed" and len(cloud.calls) == failures + 1


def test_breaker_trial_is_a_probe_and_a_cloud_answer_closes_it():
    clock = VirtualClock()
    now = [0.0]
    local, cloud = FakePlanner(clock, 0.1), FakePlanner(clock, 0.05)
    router, recorder = configured_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0,
                                         probe_while_warming_up=False)
    router.breaker.clock = lambda: now[0]
    router.breaker.record_heartbeat(False, 5.0)
    router.route("req", STATE)
    now[0] = 100.0
    router.route("req", STATE)
    assert router.wait_idle(30)   # the trial's cloud answer is in (the caller has its path before it may be)
    router.route("req", STATE)
    finish(router)
    assert [(r.breaker, r.probe) for r in recorder.routings] == [("open", False), ("trial", True), ("closed", False)]


def test_cost_accounting_sums_every_side_called():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.2), FakePlanner(clock, 0.05)
    costs = {id(local): (0.18, 0, 0), id(cloud): (0.004, 1200, 800)}
    router = wired_router(AlwaysLocal("local"), local, cloud, STATUSES, RouterConfig(mode="learning"),
                         clock=clock, account=lambda response: costs[id(response["side"])])
    outcomes = []
    router.on_outcome = outcomes.append
    router.route("req", STATE)
    finish(router)
    (outcome,) = outcomes
    assert outcome.robot_cpu_s == pytest.approx(0.18) and outcome.bridge_cpu_s == pytest.approx(0.004)
    assert (outcome.bytes_sent, outcome.bytes_received) == (1200, 800)


class SharedClock:
    """One time for every thread (a single side runs here, so it stays deterministic)."""

    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now

    def advance(self, seconds):
        self.now += seconds


def test_delivered_latency_runs_from_the_arrival_of_the_request():
    clock = SharedClock()
    router, recorder = make_router(AlwaysLocal("local"), FakePlanner(clock, 0.2), FakePlanner(clock, 0.1),
                                   clock)
    clock.advance(1.0)
    router.route("req", STATE, arrived=0.25)     # it waited 0.75 s before routing
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.delivered_s == pytest.approx(0.75 + 0.2) and outcome.local_s == pytest.approx(0.2)


def test_router_config_rejects_bad_modes_and_hedges():
    for kwargs, message in (({"mode": "greedy"}, "mode"), ({"hedge_quantile": 1.0}, "hedge_quantile"),
                            ({"hedge_min_s": 0.0}, "hedge_min_s"), ({"hedge_deadline_s": -1.0}, "hedge_deadline_s")):
        with pytest.raises(ValueError, match=message):
            RouterConfig(**kwargs)


def test_a_long_local_plan_is_hedged_once_the_clouds_median_has_passed():
    """A local plan slower than the cloud usually is: the cloud starts once it would have been done. A cloud
    call is never hedged that early: a local plan cannot be interrupted."""
    clock = VirtualClock()
    router, _ = configured_router(AlwaysLocal("local"), FakePlanner(clock, 0.1), FakePlanner(clock, 0.1),
                                  clock, hedge=True, hedge_min_s=0.02, hedge_max_s=0.9)
    for k in range(60):
        router.models[LOCAL].observe((1.2, 0.6, 0.05), 0.5 * (1.0 + 0.3 * (k % 3 - 1)))   # local slow, noisy
        router.models[CLOUD].observe((1.2, 0.6, 0.05), 0.12 * (1.0 + 0.3 * (k % 3 - 1)))
    assert router.hedge.deadline_s(LOCAL, STATE) == pytest.approx(0.12, rel=0.05)
    assert router.hedge.deadline_s(CLOUD, STATE) == pytest.approx(router.models[CLOUD].quantile_s((1.2, 0.6, 0.05), 0.95))
    assert router.hedge.deadline_s(CLOUD, STATE) > 0.12


def test_a_warm_started_policy_probes_until_both_latency_models_are_ready():
    """A trained DQN on a fresh node: no latency model has samples, so one-sided requests would teach nothing
    and the hedge would wait its maximum; it probes until both models are ready, then at its rate."""
    clock = VirtualClock()
    policy = LearningRecorder(CLOUD)           # learns, never warming up
    router, recorder = configured_router(policy, FakePlanner(clock, 0.2), FakePlanner(clock, 0.05), clock,
                                         mode="deployed", probe_rate=0.0)
    for _ in range(40):
        router.route("req", STATE)
        assert router.wait_idle(30)   # each request learned before the next (the caller has its path first)
    finish(router)
    probes = [r.probe for r in recorder.routings]
    min_samples = router.config.latency_model.min_samples
    assert all(probes[:min_samples]) and not any(probes[min_samples:])
    assert all(o.learned for o in recorder.outcomes)


def test_hedge_keeps_a_cloud_choice_local_when_the_round_trip_alone_exceeds_the_local_plans_quantile():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.1), FakePlanner(clock, 0.05)
    routers = {}
    for hedge in (True, False):
        router, recorder = configured_router(AlwaysCloud("cloud"), local, cloud, clock, hedge=hedge,
                                             probe_rate=0.0, probe_while_warming_up=False)
        for k in range(90):      # the local plan takes 0.1 s whatever the link does
            router.models[LOCAL].observe((1.2, 0.6, (0.01, 0.1, 0.6)[k % 3]), 0.1 * (1.0 + 0.05 * (k % 5 - 2)))
        routers[hedge] = router, recorder
    router, recorder = routers[True]
    calls = len(cloud.calls)
    router.route("req", State(1.2, 0.6, 0.02, 2e7))       # a fast link: the cloud as chosen
    router.route("req", State(1.2, 0.6, 0.5, 2e7))        # 0.5 s of round trip against a 0.1 s local plan
    finish(router)
    assert [(r.action, r.breaker, r.decision.action) for r in recorder.routings] == [
        (CLOUD, "closed", CLOUD), (LOCAL, "slow", CLOUD)]
    assert len(cloud.calls) == calls + 1 and recorder.outcomes[-1].delivered == LOCAL
    router, recorder = routers[False]                # without the hedge the policy's choice stands
    router.route("req", State(1.2, 0.6, 0.5, 2e7))
    finish(router)
    assert [(r.action, r.breaker) for r in recorder.routings] == [(CLOUD, "closed")]


class BusyLearner(LearningRecorder):
    """Spends `cpu_s` of its own thread's CPU on every transition, as a gradient step does."""

    def __init__(self, action, cpu_s):
        super().__init__(action)
        self.cpu_s = cpu_s

    def learn(self, state, action, reward_value):
        import time
        began = time.thread_time()
        while time.thread_time() - began < self.cpu_s:
            pass
        return super().learn(state, action, reward_value)


def test_the_learners_own_cpu_for_a_request_is_accounted():
    clock = VirtualClock()
    for policy, low, high in ((BusyLearner(LOCAL, 0.02), 0.04, 1.0), (AlwaysLocal("local"), 0.0, 0.01)):
        router, recorder = configured_router(policy, FakePlanner(clock, 0.2), FakePlanner(clock, 0.05), clock,
                                             mode="learning")
        router.route("req", STATE)
        finish(router)
        (outcome,) = recorder.outcomes
        assert low <= outcome.learner_cpu_s < high, (policy.name, outcome.learner_cpu_s)   # two transitions


def test_a_cloud_refusal_is_checked_locally_and_a_lying_one_counts_as_a_cloud_failure():
    """#31 Medium 5: in deployed mode a cloud's NO_PATH was delivered as final: against a cloud that always
    says NO_PATH, 192 of 200 requests got no path and the breaker never tripped. The local planner checks a
    refusal; its path is delivered, and the cloud's answer is a cloud failure (the breaker, the learner)."""
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.1), FakePlanner(clock, 0.02, status=NO_PATH)
    router, recorder = configured_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0,
                                         probe_while_warming_up=False)
    router.breaker.clock = lambda: 0.0          # no trial falls due
    for _ in range(5):
        delivered = router.route("req", STATE)
        assert delivered.status == OK and delivered.response["side"] is local
        assert router.wait_idle(30)   # the refusal's verdict is in before the next request
    finish(router)
    failures = router.config.breaker.failures_to_open
    assert len(cloud.calls) == failures, "the lying cloud was not taken out of service"
    lied = [o for o in recorder.outcomes if o.cloud is not None]
    assert len(lied) == failures and all(o.cloud.status == ERROR and "contradicted" in o.cloud.raised for o in lied)


def test_a_refusal_the_local_planner_agrees_with_is_delivered_and_is_no_failure():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.1, status=NO_PATH), FakePlanner(clock, 0.02, status=NO_PATH)
    router, recorder = configured_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=0.0,
                                         probe_while_warming_up=False)
    for _ in range(5):
        assert router.route("req", STATE).status == NO_PATH
    finish(router)
    assert len(cloud.calls) == 5 and not router.breaker.is_open
    assert all(o.cloud.status == NO_PATH for o in recorder.outcomes)
