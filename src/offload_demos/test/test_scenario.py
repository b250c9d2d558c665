"""bench-policies' scenarios: the shipped files load, bad files are refused with the key and the reason, and every
policy's run is given the same schedule request by request."""
import pathlib

import pytest

from offload_demos import bench_policies, driver
from offload_demos.scenario import NAMED, Scenario, ScenarioError, load_scenario
from offload_demos.workload import StepLoad

MAPS = pathlib.Path(__file__).resolve().parents[2] / "offload_planner_cpp" / "maps"


def conditions_of(argv) -> tuple:
    """What a run's requests meet, from its driver command line read back as the driver reads it: the seed, the
    launch's map, and (time, base round trip, load level, map) of every request."""
    args = driver.build_parser().parse_args(argv)
    scenario = load_scenario(args.scenario or "stationary")
    if args.link:     # a link profile named on the command line is the run's link
        scenario = Scenario(**{**scenario.__dict__, "link": args.link, "rtt_trace": None})
    return args.seed, args.map, args.start_lead_s, scenario.per_request(args.steps, args.goal_rate_hz, args.seed)


def fake_figures(run_dir, cloud_timeout_s):
    """measure()'s figures of a run that did not happen (no bag): numbers to let the bench go on."""
    figures = {field: 0.05 for field in bench_policies.FIELDS}
    figures.update(requests=60, paths_delivered=60, cloud_timeouts=0, robot_cpu=None, cloud_share=0.5,
                   first_local_cpu_s_per_request=0.01, probe_oracle_mean_s=0.04, delivered_s=[0.05] * 60,
                   run_dir=str(run_dir), probe_rows=([0.5, 1.0, 2.0], [0.01, 0.05, 0.3], [0.06, 0.05, 0.07]),
                   request_sides_s=([0.01, 0.05, 0.3], [0.06, 0.05, 0.07]))
    return figures


def bench_commands(argv, tmp_path, monkeypatch) -> dict:
    """Each run's driver command line as bench-policies builds it for these options (the learning run's too), the
    runs themselves faked."""
    captured = {}

    def fake_run(launch, runs_dir, steps, seed, map_yaml, extra, progress=""):
        runs_dir = pathlib.Path(runs_dir)
        captured[runs_dir.name] = bench_policies.demo_command(launch, runs_dir, steps, seed, map_yaml, extra)[3:]
        (runs_dir / "run").mkdir(parents=True)
        return runs_dir / "run"
    monkeypatch.setattr(bench_policies, "run_demo", fake_run)
    monkeypatch.setattr(bench_policies, "measure", fake_figures)
    assert bench_policies.main(argv + ["--runs-dir", str(tmp_path)]) == 0
    return captured


@pytest.mark.parametrize("name", NAMED)
def test_every_policy_meets_the_same_schedule_request_by_request(name, tmp_path, monkeypatch):
    # each scenario's own length: its changes (a handover at 30 s, a map switch at request 100) happen within it
    commands = bench_commands(["--scenario", name, "--outage-policies", ""], tmp_path, monkeypatch)
    assert set(commands) == set(bench_policies.POLICIES) | {"learning"}
    seen = {run: conditions_of(argv) for run, argv in commands.items()}
    reference = seen["local"]
    assert len(reference[3]) == load_scenario(name).steps
    for run, schedule in seen.items():
        if run == "learning":     # its own length (--learning-steps); the same schedule over it
            length = min(len(schedule[3]), len(reference[3]))
            assert schedule[:3] == reference[:3] and schedule[3][:length] == reference[3][:length]
            continue
        assert schedule == reference, f"{run} meets another schedule than local on scenario {name}"


def test_the_shipped_scenarios_change_what_they_say():
    per = {name: load_scenario(name).per_request(480, 4.0, 1) for name in NAMED}
    rtt = lambda name, t0, t1: {r for t, r, _, _ in per[name] if t0 <= t < t1}   # noqa: E731
    assert max(rtt("handover", 0, 30)) <= 0.06 and max(rtt("handover", 30, 60)) >= 0.16   # edge, then WAN
    assert rtt("handover", 60, 90) == rtt("handover", 0, 30)                              # and back
    loads = {t: level for t, _, level, _ in per["load-shift"]}
    assert loads[10.0] == 0.1 and loads[45.0] == 0.85 and loads[95.0] == 0.1
    drift = [r for _, r, _, _ in per["drift"]]
    assert drift == sorted(drift) and drift[0] == 0.01 and drift[-1] == 0.4
    maps = [m for _, _, _, m in load_scenario("map-switch").per_request(400, 4.0, 1)]
    assert maps[:100] == [maps[0]] * 100 and maps[100:200] == [maps[100]] * 100 and maps[0] != maps[100]
    assert maps[200:300] == maps[:100]
    assert load_scenario("stationary").per_request(200, 4.0, 1)[199][0] == pytest.approx(199 / 4.0)


def test_a_map_switch_pauses_the_open_loop_schedule_the_same_in_every_run():
    scenario = load_scenario("map-switch")
    times = scenario.request_times(250, 4.0)
    assert times[99] == pytest.approx(99 / 4.0) and times[100] == pytest.approx(100 / 4.0 + 2.0)
    assert times[200] == pytest.approx(200 / 4.0 + 4.0)


def write(tmp_path, text, name="s.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("text, says", [
    ("link: edge\nrtt_trace: x.txt\n", "exactly one of link"),
    ("steps: 100\n", "exactly one of link"),
    ("link: lte\n", "link: expected edge or wan"),
    ("link: edge\nspeed: 3\n", "unknown keys ['speed']"),
    ("rtt_trace: missing.txt\n", "rtt_trace: "),
    ("rtt_trace: bad.txt\n", "expected `time_s rtt_ms`"),
    ("link: edge\nload: {schedule: [[0, 0.2], [30, 1.5]]}\n", "[0, 1)"),
    ("link: edge\nload: {schedule: [[5, 0.2]]}\n", "start at 0 and increase"),
    ("link: edge\nload: {schedule: [[0, 0.2], [30, 0.5], [20, 0.1]]}\n", "start at 0 and increase"),
    ("link: edge\nload: {schedule: [0, 0.2]}\n", "[time_s, level] pairs"),
    ("link: edge\nload: busy\n", "load: expected"),
    ("link: edge\nmaps: [{map: nowhere.yaml, requests: 10}]\n", "maps[0].map"),
    ("link: edge\nmaps: [{map: package://offload_planner_cpp/maps/turtlebot3_world/map.yaml, requests: 0}]\n",
     "maps[0].requests: expected a positive integer"),
    ("link: edge\nmaps: [{map: package://no_such_package/m.yaml}]\n", "no ROS package 'no_such_package'"),
    ("link: edge\nmaps: [{map: bad.txt}]\n", "maps[0].map"),
    ("link: edge\nsteps: 5\n", "steps: expected an integer >= 10"),
    ("link: edge\nmap_settle_s: -1\n", "map_settle_s"),
    ("- link\n", "expected a mapping"),
    ("link: [edge\n", "not readable YAML"),
])
def test_a_bad_scenario_file_is_refused_with_its_key_and_reason(tmp_path, text, says):
    (tmp_path / "bad.txt").write_text("0 20\n10 fast\n")
    with pytest.raises(ScenarioError) as error:
        load_scenario(write(tmp_path, text))
    assert says in str(error.value)


def test_a_users_own_scenario_names_its_trace_load_and_maps_relative_to_itself(tmp_path):
    (tmp_path / "logged.txt").write_text("# time_s rtt_ms from our robot\n0 15\n20 250\n40 15\n")
    path = write(tmp_path, f"rtt_trace: logged.txt\nload: {{schedule: [[0, 0.2], [10, 0.7], [20, 0.2]]}}\n"
                           f"maps:\n  - {{map: {MAPS}/turtlebot3_world/map.yaml, requests: 5}}\n"
                           f"  - {{map: {MAPS}/husky_playpen/playpen_map.yaml, requests: 3}}\nsteps: 20\n")
    scenario = load_scenario(path)
    assert scenario.rtt_trace == tmp_path / "logged.txt" and isinstance(scenario.load, StepLoad)
    rows = scenario.per_request(16, 1.0, 7)
    assert [m.split("/")[-2] for *_, m in rows[:9]] == ["turtlebot3_world"] * 5 + ["husky_playpen"] * 3 + \
        ["turtlebot3_world"]
    assert rows[0][1:3] == (0.015, 0.2) and rows[12][1:3] == (0.015, 0.7)   # 12 s + one 2 s map pause: t = 14


def test_an_unknown_name_or_missing_file_is_refused():
    with pytest.raises(ScenarioError, match="neither one of stationary"):
        load_scenario("rush-hour")


def test_the_bench_and_the_driver_refuse_a_bad_scenario_before_anything_runs(tmp_path, capsys):
    bad = write(tmp_path, "link: lte\n")
    with pytest.raises(SystemExit):
        bench_policies.main(["--scenario", bad, "--runs-dir", str(tmp_path)])
    assert "link: expected edge or wan" in capsys.readouterr().err
    assert driver.main(["--launch", "x", "--scenario", bad, "--runs-dir", str(tmp_path)]) == 2
    assert "link: expected edge or wan" in capsys.readouterr().err
    assert not any(tmp_path.glob("bench-policies-*"))


def test_a_load_schedule_loops_after_its_last_step_like_a_trace():
    load = StepLoad(((0.0, 0.1), (30.0, 0.85), (90.0, 0.1), (120.0, 0.1)))
    assert [load.level_at(t) for t in (0, 29.9, 30, 89, 90, 125, 150, 215)] == [0.1, 0.1, 0.85, 0.85, 0.1, 0.1,
                                                                                0.85, 0.1]
    assert StepLoad(((0.0, 0.4),)).level_at(1e6) == 0.4


def test_the_schedule_lag_is_how_late_a_run_kept_the_open_loop_schedule():
    nominal = [0.0, 0.25, 0.5, 0.75]
    assert bench_policies.schedule_lag_s([[0.0, 0.25, 0.5, 0.75]], nominal) == pytest.approx(0.0)
    assert bench_policies.schedule_lag_s([[0.0, 0.25, 0.5, 0.75], [0.0, 0.3, 1.4, 1.5]], nominal) == pytest.approx(0.9)
    assert bench_policies.schedule_lag_s([], nominal) is None


@pytest.mark.parametrize("policies", ["threshold_best", "threshold_best,hedge", "local,threshold_best"])
def test_threshold_best_needs_the_hedge_run_before_it(policies, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench_policies.main(["--policies", policies, "--runs-dir", str(tmp_path)])
    assert "list hedge before it" in capsys.readouterr().err
