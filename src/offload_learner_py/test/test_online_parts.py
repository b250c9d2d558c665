"""The ROS-free pieces of the online system: goal sampling, records -> transition table, the run
summary, the robot workload and the robot's CPU availability readers."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.online.cpu import CgroupBudgetReader, CpuAvailability, LatestCpuAvailability, parse_cpu_list, \
    read_proc_stat_cores
from offload_learner_py.data.dataset import TransitionTable
from offload_planner_cpp import free_cells
from offload_learner_py.online.goals import GoalSampler, default_start_cell
from offload_learner_py.data.records import NO_PATH_DELIVERED, RecordMismatchError, pair_records, transition_table
from offload_learner_py.core.reward import reward
from offload_learner_py.offline.summary import format_summary, learned_offload_input_size, oracle_share_by_tercile, \
    summarise
from offload_learner_py.online.workload import LoadSchedule, run_workload


# --- goals -------------------------------------------------------------------------------------
def test_free_cells_follow_the_planner_rules():
    grid = np.array([[0, 49, 50, 100, -1]], dtype=np.int8)
    assert free_cells(grid, 50, unknown_is_obstacle=True).tolist() == [[True, True, False, False, False]]
    assert free_cells(grid, 50, unknown_is_obstacle=False).tolist() == [[True, True, False, False, True]]
    with pytest.raises(ValueError, match="lethal_threshold"):
        free_cells(grid, 0)


def test_goals_are_only_drawn_from_the_start_component_and_are_seeded():
    grid = np.zeros((20, 30), dtype=np.int8)
    grid[:, 10] = 100                      # a wall: x > 10 is unreachable from x < 10
    free = free_cells(grid)
    sampler = GoalSampler(free, (2, 5), seed=4)
    goals = [sampler.draw() for _ in range(300)]
    assert all(x < 10 for x, _ in goals)
    assert sampler.reachable_cells == 10 * 20
    assert goals == [GoalSampler(free, (2, 5), seed=4).draw() for _ in range(1)] + goals[1:]
    far = GoalSampler(free, (0, 0), seed=1, min_distance_cells=15)
    assert all(math.hypot(x, y) >= 15 for x, y in (far.draw() for _ in range(100)))


def test_goal_sampler_rejects_a_blocked_or_off_map_start():
    free = free_cells(np.array([[0, 100], [0, 0]], dtype=np.int8))
    with pytest.raises(ValueError, match="not free"):
        GoalSampler(free, (1, 0))
    with pytest.raises(ValueError, match="off the"):
        GoalSampler(free, (5, 0))
    assert default_start_cell(free) == (1, 1)


# --- records -----------------------------------------------------------------------------------
def decision(request_id, action=LOCAL, d=1.0, u=0.5, b=0.05, propensity=0.95):
    return SimpleNamespace(request_id=request_id, input_size=d, cpu_availability=u, round_trip_s=b, action=action,
                           action_propensity=propensity, q_local=0.0, q_cloud=0.1, policy="dqn", model_steps=3,
                           probe=True)


def outcome(request_id, action=LOCAL, local_s=0.2, cloud_s=0.1, reward_valid=True, timeout=False, delivered=None):
    return SimpleNamespace(request_id=request_id, action=action,
                           delivered=CLOUD if delivered is None and cloud_s < local_s else (delivered or LOCAL),
                           local_measured=True, local_s=local_s, local_status=0, cloud_measured=True, cloud_s=cloud_s,
                           cloud_status=9 if timeout else 0, cloud_timeout=timeout, reward_valid=reward_valid,
                           reward=reward(action, local_s, cloud_s) if reward_valid else float("nan"),
                           loss_valid=False, loss=float("nan"), delivered_s=min(local_s, cloud_s))


def test_records_rebuild_transition_table_rows_by_request_id():
    decisions = [decision(12, CLOUD, d=2.0), decision(10, LOCAL, d=0.5), decision(11, LOCAL)]
    outcomes = [outcome(10, LOCAL, 0.1, 0.3), outcome(12, CLOUD, 0.4, 0.2), outcome(11, reward_valid=False)]
    log = pair_records(decisions, outcomes)
    table = transition_table(log)
    assert isinstance(table, TransitionTable)
    assert table.t.tolist() == [10, 12]            # the request without a reward is not a transition
    assert table.action.tolist() == [LOCAL, CLOUD]
    assert table.input_size.tolist() == [0.5, 2.0]
    assert table.local_s.tolist() == [0.1, 0.4] and table.cloud_s.tolist() == [0.3, 0.2]
    assert table.reward[1] == pytest.approx(reward(CLOUD, 0.4, 0.2))


def test_records_keep_a_decision_whose_outcome_is_missing():
    log = pair_records([decision(1), decision(2)], [outcome(1)])
    assert log["has_outcome"].tolist() == [True, False]
    assert len(transition_table(log)) == 1


@pytest.mark.parametrize("decisions, outcomes, message", [
    ([decision(1)], [outcome(2)], "no decision"),
    ([decision(1, LOCAL)], [outcome(1, CLOUD)], "action"),
    ([decision(1), decision(1)], [], "two decisions"),
    ([decision(1)], [outcome(1), outcome(1)], "two outcomes"),
])
def test_records_that_disagree_are_rejected(decisions, outcomes, message):
    with pytest.raises(RecordMismatchError, match=message):
        pair_records(decisions, outcomes)


# --- summary -----------------------------------------------------------------------------------
def run_log(n=60):
    """Cloud wins exactly when d > 1: a policy that follows that rule in the second half only."""
    decisions, outcomes = [], []
    for k in range(n):
        d = 0.2 + 1.6 * (k % 10) / 9
        best = CLOUD if d > 1 else LOCAL
        action = best if k >= n // 2 else LOCAL
        local_s, cloud_s = 0.1 * d + 0.02, 0.12
        decisions.append(decision(k, action, d=d, u=0.2 + 0.01 * k, b=0.05))
        outcomes.append(outcome(k, action, local_s, cloud_s))
    return pair_records(decisions, outcomes)


def test_summary_compares_against_the_baselines_on_the_same_probe_steps():
    log = run_log()
    table = transition_table(log)
    summary = summarise(log, table, q_values=lambda s: np.stack([np.ones(len(s)), np.asarray(s)[:, 0]], axis=1))
    assert summary["requests"] == summary["paths_delivered"] == 60
    second = summary["second_half"]
    assert second["accuracy"] == 1.0
    assert second["mean_latency_s"] == pytest.approx(summary["second_half_oracle_mean_latency_s"])
    assert second["mean_latency_s"] < min(second["mean_latency_always_local_s"], second["mean_latency_always_cloud_s"])
    assert summary["second_half_beats_both"] is True
    assert summary["final_greedy_accuracy"] == 1.0
    assert summary["learned_offload_input_size"] == pytest.approx(1.0, rel=0.02)
    shares = summary["oracle_cloud_share_by_tercile"]["d_t"]["cloud_share"]
    assert shares[0] == 0.0 and shares[2] == 1.0
    text = format_summary(summary)
    for line in ("beats both fixed policies", "always local", "always cloud", "oracle", "accuracy", "d_t:", "u_t:", "b_t:", "paths delivered 60/60"):
        assert line in text


def test_learned_offload_point_is_nan_when_the_policy_never_switches():
    states = np.array([[0.1, 0.5, 0.1], [3.0, 0.5, 0.1]])
    always_local = lambda s: np.tile([1.0, 0.0], (len(s), 1))  # noqa: E731
    assert math.isnan(learned_offload_input_size(always_local, states))
    log = pair_records([decision(1, d=0.1), decision(2, d=3.0)], [outcome(1, local_s=0.1), outcome(2, local_s=0.1)])
    text = format_summary(summarise(log, transition_table(log), always_local))
    assert "none in the observed d_t range" in text and "none in the observed u_t range" in text


def test_oracle_share_by_tercile_on_a_cpu_rule():
    u = np.linspace(0.05, 0.95, 30)
    table = TransitionTable(t=np.arange(30), input_size=np.ones(30), cpu_availability=u, round_trip_s=np.zeros(30),
                            local_s=np.where(u < 0.5, 0.3, 0.1), cloud_s=np.full(30, 0.2), action=np.zeros(30, int),
                            action_propensity=np.ones(30), reward=np.zeros(30))
    shares = oracle_share_by_tercile(table)["u_t"]["cloud_share"]
    assert shares[0] == 1.0 and shares[2] == 0.0


def test_summary_names_requests_cut_off_by_the_end_of_the_run():
    log = pair_records([decision(1), decision(2)], [outcome(1)])
    text = format_summary(summarise(log, transition_table(log)))
    assert "paths delivered 1/2" in text and "1 request(s) still in flight" in text


def test_summary_of_a_run_without_probe_steps():
    log = pair_records([decision(1)], [outcome(1, reward_valid=False)])
    summary = summarise(log, transition_table(log))
    assert summary["probe_steps"] == 0 and "nothing to compare" in format_summary(summary)


# --- workload ----------------------------------------------------------------------------------
def test_load_schedule_is_a_seeded_function_of_time():
    schedule = LoadSchedule(levels=(0.0, 0.5, 0.9), phase_s=2.0, seed=7)
    levels = [schedule.level_at(t) for t in np.arange(0, 40, 0.5)]
    assert set(levels) <= {0.0, 0.5, 0.9} and len(set(levels)) > 1
    assert levels == [LoadSchedule(levels=(0.0, 0.5, 0.9), phase_s=2.0, seed=7).level_at(t)
                      for t in np.arange(0, 40, 0.5)]
    assert schedule.level_at(0.1) == schedule.level_at(1.9)
    with pytest.raises(ValueError, match="levels"):
        LoadSchedule(levels=(1.0,))


def test_workload_burns_its_share_of_the_budget_per_slice():
    wall, cpu, slept, seen = [0.0], [0.0], [], []

    def clock():
        return wall[0]

    def cpu_clock():              # spinning: every look at the CPU clock burns 1 ms of CPU and wall time
        wall[0] += 0.001
        cpu[0] += 0.001
        return cpu[0]

    def sleep(seconds):
        slept.append(seconds)
        wall[0] += seconds

    run_workload(LoadSchedule(levels=(0.5,), phase_s=10.0), budget_cores=0.4, stop=lambda: len(slept) >= 20,
                 on_level=seen.append, slice_s=0.02, clock=clock, cpu_clock=cpu_clock, sleep=sleep)
    assert seen == [0.5]
    # 0.5 of a 0.4-core budget over 20 slices of 20 ms is 80 ms of CPU (within one clock tick per slice).
    assert cpu[0] == pytest.approx(0.5 * 0.4 * 0.02 * 20, abs=20 * 0.002)


# --- the robot's CPU availability ----------------------------------------------------------------
def test_parse_cpu_list():
    assert parse_cpu_list("0") == (0,)
    assert parse_cpu_list("0,2-3") == (0, 2, 3)
    for bad in ("", "a", "3-1", "-1"):
        with pytest.raises(ValueError, match="CPU list"):
            parse_cpu_list(bad)


def test_per_core_proc_stat_counts_only_the_pinned_cores(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  300 0 300 600 0 0 0 0 0 0\n"
                    "cpu0 100 0 100 200 0 0 0 0 0 0\n"
                    "cpu1 200 0 200 400 0 0 0 0 0 0\n"
                    "intr 5\n")
    assert read_proc_stat_cores([0], str(stat)) == (200, 400)
    assert read_proc_stat_cores([0, 1], str(stat)) == (600, 1200)
    with pytest.raises(ValueError, match="cpu7"):
        read_proc_stat_cores([7], str(stat))


def test_cgroup_budget_availability_is_the_unused_share_of_the_quota(tmp_path):
    for controller in ("cpu", "cpuacct"):
        (tmp_path / controller / "robot").mkdir(parents=True)
    (tmp_path / "cpu" / "robot" / "cpu.cfs_quota_us").write_text("1000\n")
    (tmp_path / "cpu" / "robot" / "cpu.cfs_period_us").write_text("4000\n")
    usage = tmp_path / "cpuacct" / "robot" / "cpuacct.usage"
    usage.write_text("0\n")
    now = [0]
    reader = CgroupBudgetReader("robot", root=str(tmp_path), clock=lambda: now[0])
    assert reader.budget_cores == 0.25
    availability = CpuAvailability(reader, sleep=lambda s: now.__setitem__(0, now[0] + int(s * 1e9)))
    assert availability.sample() == 1.0              # first sample: nothing used over its short window
    now[0] += 1_000_000_000                          # one second of wall time: a 0.25 s budget
    usage.write_text(str(100_000_000))               # the group used 0.1 s of it
    assert availability.sample() == pytest.approx(0.6)


def test_cgroup_without_a_quota_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="cgroup 'nothere'"):
        CgroupBudgetReader("nothere", root=str(tmp_path))


def test_latest_availability_never_waits_and_keeps_the_last_measured_window():
    readings = iter([(0, 0), (50, 100), (50, 101), (60, 102), (110, 300)])
    slept = []
    cpu = LatestCpuAvailability(lambda: next(readings), min_window=10, sleep=slept.append)
    assert cpu.value == 0.5 and len(slept) == 1          # the first window, measured at construction
    assert cpu.sample() == 0.5 and cpu.sample() == 0.5   # 1 and 2 ticks later: too short, last value kept
    assert cpu.sample() == pytest.approx(60 / 200)       # 200 ticks since the last measured reading
    assert len(slept) == 1


def test_delivered_figures_are_what_the_caller_saw_and_the_robot_paid():
    from offload_learner_py.offline.summary import delivered_figures
    decisions, outcomes = [], []
    for k in range(10):
        decisions.append(SimpleNamespace(**vars(decision(k)), mode="deployed", routed=LOCAL,
                                         breaker="open" if k >= 8 else "closed", deadline_s=float("nan")))
        done = outcome(k, local_s=0.1, cloud_s=0.3)
        done.delivered_s = 6.0 if k == 9 else 0.1 * (k + 1)
        done.cloud_timeout = k == 9
        done.delivered = NO_PATH_DELIVERED if k == 0 else LOCAL
        outcomes.append(SimpleNamespace(**vars(done), hedged=k == 5, transitions=2, imputed=NO_PATH_DELIVERED,
                                        robot_cpu_s=0.02 * k, bridge_cpu_s=0.001, link_bytes_sent=1000,
                                        link_bytes_received=3000))
    figures = delivered_figures(pair_records(decisions, outcomes), cloud_timeout_s=5.0)
    assert figures["requests"] == 10 and figures["paths_delivered"] == 9
    assert figures["mean_s"] == pytest.approx((sum(0.1 * (k + 1) for k in range(9)) + 6.0) / 10)
    assert figures["p50_s"] == pytest.approx(0.55) and figures["max_s"] == 6.0
    assert figures["robot_cpu_s_per_request"] == pytest.approx(0.09)
    assert figures["bridge_cpu_s_per_request"] == pytest.approx(0.001)
    assert figures["link_bytes_per_request"] == 4000
    assert (figures["cloud_timeouts"], figures["waited_the_timeout"]) == (1, 1)
    assert (figures["hedged"], figures["breaker_open"], figures["probes"]) == (1, 2, 10)


@pytest.mark.parametrize("second_half_action, beats", [(CLOUD, False), (LOCAL, False), (None, True)])
def test_beating_both_fixed_policies_means_both(second_half_action, beats):
    """Always cloud in the second half beats always-local there but only ties always-cloud; only the oracle
    rule beats both (a max in place of the min would say yes to the first)."""
    decisions, outcomes = [], []
    for k in range(40):
        d = 0.2 + 1.6 * (k % 10) / 9
        best = CLOUD if d > 1 else LOCAL
        action = best if second_half_action is None or k < 20 else second_half_action
        local_s, cloud_s = 0.1 * d + 0.02, 0.10     # always cloud (0.10 s) beats always local (0.12 s)
        decisions.append(decision(k, action, d=d))
        outcomes.append(outcome(k, action, local_s, cloud_s))
    log = pair_records(decisions, outcomes)
    assert summarise(log, transition_table(log))["second_half_beats_both"] is beats
