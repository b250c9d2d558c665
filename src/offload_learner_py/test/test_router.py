"""The online router without ROS: fake planners with scripted costs on a per-thread virtual clock (no
sleeps, no timing assertions), every routing path, eq. 10 on probe steps, fallback and learning."""
import threading

import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.reward import CostWeights, reward
from offload_learner_py.core.policies import AlwaysCloud, AlwaysLocal, Decision, DQNPolicy, InputSizeThreshold, \
    Policy, RandomPolicy
from offload_learner_py.data.records import NO_PATH_DELIVERED
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


def test_local_decision_calls_only_the_local_planner():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.120), FakePlanner(clock, 0.050)
    router, recorder = make_router(AlwaysLocal("local"), local, cloud, clock)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == OK and result.response["side"] is local
    assert len(local.calls) == 1 and not cloud.calls
    (outcome,) = recorder.outcomes
    assert outcome.delivered == LOCAL and outcome.local_s == pytest.approx(0.120)
    assert outcome.cloud_s is None and outcome.reward is None and not outcome.learned
    assert recorder.decisions[0][0] == outcome.request_id == 0 and recorder.decisions[0][3] is False


def test_probe_runs_both_and_rewards_with_eq10():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.200), FakePlanner(clock, 0.080)
    router, recorder = make_router(AlwaysLocal("local"), local, cloud, clock, probe_rate=1.0)
    router.route("req", STATE)
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.probe and len(local.calls) == 1 and len(cloud.calls) == 1
    assert outcome.local_s == pytest.approx(0.200) and outcome.cloud_s == pytest.approx(0.080)
    assert outcome.reward == pytest.approx(reward(LOCAL, 0.200, 0.080, CostWeights()))
    assert outcome.reward == 0.0   # eq. 10: choosing local costs nothing relative to local


def test_probe_delivers_the_first_good_path_while_the_other_side_still_runs():
    clock = VirtualClock()
    gate = threading.Event()
    local, cloud = FakePlanner(clock, 0.300, gate=gate), FakePlanner(clock, 0.090)
    router, recorder = make_router(AlwaysLocal("local"), local, cloud, clock, probe_rate=1.0)
    result = router.route("req", STATE)
    assert result.response["side"] is cloud      # returned before the local planner was allowed to finish
    assert not recorder.outcomes                   # the outcome waits for both latencies
    gate.set()
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.delivered == CLOUD and outcome.local_s == pytest.approx(0.300)
    assert outcome.reward == pytest.approx(reward(LOCAL, 0.300, 0.090))


def test_the_slower_side_of_a_probe_does_not_hold_up_the_next_request():
    clock = VirtualClock()
    gate = threading.Event()
    local, cloud = FakePlanner(clock, 0.3, gate=gate), FakePlanner(clock, 0.1)
    router, recorder = make_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=1.0)
    first = router.route("first", STATE)
    second = router.route("second", STATE)     # the first probe's local side is still running
    assert first.response["side"] is cloud and second.response["side"] is cloud
    assert len(cloud.calls) == 2 and not recorder.outcomes
    gate.set()
    finish(router)
    assert sorted(o.request_id for o in recorder.outcomes) == [0, 1]


def test_a_background_call_not_yet_started_is_cancelled_by_a_newer_request():
    """The local planner serves one call at a time: of two probes queued behind a running local call, the
    older one's local call is dropped (its caller already has the cloud path), so work never piles up."""
    clock = VirtualClock()
    gate = threading.Event()
    local, cloud = FakePlanner(clock, 0.3, gate=gate), FakePlanner(clock, 0.1)
    router, recorder = make_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=1.0)
    for name in ("first", "second", "third"):
        assert router.route(name, STATE).response["side"] is cloud
    gate.set()
    finish(router)
    assert [c for c in local.calls] == ["first", "third"]
    by_id = {o.request_id: o for o in recorder.outcomes}
    assert by_id[1].local is None and by_id[1].local_s is None      # cancelled: not measured
    assert by_id[0].local_s == pytest.approx(0.3) and by_id[2].local_s == pytest.approx(0.3)


@pytest.mark.parametrize("failure", ["timeout", "error", "raises"])
def test_cloud_failure_falls_back_to_a_local_path_and_costs_the_timeout(failure):
    clock = VirtualClock()
    local = FakePlanner(clock, 0.150)
    cloud = {"timeout": FakePlanner(clock, 2.0, status=TIMEOUT), "error": FakePlanner(clock, 0.01, status=ERROR),
             "raises": FakePlanner(clock, 0.01, raises=RuntimeError("bridge gone"))}[failure]
    router, recorder = make_router(AlwaysCloud("cloud"), local, cloud, clock, timeout_s=2.0)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == OK and result.response["side"] is local
    (outcome,) = recorder.outcomes
    assert outcome.delivered == LOCAL
    assert outcome.cloud_s == 2.0 and outcome.cloud_timeout == (failure == "timeout")
    # Both latencies are known (the cloud's is the timeout), so the step is still a transition.
    assert outcome.reward == pytest.approx(reward(CLOUD, 0.150, 2.0))


def test_unreachable_goal_gets_the_planner_status_and_teaches_nothing():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.05, status=NO_PATH), FakePlanner(clock, 0.09, status=NO_PATH)
    policy = DQNPolicy(agent=DQNAgent(DQNConfig(learning_starts=0)))
    router, recorder = make_router(policy, local, cloud, clock, probe_rate=1.0)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == NO_PATH
    (outcome,) = recorder.outcomes
    assert outcome.delivered == NO_PATH_DELIVERED and outcome.reward is None and not outcome.learned
    assert policy.steps == 0


def test_request_without_a_state_goes_to_the_local_planner_without_a_decision():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.05, status=NO_PATH), FakePlanner(clock, 0.09)
    router, recorder = make_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=1.0)
    assert router.route("req", None).status == NO_PATH
    finish(router)
    assert not recorder.decisions and not cloud.calls
    assert recorder.outcomes[0].state is None


def test_request_ids_are_consecutive_from_the_configured_base():
    clock = VirtualClock()
    router, recorder = make_router(AlwaysLocal("local"), FakePlanner(clock, 0.01), FakePlanner(clock, 0.01),
                                   clock)
    router.next_request_id = 1000
    for _ in range(3):
        router.route("req", STATE)
    finish(router)
    assert [d[0] for d in recorder.decisions] == [1000, 1001, 1002]


def test_dqn_learns_on_probe_steps_and_prefers_the_faster_side():
    """Cloud is faster for long requests, local for short ones: after online learning over real
    rewards, the greedy policy follows the rule."""
    clock = VirtualClock()
    policy = DQNPolicy(agent=DQNAgent(DQNConfig(learning_starts=40, train_frequency=1, target_update_interval=10,
                                            seed=3)))

    class ScriptedSide:
        def __init__(self, cloud):
            self.cloud, self.state = cloud, None

        def __call__(self, request):
            d = request
            cost = 0.05 + (0.02 if self.cloud else 0.1 * d)   # cloud wins above d = 0.2
            clock.advance(cost)
            return OK, None

    router, recorder = make_router(policy, ScriptedSide(False), ScriptedSide(True), clock, probe_rate=1.0)
    sizes = [0.01 * (k % 50) for k in range(300)]
    for d in sizes:
        router.route(d, State(d, 0.5, 0.05))
    finish(router)
    policy.flush()
    assert policy.steps == 2 * len(sizes)     # full information: both actions' rewards from every probe
    assert all(o.learned and o.transitions == 2 for o in recorder.outcomes)
    assert any(o.loss is not None for o in recorder.outcomes)
    assert policy.decide(State(0.45, 0.5, 0.05)).q_cloud > policy.decide(State(0.45, 0.5, 0.05)).q_local
    assert policy.agent.greedy_action(State(0.02, 0.5, 0.05).as_array()) == LOCAL


def test_frozen_dqn_is_greedy_and_does_not_learn():
    agent = DQNAgent(DQNConfig(learning_starts=0))
    policy = DQNPolicy(agent=agent, learn=False)
    decision = policy.decide(STATE)
    assert decision.propensity == 1.0
    assert decision.action == (CLOUD if decision.q_cloud > decision.q_local else LOCAL)
    assert policy.learn(STATE, decision.action, 0.3) is None and agent.steps == 0


def test_dqn_warm_up_explores_uniformly_with_propensity_one_half():
    policy = DQNPolicy(agent=DQNAgent(DQNConfig(learning_starts=100)))
    decisions = [policy.decide(STATE) for _ in range(200)]
    assert {d.propensity for d in decisions} == {0.5}
    assert {d.action for d in decisions} == {LOCAL, CLOUD}


def test_baseline_policies():
    assert InputSizeThreshold(1.1).decide(State(1.2, 0.5, 0.0)).action == CLOUD
    assert InputSizeThreshold(1.1).decide(State(1.0, 0.5, 0.0)).action == LOCAL
    actions = {RandomPolicy(seed=2).decide(STATE).action for _ in range(1)}
    assert actions <= {LOCAL, CLOUD}
    assert isinstance(AlwaysCloud("cloud"), Policy) and AlwaysCloud("c").decide(STATE) == \
        Decision(CLOUD, 1.0)
    with pytest.raises(ValueError, match="threshold"):
        InputSizeThreshold(float("nan"))


@pytest.mark.parametrize("kwargs, message", [({"probe_rate": 1.5}, "probe_rate"),
                                              ({"cloud_timeout_s": 0.0}, "cloud_timeout_s")])
def test_router_config_rejects_bad_values(kwargs, message):
    with pytest.raises(ValueError, match=message):
        RouterConfig(**kwargs)


class StaleThenFresh:
    """A planner that answers from the old map `stale_calls` times, then from the new one; each call
    costs `cost_s` on the virtual clock."""

    def __init__(self, clock, cost_s, stale_calls):
        self.clock, self.cost_s, self.stale_calls = clock, cost_s, stale_calls
        self.calls = 0

    def __call__(self, request):
        self.calls += 1
        self.clock.advance(self.cost_s)
        return OK, {"side": self, "map": "old" if self.calls <= self.stale_calls else "new"}


def stale_router(policy, local, cloud, clock, probe_rate=0.0, map_wait_s=2.0, stale_map=None):
    recorder = Recorder()
    statuses = Statuses(ok=OK, cloud_timeout=TIMEOUT, cloud_error=ERROR, stale_map=stale_map)
    router = OffloadRouter(policy, local, cloud, statuses,
                           RouterConfig(probe_rate=probe_rate, cloud_timeout_s=5.0, map_wait_s=map_wait_s,
                                        map_retry_s=0.02),
                           on_decision=recorder.decision, on_outcome=recorder.outcome, clock=clock,
                           stale=lambda response: "old map" if response["map"] == "old" else None,
                           sleep=clock.advance)
    return router, recorder


NO_MAP = 1


def test_a_path_from_a_stale_map_is_never_delivered_the_planner_is_asked_again():
    clock = VirtualClock()
    local, cloud = StaleThenFresh(clock, 0.010, stale_calls=3), FakePlanner(clock, 0.050)
    router, recorder = stale_router(AlwaysLocal("local"), local, cloud, clock)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == OK and result.response["map"] == "new"
    assert local.calls == 4
    (outcome,) = recorder.outcomes
    # the measured latency includes the calls on the old map and the pauses between them
    assert outcome.local_s == pytest.approx(4 * 0.010 + 3 * 0.02)


def test_a_local_planner_that_never_takes_the_announced_map_keeps_serving_its_last_good_map():
    """The announced map never reached the planner in a usable form (a malformed grid it refused): after
    the wait the robot gets the path on the last map the planner accepted, with a note, and nothing is
    learned from a latency that measured the wait."""
    clock = VirtualClock()
    local, cloud = StaleThenFresh(clock, 0.010, stale_calls=10**9), FakePlanner(clock, 0.050)
    router, recorder = stale_router(AlwaysLocal("local"), local, cloud, clock, map_wait_s=0.5)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == OK and result.response["map"] == "old" and result.raised is None
    assert "last map the planner accepted" in result.note and "old map" in result.note
    (outcome,) = recorder.outcomes
    assert outcome.delivered == LOCAL and outcome.reward is None
    assert 0.5 <= outcome.local_s < 0.5 + 0.010 + 0.02 + 1e-9


STALE = 12


def test_a_path_only_on_the_old_map_is_never_ok_and_is_waited_for_once_per_map():
    """The planner never takes the announced map: the caller gets the old path with STALE_MAP and why, and
    the next request on the same stale map does not wait map_wait_s again."""
    clock = VirtualClock()
    local, cloud = StaleThenFresh(clock, 0.010, stale_calls=10**9), FakePlanner(clock, 0.050)
    router, recorder = stale_router(AlwaysLocal("local"), local, cloud, clock, map_wait_s=0.5,
                                    stale_map=STALE)
    first = router.route("req", STATE)
    calls_after_first = local.calls
    second = router.route("req", STATE)
    finish(router)
    assert first.status == second.status == STALE and "last map the planner accepted" in first.note
    assert first.response["map"] == "old"
    assert calls_after_first > 10 and local.calls == calls_after_first + 1   # no second wait
    assert all(o.delivered == NO_PATH_DELIVERED and o.reward is None for o in recorder.outcomes)


def test_a_stale_cloud_path_falls_back_to_the_local_path_and_costs_the_timeout():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.120), StaleThenFresh(clock, 0.010, stale_calls=10**9)
    router, recorder = stale_router(AlwaysCloud("cloud"), _Fresh(local), cloud, clock, map_wait_s=0.3)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == OK and result.response["map"] == "new" and result.response["side"] is local
    (outcome,) = recorder.outcomes
    assert outcome.delivered == LOCAL and outcome.cloud.status == ERROR and outcome.cloud_s == 5.0


def test_probe_delivers_the_fresh_side_even_when_the_stale_side_answers_first():
    clock = VirtualClock()
    local, cloud = StaleThenFresh(clock, 0.001, stale_calls=10**9), _Fresh(FakePlanner(clock, 0.300))
    router, recorder = stale_router(AlwaysLocal("local"), local, cloud, clock, probe_rate=1.0,
                                    map_wait_s=1.0)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == OK and result.response["map"] == "new"
    (outcome,) = recorder.outcomes
    assert outcome.delivered == CLOUD and outcome.local.note and outcome.reward is None


class _Fresh:
    """A FakePlanner whose answers come from the new map."""

    def __init__(self, planner):
        self.planner = planner

    def __call__(self, request):
        status, response = self.planner(request)
        return status, {**response, "map": "new"}


def test_router_config_rejects_a_bad_map_wait():
    with pytest.raises(ValueError, match="map_wait_s"):
        RouterConfig(map_wait_s=float("nan"))
    with pytest.raises(ValueError, match="map_retry_s"):
        RouterConfig(map_retry_s=0.0)


def test_probe_with_both_sides_on_the_old_map_delivers_the_local_last_good_map():
    clock = VirtualClock()
    local, cloud = StaleThenFresh(clock, 0.001, stale_calls=10**9), StaleThenFresh(clock, 0.002, stale_calls=10**9)
    router, recorder = stale_router(AlwaysCloud("cloud"), local, cloud, clock, probe_rate=1.0, map_wait_s=0.2)
    result = router.route("req", STATE)
    finish(router)
    assert result.status == OK and result.response["side"] is local and result.note
    (outcome,) = recorder.outcomes
    assert outcome.delivered == LOCAL and outcome.cloud.status == ERROR and outcome.reward is None


# --- modes, hedge, breaker, accounting ------------------------------------------------------------
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
    recorder = Recorder()
    router = OffloadRouter(policy, local, cloud, STATUSES, RouterConfig(**config), on_decision=recorder.decision,
                           on_outcome=recorder.outcome, clock=clock)
    return router, recorder


def test_learning_mode_probes_every_request_and_teaches_both_actions():
    clock = VirtualClock()
    policy = LearningRecorder(CLOUD)
    router, recorder = configured_router(policy, FakePlanner(clock, 0.2), FakePlanner(clock, 0.08), clock,
                                         mode="learning", probe_rate=0.0)
    for _ in range(3):
        router.route("req", STATE)
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
    assert router._deadline_s(CLOUD, STATE) == 0.9          # no model yet: the upper bound
    for k in range(60):
        router.models[CLOUD].observe((1.2, 0.6, 0.05), 0.1 * (1.0 + 0.05 * (k % 3 - 1)))
    assert 0.1 < router._deadline_s(CLOUD, STATE) < 0.3      # a high quantile of about 0.1 s


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
    router.breaker.record_heartbeat(True, 0.05)  # a ping says the link is back
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
    router.route("req", STATE)
    finish(router)
    assert [(r.breaker, r.probe) for r in recorder.routings] == [("open", False), ("trial", True), ("closed", False)]


def test_cost_accounting_sums_every_side_called():
    clock = VirtualClock()
    local, cloud = FakePlanner(clock, 0.2), FakePlanner(clock, 0.05)
    costs = {id(local): (0.18, 0, 0), id(cloud): (0.004, 1200, 800)}
    router = OffloadRouter(AlwaysLocal("local"), local, cloud, STATUSES, RouterConfig(mode="learning"),
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
    assert router._deadline_s(LOCAL, STATE) == pytest.approx(0.12, rel=0.05)
    assert router._deadline_s(CLOUD, STATE) == pytest.approx(router.models[CLOUD].quantile_s((1.2, 0.6, 0.05), 0.95))
    assert router._deadline_s(CLOUD, STATE) > 0.12


def test_a_warm_started_policy_probes_until_both_latency_models_are_ready():
    """A trained DQN on a fresh node: no latency model has samples, so one-sided requests would teach nothing
    and the hedge would wait its maximum; it probes until both models are ready, then at its rate."""
    clock = VirtualClock()
    policy = LearningRecorder(CLOUD)           # learns, never warming up
    router, recorder = configured_router(policy, FakePlanner(clock, 0.2), FakePlanner(clock, 0.05), clock,
                                         mode="deployed", probe_rate=0.0)
    for _ in range(40):
        router.route("req", STATE)
    finish(router)
    probes = [r.probe for r in recorder.routings]
    min_samples = router.config.latency_model.min_samples
    assert all(probes[:min_samples]) and not any(probes[min_samples:])
    assert all(o.learned for o in recorder.outcomes)
