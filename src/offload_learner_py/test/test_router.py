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
from offload_learner_py.online.router_types import RouterConfig, Statuses
from offload_learner_py.core.state import State
from routertools import ERROR, NO_PATH, OK, STATE, TIMEOUT, FakePlanner, Recorder, VirtualClock, finish, \
    make_router, wired_router



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


def gated_local(local_s: float, cloud_s: float):
    """A virtual clock, the gate that holds the local planner's answer, and the two fake planners."""
    clock, gate = VirtualClock(), threading.Event()
    return clock, gate, FakePlanner(clock, local_s, gate=gate), FakePlanner(clock, cloud_s)


def test_probe_delivers_the_first_good_path_while_the_other_side_still_runs():
    clock, gate, local, cloud = gated_local(0.300, 0.090)
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
    clock, gate, local, cloud = gated_local(0.3, 0.1)
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
        router.route(d, State(d, 0.5, 0.05, 2e7))
        # Both sides measured before the next request: its caller goes on once it has the first path, and a local
        # side not yet started when a newer request needs the planner is dropped (test_router_cancel.py).
        assert router.wait_idle(30)
    finish(router)
    policy.flush()
    assert policy.steps == 2 * len(sizes)     # full information: both actions' rewards from every probe
    assert all(o.learned and o.transitions == 2 for o in recorder.outcomes)
    assert any(o.loss is not None for o in recorder.outcomes)
    assert policy.decide(State(0.45, 0.5, 0.05, 2e7)).q_cloud > policy.decide(State(0.45, 0.5, 0.05, 2e7)).q_local
    assert policy.agent.greedy_action(State(0.02, 0.5, 0.05, 2e7).as_array()) == LOCAL


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
    assert InputSizeThreshold(1.1).decide(State(1.2, 0.5, 0.0, 2e7)).action == CLOUD
    assert InputSizeThreshold(1.1).decide(State(1.0, 0.5, 0.0, 2e7)).action == LOCAL
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
    router = wired_router(policy, local, cloud, statuses,
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
