"""p_t, the robot's own local planning rate: how the learner measures it (online/plan_rate.py) and that a model
trained with it tells robots apart. Two robots that differ only in how fast they plan see the same requests on
the same link: the same (d_t, u_t, b_t) is best planned on board by the fast one and in the cloud by the slow one,
and only p_t can tell the network which robot asks."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.reward import CostWeights, rewards
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.offline.retrain import train_offline
from offload_learner_py.online.plan_rate import PlanRateEstimator
from offload_learner_py.online.router_types import SideResult
from statetools import raw_states

NOT_MEASURED = STATE_SCHEMA["local_plan_rate"].missing


def test_the_rate_is_not_measured_until_a_plan_is_timed_then_its_input_size_per_second():
    rate = PlanRateEstimator(NOT_MEASURED, weight=0.25)
    assert rate.value == 0.0 and rate.plans == 0
    assert rate.observe(2.0, 0.004)                          # the first timed plan is the rate, not a blend with 0
    assert rate.value == pytest.approx(500.0) and rate.plans == 1
    assert rate.observe(0.1, 0.001)
    assert rate.value == pytest.approx(0.75 * 500.0 + 0.25 * 100.0)
    assert rate.plans == 2


@pytest.mark.parametrize("input_size, seconds", [
    (0.0, 0.01),            # a goal beside the start: the planner's fixed costs, not its rate
    (1.0, 5e-6),            # too short for the timer
    (1.0, math.nan), (1.0, math.inf), (1.0, -0.01), (math.nan, 0.01),
])
def test_plans_too_small_or_badly_timed_do_not_count(input_size, seconds):
    rate = PlanRateEstimator(NOT_MEASURED)
    rate.observe(2.0, 0.004)
    assert not rate.observe(input_size, seconds)
    assert rate.value == pytest.approx(500.0) and rate.plans == 1


OK, NO_PATH = 0, 7   # PlanPath's statuses


def outcome(input_size, local_status=OK, local_time_s=0.004, cancelled=False, local=True):
    response = SimpleNamespace(planning_time_s=local_time_s)
    side = SideResult(local_status, response, 0.01, cancelled=cancelled) if local else None
    return SimpleNamespace(state=SimpleNamespace(input_size=input_size), local=side)


def test_the_learner_pairs_each_requests_d_t_with_its_own_local_planning_time():
    """From the router's outcome: the request's d_t over the local planner core's time for it. A robot whose search
    is faster (jump points: a tenth of the time, a hundredth of the cells settled) reads as faster, whatever it
    settles; a local side that found no path, was cancelled or did not run teaches nothing."""
    waves, jumps = PlanRateEstimator(NOT_MEASURED), PlanRateEstimator(NOT_MEASURED)
    assert waves.observe_outcome(outcome(2.0, local_time_s=0.04), OK)
    assert jumps.observe_outcome(outcome(2.0, local_time_s=0.004), OK)
    assert waves.value == pytest.approx(50.0) and jumps.value == pytest.approx(500.0)
    for skipped in (outcome(2.0, NO_PATH), outcome(2.0, cancelled=True), outcome(2.0, local=False),
                    outcome(2.0, local_time_s=math.nan)):
        assert not jumps.observe_outcome(skipped, OK)
    assert jumps.value == pytest.approx(500.0) and jumps.plans == 1


@pytest.mark.parametrize("initial, weight", [(-1.0, 0.2), (math.nan, 0.2), (0.0, 0.0), (0.0, 1.5), (0.0, -0.2)])
def test_a_bad_start_or_weight_is_refused(initial, weight):
    with pytest.raises(ValueError):
        PlanRateEstimator(initial, weight)


# d_t/s: a robot with a free fast CPU, one with a tenth of it, and the cloud (the demo's robots plan 114-746)
FAST, SLOW = 400.0 / 3, 40.0 / 3
CLOUD_RATE = 1000.0 / 3


def robot_rows(plan_rate: float, n: int, seed: int) -> dict:
    """One robot's probe rows: random requests over the same link; local and cloud times from d_t over each
    side's rate."""
    rng = np.random.default_rng(seed)
    d = 10 ** rng.uniform(-2, 0.5, n)
    u = rng.uniform(0.3, 1.0, n)
    b = rng.uniform(0.02, 0.04, n)
    local_s = 0.002 + d / plan_rate
    cloud_s = b + 0.002 + d / CLOUD_RATE
    return dict(input_size=d, cpu_availability=u, round_trip_s=b, local_plan_rate=np.full(n, plan_rate),
                local_s=local_s, cloud_s=cloud_s)


def pooled_table() -> TransitionTable:
    rows = [robot_rows(FAST, 400, 1), robot_rows(SLOW, 400, 2)]
    columns = {name: np.concatenate([r[name] for r in rows]) for name in rows[0]}
    action = np.random.default_rng(3).integers(0, 2, 800)
    return TransitionTable(t=np.arange(800), **columns, action=action, action_propensity=np.full(800, 0.5),
                           reward=rewards(action, columns["local_s"], columns["cloud_s"], CostWeights()))


def greedy_on_both_robots(table: TransitionTable):
    """The trained network's greedy action for the same held-out requests asked by the fast and the slow robot,
    and the right ones."""
    agent = train_offline(table, DQNConfig(seed=5)).agent
    probe = robot_rows(SLOW, 300, 9)
    greedy, right = {}, {}
    for name, rate in (("fast", FAST), ("slow", SLOW)):
        rows = robot_rows(rate, 300, 9)
        states = raw_states(probe["input_size"], probe["cpu_availability"], probe["round_trip_s"], rate)
        greedy[name] = agent.greedy_actions(states)
        right[name] = np.where(rows["cloud_s"] < rows["local_s"], CLOUD, LOCAL)
    return greedy, right


def test_one_pooled_model_gives_robots_that_differ_only_in_plan_rate_their_own_actions():
    greedy, right = greedy_on_both_robots(pooled_table())
    differ = right["fast"] != right["slow"]
    assert 0.3 < differ.mean() < 0.8                                # the same request, different right answers
    clear = differ & (np.abs(np.log10(robot_rows(SLOW, 300, 9)["input_size"]) - math.log10(0.42)) > 0.15)
    assert np.mean(greedy["fast"][clear] == LOCAL) > 0.9 and np.mean(greedy["slow"][clear] == CLOUD) > 0.9
