"""bench-policies' figures: one policy's repeated runs are pooled request by request, and each run's mean is
kept to show the spread between repeats."""
import numpy as np
import pytest

from bagtools import CLOUD, LOCAL, make_requests, write
from offload_learner_py.core.reward import reward
from offload_demos.bag_writer import probe_request
from offload_demos.bench_policies import measure


def test_repeated_runs_are_pooled_and_each_runs_mean_is_kept(tmp_path):
    runs = []
    for k, n in enumerate((30, 50)):
        run = tmp_path / f"repeat{k + 1}"
        run.mkdir()
        write(run / "offload.bag", make_requests(n, seed=k, probe_every=3, first_id=1000 * (k + 1)))
        runs.append(run)
    alone = [measure(run, 5.0) for run in runs]
    pooled = measure(runs, 5.0)
    assert pooled["requests"] == 80 and len(pooled["delivered_s"]) == 80
    assert pooled["run_means_s"] == pytest.approx([figures["mean_s"] for figures in alone])
    assert pooled["mean_s"] == pytest.approx((30 * alone[0]["mean_s"] + 50 * alone[1]["mean_s"]) / 80)
    assert pooled["p99_s"] == pytest.approx(np.percentile(alone[0]["delivered_s"] + alone[1]["delivered_s"], 99))
    assert "run_means_s" not in alone[0]
    # each run's own latencies, for the ratio to always-local over the pairs of runs (mean_ratio.py)
    for run, figures in zip(pooled["run_delivered_s"], alone):
        assert list(run) == pytest.approx(figures["delivered_s"])
    # each mean is its own run's, whatever order the runs are given in (the reader sorts the bags)
    assert measure(runs[::-1], 5.0)["run_means_s"] == pytest.approx(pooled["run_means_s"][::-1])


def test_the_hedge_runs_first_side_is_the_oracles_choice_and_only_its_local_plans_cost_cpu(tmp_path):
    # Both sides on every request: the side delivered first is the faster one, and a local plan that lost
    # (finished after the cloud's path, or was cancelled) is the probe's CPU, not what the oracle would spend.
    requests = []
    for i, (local_s, cloud_s, cpu_s) in enumerate([(0.05, 0.20, 0.010), (0.30, 0.10, 0.040),
                                                   (0.08, 0.09, 0.020), (0.50, 0.12, 0.070)]):
        decision, outcome = probe_request(2000 + i, 1.0, 0.5, 0.05, local_s, cloud_s, LOCAL, 1.0,
                                          reward(LOCAL, local_s, cloud_s))
        outcome.update(delivered=LOCAL if local_s <= cloud_s else CLOUD, robot_cpu_s=cpu_s)
        requests.append((decision, outcome))
    write(tmp_path / "offload.bag", requests)
    figures = measure(tmp_path, 5.0)
    assert figures["cloud_share"] == pytest.approx(0.5)
    assert figures["first_local_cpu_s_per_request"] == pytest.approx((0.010 + 0.020) / 4)
    assert figures["robot_cpu_s_per_request"] == pytest.approx((0.010 + 0.040 + 0.020 + 0.070) / 4)


def test_cloud_failures_count_link_failures_not_the_planners_verdicts(tmp_path):
    # A run the link-down window never touched has no cloud failure, and the bench says so instead of
    # reporting its figures as a link failure's.
    requests = []
    for i, status in enumerate((0, 9, 10, 7, 0)):       # OK, CLOUD_TIMEOUT, CLOUD_ERROR, NO_PATH, OK
        decision, outcome = probe_request(3000 + i, 1.0, 0.5, 0.05, 0.1, 0.2, CLOUD, 1.0, 0.0, probe=False)
        outcome.update(cloud_status=status)
        requests.append((decision, outcome))
    write(tmp_path / "offload.bag", requests)
    assert measure(tmp_path, 5.0)["cloud_failures"] == 2


def test_the_live_oracle_replays_each_requests_faster_side_in_request_order(tmp_path):
    # The hedge run's probes -> each request's faster side -> the learner's replay policy: request k of the oracle's
    # run takes the side that was faster for request k (a cloud side that timed out loses however short its time).
    from offload_msgs.srv import PlanPathResponse
    from offload_demos.hindsight import faster_sides
    from offload_learner_py.core.replay_policy import ReplayPolicy
    from offload_learner_py.core.state import State
    sides = [(0.05, 0.20), (0.30, 0.10), (0.08, 0.09), (0.50, 0.12), (0.40, 0.02), (0.06, 0.07), (0.20, 0.03)]
    requests = []
    for i, (local_s, cloud_s) in enumerate(sides):
        decision, outcome = probe_request(3000 + i, 1.0, 0.5, 0.05, local_s, cloud_s, LOCAL, 1.0,
                                          reward(LOCAL, local_s, cloud_s))
        if i == 4:
            outcome.update(cloud_status=PlanPathResponse.CLOUD_TIMEOUT, cloud_timeout=True)
        requests.append((decision, outcome))
    write(tmp_path / "offload.bag", requests)
    local_s, cloud_s = measure(tmp_path, 5.0)["request_sides_s"]
    assert local_s == pytest.approx([side[0] for side in sides])
    actions = faster_sides(local_s, cloud_s)
    assert actions.tolist() == [LOCAL, CLOUD, LOCAL, CLOUD, LOCAL, LOCAL, CLOUD]
    (tmp_path / "actions.txt").write_text("".join(f"{action}\n" for action in actions))
    replay = ReplayPolicy.from_file(str(tmp_path / "actions.txt"))
    state = State(1.0, 0.5, 0.05, 0.0)
    replayed = [replay.decide(state).action for _ in sides]
    chosen = [cloud if action == CLOUD else local for action, (local, cloud) in zip(replayed, sides)]
    assert replayed == actions.tolist()
    assert chosen == [min(side) if k != 4 else side[0] for k, side in enumerate(sides)]
    # past the list's end: local, counted
    assert replay.decide(state).action == LOCAL and replay.beyond == 1


def test_faster_sides_takes_the_measured_side_when_one_is_missing():
    from offload_demos.hindsight import faster_sides
    nan = float("nan")
    assert faster_sides([0.1, nan, 0.3, nan, 0.2], [nan, 0.2, 0.1, nan, 0.2]).tolist() == [LOCAL, CLOUD, CLOUD, LOCAL,
                                                                                           LOCAL]


def test_the_learning_run_learns_on_its_own_routing_below_a_probe_rate_of_one():
    from offload_demos.bench_policies import learning_args
    from offload_demos.driver import build_parser
    assert learning_args(1.0) == ["--policy", "dqn", "--mode", "learning"]
    args = build_parser().parse_args(["--launch", "x.launch"] + learning_args(0.3))
    assert (args.policy, args.mode, args.learn, args.probe_rate) == ("dqn", "deployed", "true", 0.3)


def test_oracle_agreement_weighs_each_choice_by_what_it_cost_on_the_probes(tmp_path):
    from offload_demos.oracle_agreement import agreement, request_actions
    nan = float("nan")
    local_s, cloud_s = [0.05, 0.30, 0.08, 0.50, nan], [0.20, 0.10, 0.09, 0.12, 0.04]
    figures = agreement([LOCAL, LOCAL, CLOUD, CLOUD, CLOUD], local_s, cloud_s)
    assert figures["agree"] == pytest.approx(3 / 5) and figures["oracle_cloud_share"] == pytest.approx(3 / 5)
    assert figures["probe_regret_s"] == pytest.approx((0.0 + 0.20 + 0.01 + 0.0) / 4)   # both sides measured only
    # a run's actions come back in request order
    requests = [probe_request(4000 + i, 1.0, 0.5, 0.05, 0.1, 0.2, action, 1.0, 0.0, probe=False)
                for i, action in enumerate([CLOUD, LOCAL, LOCAL, CLOUD])]
    write(tmp_path / "offload.bag", requests)
    assert request_actions(tmp_path).tolist() == [CLOUD, LOCAL, LOCAL, CLOUD]


def test_the_deployed_model_is_the_learning_runs_rows_trained_as_one_batch(tmp_path):
    """Every row of the learning run trains it (its normalisation is fitted on them all, not on a warm-up), it acts
    at once when loaded, and the same bag and seed give the same model."""
    from offload_learner_py.core.checkpoint import load_checkpoint
    from offload_learner_py.core.normalisation import StateNormalisation
    from offload_learner_py.data.bags import read_bags
    from offload_learner_py.data.records import transition_table
    from offload_demos.bench_policies import batch_checkpoint
    write(tmp_path / "offload.bag", make_requests(90, seed=4, probe_every=1))
    table = transition_table(read_bags([str(tmp_path / "offload.bag")], workers=1).log)
    assert len(table) == 90
    agent = load_checkpoint(batch_checkpoint(tmp_path, seed=3))
    assert agent.normalisation == StateNormalisation.fit(table.states)
    assert not agent.in_warm_up()
    again = load_checkpoint(batch_checkpoint(tmp_path, seed=3))
    np.testing.assert_array_equal(again.q_values(table.states), agent.q_values(table.states))


def _table_row(cloud_calls, per_cloud):
    return {"requests": 10, "paths_delivered": 10, "mean_s": 0.05, "p50_s": 0.04, "p95_s": 0.09, "p99_s": 0.1,
            "robot_cpu_s_per_request": 0.003, "bridge_cpu_s_per_request": 0.0002, "learner_cpu_s_per_request": 0.0001,
            "robot_total_cpu_s_per_request": None, "robot_workload_cpu_s_per_request": None,
            "link_bytes_per_request": 2048.0, "cloud_timeouts": 0, "cloud_share": 0.4, "cloud_calls": cloud_calls,
            "bridge_cpu_s_per_cloud_request": per_cloud}


def test_the_table_gives_the_bridge_cost_per_cloud_request_of_a_policy_that_asked_the_cloud():
    from offload_demos.bench_report import format_table
    text = format_table({"policies": {"dqn": _table_row(4, 0.00045), "local": _table_row(0, float("nan"))}})
    assert "dqn: the bridge's own accounting per cloud request 0.450 ms (4 requests asked the cloud)" in text
    assert "local: the bridge's" not in text


def test_the_scenario_table_gives_the_gap_closed_within_each_round_of_repeats():
    from offload_demos.bench_report import format_scenario_table, scenario_rows
    runs = {"threshold_best": [0.040, 0.046], "oracle": [0.038, 0.036], "dqn": [0.041, 0.039]}
    results = {"scenario": "pulse", "policies": {
        name: {**_table_row(0, None), "mean_s": float(np.mean(means)), "run_means_s": means}
        for name, means in runs.items()}}
    rows = {row["policy"]: row for row in scenario_rows(results)}
    # Round 1: 40 -> 38, the DQN at 41 is half the gap worse; round 2: 46 -> 36, the DQN at 39 closes 70 %.
    assert rows["dqn"]["gap_closed_runs"] == pytest.approx([-0.5, 0.7])
    assert rows["dqn"]["gap_closed"] == pytest.approx((0.043 - 0.040) / (0.043 - 0.037))
    assert rows["oracle"]["gap_closed_runs"] == pytest.approx([1.0, 1.0])
    assert "-50 %, 70 %" in format_scenario_table(results)
    # Two rounds that disagree this much do not tell the gap from zero: the table says so rather than give a range.
    assert rows["dqn"]["gap_closed_interval"]["rounds"] == 2 and rows["dqn"]["gap_closed_interval"]["low"] is None
    assert "no bound" in format_scenario_table(results)
    one_round = {"policies": {name: {**f, "run_means_s": f["run_means_s"][:1]}
                              for name, f in results["policies"].items()}}
    assert all(row["gap_closed_runs"] is None and row["gap_closed_interval"] is None
               for row in scenario_rows(one_round))
