"""The latency-bound rule (FogROS2-LS): offload when last round trip + the cloud's planning time is below the
robot's predicted planning time; both planning times from the recent measured plans of each side."""
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.policies import LatencyBound
from offload_learner_py.core.state import State
from offload_learner_py.online.session import SessionConfig, make_policy


def state(d=1.0, u=1.0, b=0.02):
    return State(input_size=d, cpu_availability=u, round_trip_s=b, local_plan_rate=0.0)


def trained(local_per_d=0.05, cloud_per_d=0.01, samples=5):
    """A rule that has seen `samples` plans of each side: local 50 ms per unit d at full CPU, cloud 10 ms."""
    rule = LatencyBound()
    for _ in range(samples):
        rule.observe(state(d=2.0, u=0.5, b=0.03), local_per_d * 2.0 / 0.5, 0.03 + cloud_per_d * 2.0)
    return rule


def test_it_tries_each_side_until_it_has_a_bound_for_both():
    rule = LatencyBound(min_samples=2)
    actions = []
    for _ in range(4):
        action = rule.decide(state()).action
        actions.append(action)
        rule.observe(state(), 0.05 if action == LOCAL else None, 0.04 if action == CLOUD else None)
    assert sorted(actions) == [LOCAL, LOCAL, CLOUD, CLOUD]


def test_it_predicts_from_the_round_trip_the_cpu_and_the_recent_planning_rates():
    rule = trained()
    local_s, cloud_s = rule.predicted_s(state(d=1.0, u=0.25, b=0.1))
    assert local_s == pytest.approx(0.05 / 0.25)
    assert cloud_s == pytest.approx(0.1 + 0.01)


def test_the_round_trip_and_the_cpu_decide():
    rule = trained()
    assert rule.decide(state(d=1.0, u=1.0, b=0.01)).action == CLOUD     # 20 ms cloud against 50 ms local
    assert rule.decide(state(d=1.0, u=1.0, b=0.2)).action == LOCAL      # a slow link: local
    assert rule.decide(state(d=1.0, u=0.1, b=0.2)).action == CLOUD      # the same link, a starved CPU: cloud


def test_its_planning_estimate_follows_a_new_map_within_a_few_requests():
    rule = trained(local_per_d=0.05)
    for _ in range(15):   # a map where local plans take ten times as long per unit d_t
        rule.observe(state(d=1.0), 0.5, None)
    assert rule.predicted_s(state(d=1.0))[0] == pytest.approx(0.5, rel=0.05)


def test_the_node_builds_it_by_name():
    policy, agent = make_policy(SessionConfig(policy="latency_bound"))
    assert isinstance(policy, LatencyBound) and agent is None and not policy.learns


def test_the_online_learner_hands_it_every_measured_latency_and_nothing_else():
    from routertools import ERROR, OK, STATE, STATUSES
    from test_learning import outcome
    from offload_learner_py.online.learning import OnlineLearner

    rule = LatencyBound()
    learner = OnlineLearner(rule, STATUSES)
    learner.learn(outcome(local=(OK, 0.2), cloud=(OK, STATE.round_trip_s + 0.05)))      # a probe: both sides
    learner.learn(outcome(action=LOCAL, local=(OK, 0.1), cloud=None, probe=False))     # deployed: local alone
    learner.learn(outcome(local=None, cloud=(ERROR, 0.01), probe=False))                # a failed cloud plans nothing
    assert rule.samples == {LOCAL: 2, CLOUD: 1}
    work = max(STATE.input_size, rule.d_floor)
    assert rule.seconds_per_d[CLOUD] == pytest.approx(0.05 / work)
