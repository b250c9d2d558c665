"""bench-fleet-learning's figures (#30 item 8): the per-request side table pooled over a robot's runs, each arm's
decisions scored with it (like with like: never a delivered latency against a side's, never the other side's),
requests until the trailing mean is within 5 % of the best decisions', the first-300 means, a bad model's cost and
rollback, and the bench's loop over robots and arms on synthetic runs (no ROS)."""
import json

import numpy as np
import pytest

from bagtools import write
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.reward import reward
from offload_demos import bench_fleet_learning as bench
from offload_demos import fleet_metrics
from offload_demos.bag_writer import probe_request


def test_the_side_table_averages_both_sides_over_the_runs_that_measured_both():
    a = {"local_s": [0.1, 0.2, np.nan, 0.4], "cloud_s": [0.3, 0.1, 0.2, np.nan]}
    b = {"local_s": [0.3, np.nan, 0.5], "cloud_s": [0.1, 0.2, 0.6]}
    table = fleet_metrics.side_table([a, b])
    # request 0: both runs; 1: a alone (b measured one side); 2: b alone; 3: no run measured both
    assert table[LOCAL] == pytest.approx([0.2, 0.2, 0.5, np.nan], nan_ok=True)
    assert table[CLOUD] == pytest.approx([0.2, 0.1, 0.6, np.nan], nan_ok=True)
    assert fleet_metrics.best_latency(table) == pytest.approx([0.2, 0.1, 0.5, np.nan], nan_ok=True)
    # a decision costs its own side's latency, never the other's
    assert fleet_metrics.decision_latency([CLOUD, LOCAL, CLOUD, CLOUD], table) == pytest.approx(
        [0.2, 0.2, 0.6, np.nan], nan_ok=True)


def test_requests_to_within_is_the_first_window_that_gets_there():
    best = np.full(200, 0.10)
    decided = np.concatenate([np.full(100, 0.20), np.full(100, 0.10)])
    # the window of 50 ending at k holds (100 - (k - 50)) slow requests: its mean is at most 0.105 from k = 148
    assert fleet_metrics.requests_to_within(decided, best, 0.05, 50) == 148
    assert fleet_metrics.requests_to_within(decided, best, 0.05, 10) == 110
    assert fleet_metrics.requests_to_within(np.full(200, 0.2), best) is None
    # only requests with both sides in the table are scored: a window with fewer than min_known cannot be judged
    sparse = np.full(200, np.nan)
    sparse[::20] = 0.10
    assert fleet_metrics.requests_to_within(np.full(200, 0.1), sparse, window=50, min_known=3) == 50
    assert fleet_metrics.requests_to_within(np.full(200, 0.1), sparse, window=50, min_known=4) is None
    # a shorter table (a shorter oracle run) leaves the rest unknown
    assert fleet_metrics.requests_to_within(np.full(200, 0.1), np.full(60, 0.1), window=50) == 50
    with pytest.raises(ValueError):
        fleet_metrics.requests_to_within(decided, best, tolerance=1.5)


def two_side_runs(n=200, seed=0):
    """An oracle run (both sides, local faster: 3 ms against 10 ms) and an arm's run that decided local on every
    request, on a machine 30 % slower that run, delivered 1 ms of routing over its side."""
    rng = np.random.default_rng(seed)
    local_s = 0.003 * (1 + 0.1 * rng.random(n))
    oracle = {"local_s": local_s, "cloud_s": np.full(n, 0.010), "action": np.full(n, LOCAL),
              "delivered_s": local_s + 0.001}
    arm_local = 1.3 * local_s
    arm = {"local_s": arm_local, "cloud_s": np.full(n, np.nan), "action": np.full(n, LOCAL),
           "delivered_s": arm_local + 0.001}
    return oracle, arm


def test_an_arm_deciding_as_the_best_decisions_is_within_at_once_whatever_its_delivered_latency():
    oracle, arm = two_side_runs()
    table = fleet_metrics.side_table([oracle, arm])
    figures = fleet_metrics.arm_figures(arm, table, first=300, window=50)
    assert figures["requests_to_within"] == 50
    assert figures["first"]["decided_mean_s"] == pytest.approx(figures["first"]["best_mean_s"])
    assert figures["first"]["mean_s"] == pytest.approx(np.mean(arm["delivered_s"]))   # the live figure, beside it
    # what the measure of 2026-11-26 did: the delivered mean against the oracle's side latency, never within
    assert fleet_metrics.requests_to_within(arm["delivered_s"], fleet_metrics.best_latency(table)) is None


def test_an_arm_deciding_the_slower_side_is_never_within():
    oracle, arm = two_side_runs()
    arm = {**arm, "action": np.full(200, CLOUD), "cloud_s": np.full(200, 0.011), "local_s": np.full(200, np.nan)}
    table = fleet_metrics.side_table([oracle, arm])
    assert fleet_metrics.arm_figures(arm, table)["requests_to_within"] is None
    assert fleet_metrics.arm_figures(arm, table)["first"]["local_share"] == 0.0
    # scored with the other side's latency it would look perfect
    swapped = fleet_metrics.decision_latency(1 - arm["action"], table)
    assert fleet_metrics.requests_to_within(swapped, fleet_metrics.best_latency(table)) == 50


def test_the_first_mean_counts_what_there_is():
    assert fleet_metrics.first_mean(np.arange(400.0), 300) == {"mean_s": pytest.approx(149.5), "requests": 300}
    assert fleet_metrics.first_mean([1.0, 3.0], 300) == {"mean_s": 2.0, "requests": 2}


def test_a_bad_models_cost_is_its_decisions_over_the_best_until_the_rollback():
    versions = ["good"] * 10 + ["bad"] * 8 + ["good"] * 5
    delivered = np.full(23, 0.1)
    delivered[10:18] = 0.3
    oracle = np.full(23, 0.1)
    oracle[12] = np.nan             # not every request's best decision is known
    cost = fleet_metrics.bad_model_cost(versions, "bad", delivered, oracle, rolled_back_at=18)
    assert cost["requests_under_bad"] == 8 and cost["requests_to_rollback"] == 8 and cost["rolled_back"]
    assert cost["scored"] == 7
    assert cost["excess_s"] == pytest.approx(7 * 0.2) and cost["excess_s_per_request"] == pytest.approx(0.2)
    never = fleet_metrics.bad_model_cost(versions[:18], "bad", delivered[:18], oracle[:18])
    assert not never["rolled_back"] and never["requests_to_rollback"] is None and never["requests_under_bad"] == 8
    assert fleet_metrics.bad_model_cost(versions, "other", delivered, oracle)["requests_under_bad"] == 0
    # the decisions' model_version column says when the guard rolled it back
    assert fleet_metrics.rollback_index(versions, "bad") == 18
    assert fleet_metrics.rollback_index(versions[:18], "bad") is None
    assert fleet_metrics.rollback_index(versions, "other") is None


def synthetic_run(path, learns_after, n=120, seed=0, probe_every=1, bad=()):
    """n requests whose local side is 0.05 s and cloud 0.2 s; a robot that offloads until `learns_after`, then
    plans locally; every probe_every-th request measures both sides. Requests in range `bad` are decided by the
    model version "bad" (always the cloud), the others by "good"."""
    rng = np.random.default_rng(seed)
    requests = []
    for i in range(n):
        local_s, cloud_s = 0.05 + 0.001 * rng.random(), 0.2
        action = CLOUD if i < learns_after or i in bad else LOCAL
        decision, outcome = probe_request(5000 + i, 1.0, 0.5, 0.05, local_s, cloud_s, action, 1.0,
                                          reward(action, local_s, cloud_s), probe=i % probe_every == 0)
        decision["model_version"] = "bad" if i in bad else "good"
        outcome["delivered_s"] = local_s if action == LOCAL else cloud_s
        requests.append((decision, outcome))
    write(path / "offload.bag", requests)
    return path


class FakePush:
    def __init__(self, store_dir, at, robot=""):
        self.store_dir, self.version, self.error = store_dir, "bad", ""


def test_the_bench_loops_over_robots_and_arms_and_reports(tmp_path, monkeypatch, capsys):
    learns_after = {"oracle": 0, "alone": 80, "fleet": 20, "bad_model": 0}
    calls, keyed = [], []

    def fake_run(launch, runs_dir, steps, seed, map_yaml, extra, progress=""):
        arm = runs_dir.name
        calls.append((runs_dir.parent.name, arm, map_yaml, extra))
        run = runs_dir / "20260101-000000"
        run.mkdir(parents=True)
        return synthetic_run(run, learns_after[arm], probe_every=1 if arm == "oracle" else 20,
                             bad=range(40, 52) if arm == "bad_model" else ())
    monkeypatch.setattr(bench, "run_demo", fake_run)
    monkeypatch.setattr(bench, "fleet_missing", lambda: "")
    monkeypatch.setattr(bench, "ensure_demo_robots", lambda root, names: keyed.extend(names))
    monkeypatch.setattr(bench, "DelayedPush", FakePush)
    assert bench.main(["--runs-dir", str(tmp_path), "--steps", "120", "--first", "100", "--window", "20"]) == 0
    assert len(calls) == 3 * len(bench.ROBOTS) + 1 and keyed == [robot.name for robot in bench.ROBOTS]
    # each run as its own robot; the fleet runs share one store; the bad model goes to the first robot's fleet run
    fleet_runs = [call for call in calls if call[1] in ("fleet", "bad_model")]
    assert all("--fleet" in call[3] and call[3][call[3].index("--robot-key") + 1] == call[0] for call in fleet_runs)
    assert len({call[3][call[3].index("--fleet-store") + 1] for call in fleet_runs}) == 1
    assert calls[-1][:2] == ("turtlebot-edge", "bad_model")
    assert {call[0] for call in calls} == {robot.name for robot in bench.ROBOTS}
    husky = [call for call in calls if call[0] == "husky-wan" and call[1] == "alone"][0]
    assert husky[3][husky[3].index("--budget-cores") + 1] == "0.25" and "wan" in husky[3]
    assert husky[2].endswith("playpen_map.yaml")
    results = json.loads(next(tmp_path.glob("bench-fleet-learning-*/results.json")).read_text())
    robot = results["robots"]["turtlebot-edge"]
    assert robot["best_mean_s"] == pytest.approx(0.0505, abs=0.001)
    # within 5 % once the last 20 requests are all local: 20 after the switch
    assert robot["arms"]["alone"]["requests_to_within"] == 100
    assert robot["arms"]["fleet"]["requests_to_within"] == 40
    assert robot["arms"]["alone"]["first"]["requests"] == 100
    assert robot["arms"]["alone"]["first"]["mean_s"] == pytest.approx((80 * 0.2 + 20 * 0.0505) / 100, abs=1e-3)
    assert robot["arms"]["alone"]["first"]["decided_mean_s"] == pytest.approx((80 * 0.2 + 20 * 0.0505) / 100,
                                                                              abs=1e-3)
    assert robot["arms"]["alone"]["first"]["local_share"] == 0.2
    assert results["fleet_fewer_requests"] == len(bench.ROBOTS)
    # the bad model decided requests 40-51 (0.2 s each against the oracle's 0.05) and was rolled back at 52
    bad = results["bad_model"]
    assert bad["robot"] == "turtlebot-edge" and bad["requests_to_rollback"] == 12 and bad["rolled_back"]
    assert bad["excess_s_per_request"] == pytest.approx(0.2 - 0.0505, abs=0.001)
    out = capsys.readouterr().out
    assert "fleet fewer requests to 5 % than alone: 4 of 4 robots" in out
    assert "turtlebot-edge: 12 requests to rollback" in out and "delivered live" in out


def test_without_the_fleet_pieces_the_fleet_arm_says_why(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench, "run_demo", lambda launch, runs_dir, *a, **k: synthetic_run(
        (runs_dir / "r").mkdir(parents=True) or runs_dir / "r", 0 if runs_dir.name == "oracle" else 30))
    monkeypatch.setattr(bench, "fleet_missing", lambda: "no robot fleet mode")
    assert bench.main(["--runs-dir", str(tmp_path), "--robots", "husky-wan", "--steps", "120", "--window", "20"]) == 0
    results = json.loads(next(tmp_path.glob("bench-fleet-learning-*/results.json")).read_text())
    assert "fleet" not in results["robots"]["husky-wan"]["arms"] and results["fleet_fewer_requests"] is None
    assert "n/a" in capsys.readouterr().out


def test_fleet_missing_looks_for_the_robots_fleet_mode(tmp_path):
    (tmp_path / "launch").mkdir()
    (tmp_path / "launch" / "robot.launch").write_text('<launch><arg name="model" default=""/></launch>')
    assert "fleet_endpoint" in bench.fleet_missing(tmp_path)
    (tmp_path / "launch" / "robot.launch").write_text('<launch><arg name="fleet_endpoint" default=""/></launch>')
    assert "fleet_endpoint" not in bench.fleet_missing(tmp_path)
