"""offline/summary.py: the run summary against the fixed policies and the oracle, and what the caller saw."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from recordtools import decision, outcome
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.data.records import NO_PATH_DELIVERED, pair_records, transition_table
from offload_learner_py.offline.summary import format_summary, learned_offload_input_size, oracle_share_by_tercile, \
    summarise


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


def test_the_bridge_cost_per_cloud_request_counts_only_the_requests_that_asked_the_cloud():
    """#30's bar is per cloud request: a policy that offloads a third of its requests must not read a third of it."""
    from offload_learner_py.offline.summary import delivered_figures
    decisions, outcomes = [], []
    for k in range(9):
        asked = k % 3 == 0
        action = CLOUD if asked else LOCAL
        decisions.append(SimpleNamespace(**{**vars(decision(k, action)), "probe": False}, mode="deployed",
                                         routed=action, breaker="closed", deadline_s=float("nan")))
        done = outcome(k, action=action, local_s=0.1, cloud_s=0.3, reward_valid=False)
        done.local_measured, done.cloud_measured = not asked, asked
        done.cloud_timeout = k == 6        # a timeout asked the cloud too (measured as the timeout), and cost the bridge
        outcomes.append(SimpleNamespace(**vars(done), hedged=False, transitions=1, imputed=NO_PATH_DELIVERED,
                                        robot_cpu_s=0.0 if asked else 0.01,
                                        bridge_cpu_s=(0.0004, 0.0006, 0.0008)[k // 3] if asked else 0.0,
                                        link_bytes_sent=0, link_bytes_received=0))
    figures = delivered_figures(pair_records(decisions, outcomes), cloud_timeout_s=5.0)
    assert figures["cloud_calls"] == 3
    assert figures["bridge_cpu_s_per_cloud_request"] == pytest.approx(0.0006)
    assert figures["bridge_cpu_s_per_request"] == pytest.approx(0.0002)


def test_no_cloud_request_leaves_the_bridge_cost_per_cloud_request_undefined():
    from offload_learner_py.offline.summary import delivered_figures
    decisions = [SimpleNamespace(**{**vars(decision(k)), "probe": False}, mode="deployed", routed=LOCAL,
                                 breaker="closed", deadline_s=float("nan")) for k in range(3)]
    outcomes = []
    for k in range(3):
        done = outcome(k, local_s=0.1, cloud_s=0.3, reward_valid=False)
        done.cloud_measured = False
        outcomes.append(SimpleNamespace(**vars(done), hedged=False, transitions=1, imputed=NO_PATH_DELIVERED,
                                        robot_cpu_s=0.01, bridge_cpu_s=0.0, link_bytes_sent=0, link_bytes_received=0))
    figures = delivered_figures(pair_records(decisions, outcomes), cloud_timeout_s=5.0)
    assert figures["cloud_calls"] == 0 and math.isnan(figures["bridge_cpu_s_per_cloud_request"])
