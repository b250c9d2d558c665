"""`make bench-policies`: every routing policy live, its decisions acting, on the same seeded conditions.

Each policy runs the demo's whole stack (`make demo`: the robot's processes on one core inside a CPU budget
with the seeded workload schedule, the cloud server on the other core behind the WAN emulator and its RTT
trace, the same seeded goal sequence) for STEPS requests. The conditions are the same request by request:
the RTT trace, the workload schedule and the goals start together (--start-lead-s after the launch) and the
requests arrive open-loop (--goal-rate-hz), so request k meets the same moment of the link and the load in
every run. (Paced by the answers instead, a slower policy met later, other parts of the schedules.)

- local, cloud: always plan on the robot / always offload (deployed, no probes);
- hedge: both sides on every request, the caller gets the first good path (learning mode, frozen policy);
- threshold: offload above the paper's input-size threshold;
- threshold_best: the same rule at the best threshold in hindsight: the one of an exhaustive grid with the lowest
  mean latency on the hedge run's probes (both sides measured, offload_demos.hindsight), then run live;
- oracle: each request's faster side in the hedge run's probes (offload_demos.hindsight.faster_sides), replayed live
  request by request (the learner's replay policy, deployed, no probes): the gap from threshold_best to the oracle and
  every policy's share of it are live means on one footing (the probe oracle, both sides at once on the robot's
  budget, is printed beside it: a one-sided policy can beat it);
- latency_bound: offload when the last round trip plus the cloud's recent planning time is below the robot's
  predicted planning time, as FogROS2-LS routes by a latency bound (deployed, the learner's default probe rate);
- dqn: the DQN deployed as it ships (at the learner's default probe rate): the robot decides and never trains, a
  fleet learner on the cloud side (offload-cloud-learner) pools its rows, trains and publishes model versions that
  reach the robot as they would in the field. Both start from a learning run on the same map: the robot from its
  checkpoint, the fleet learner from its bag (a first version trained from it before the requests begin);
- dqn_hedge: the same with the deadline hedge.

SCENARIO (--scenario, offload_demos.scenario): the conditions, a named one (stationary, the default and the demo's
conditions; handover, load-shift, map-switch, drift) or a YAML file; every run, the learning run included, gets the
same scenario arguments. It reports, per policy, latency as the caller saw it (mean, p50, p95, p99), robot planning CPU-seconds and
link bytes per request, paths delivered and cloud timeouts, with the oracle measured on the hedge run's
probes (both sides every request). A last run stops the cloud link for 30 s mid-run (the WAN
emulator drops everything) while the RTT trace jumps, and reports the worst wait and how many requests
waited the cloud timeout. Results go to runs/bench-policies-<time>/results.json, a figure and a table.
With always-local among the policies, each other policy's mean is given as a ratio to local's with a 95 % interval
over the repeats (offload_demos.mean_ratio: the runs' spread, not the requests', is the bench's noise); for the same
reason the scenario table gives each policy's share of the threshold_best-to-oracle gap within each round of repeats
beside the pooled share, and an interval for the share over the rounds (offload_demos.gap_share; it pools benches).
"""
import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
from offload_cloud.cli_args import bounded_float, bounded_int
from offload_demos.bench_measure import measure
from offload_demos.bench_report import format_scenario_table, format_table, plot, scenario_rows
from offload_demos.hindsight import best_threshold, faster_sides
from offload_demos.mean_ratio import MeanRatio, ratios_to
from offload_demos.scenario import NAMED, ScenarioError, load_scenario
from offload_learner_py.online.router_types import RouterConfig
from offload_demos.driver import LINK_PROFILES

POLICIES = ("local", "cloud", "hedge", "threshold", "threshold_best", "oracle", "latency_bound", "dqn", "dqn_hedge")
HINDSIGHT = ("threshold_best", "oracle")     # chosen on the hedge run's probes: hedge runs before them
RUNS = {
    "local": ["--policy", "local", "--mode", "deployed", "--probe-rate", "0"],
    "cloud": ["--policy", "cloud", "--mode", "deployed", "--probe-rate", "0"],
    "hedge": ["--policy", "local", "--mode", "learning", "--learn", "false"],
    "threshold": ["--policy", "threshold", "--mode", "deployed", "--probe-rate", "0"],
    "threshold_best": ["--policy", "threshold", "--mode", "deployed", "--probe-rate", "0"],   # + its learner config
    "oracle": ["--policy", "replay", "--mode", "deployed", "--probe-rate", "0"],               # + its learner config
    "latency_bound": ["--policy", "latency_bound", "--mode", "deployed"],
    "dqn": ["--policy", "dqn", "--mode", "deployed", "--fleet"],
    "dqn_hedge": ["--policy", "dqn", "--mode", "deployed", "--hedge", "--fleet"],
}
FIELDS = ("requests", "paths_delivered", "mean_s", "p50_s", "p95_s", "p99_s", "robot_cpu_s_per_request",
          "bridge_cpu_s_per_request", "bridge_cpu_s_per_cloud_request", "cloud_calls", "learner_cpu_s_per_request",
          "robot_total_cpu_s_per_request", "robot_workload_cpu_s_per_request", "robot_cpu", "link_bytes_per_request",
          "cloud_timeouts", "cloud_share")


def demo_command(launch: str, runs_dir: pathlib.Path, steps: int, seed: int, map_yaml: str, extra) -> list:
    """The driver's command line of one run."""
    command = [sys.executable, "-m", "offload_demos.driver", "--launch", launch, "--steps", str(steps),
               "--seed", str(seed), "--runs-dir", str(runs_dir), "--no-report", *extra]
    return command + (["--map", map_yaml] if map_yaml else [])


def conditions(args, scenario) -> list:
    """The driver options that set what the requests meet, one list for every run of the bench (the test checks the
    schedule they make is the same request by request for every policy). The stationary scenario passes only its
    link, as before scenarios: the demo's conditions, unchanged."""
    given = ["--scenario", str(scenario.path)] if (scenario.rtt_trace or scenario.load or scenario.maps) else []
    return given + (["--link", args.link or scenario.link] if not scenario.rtt_trace else []) + [
        "--goal-rate-hz", f"{args.goal_rate_hz:g}", "--start-lead-s", f"{args.start_lead_s:g}"] + (
        ["--plan-unknown"] if args.plan_unknown else [])


def policy_args(name: str, scenario_args: list, model: list, threshold_config: str = "", oracle_config: str = "") -> list:
    """One policy's driver options: how it routes, then the bench's conditions."""
    extra = RUNS[name] + (model if name.startswith("dqn") else [])
    if name in HINDSIGHT:
        extra = extra + ["--learner-config", threshold_config if name == "threshold_best" else oracle_config]
    return extra + scenario_args


def learning_args(probe_rate: float) -> list:
    """The learning run's routing: every request a probe (learning mode), or its own greedy choices with a share of
    probes and learning on (deployed mode: the other side's latency imputed, as a deployed robot that learns)."""
    if probe_rate >= 1.0:
        return ["--policy", "dqn", "--mode", "learning"]
    return ["--policy", "dqn", "--mode", "deployed", "--learn", "true", "--probe-rate", f"{probe_rate:g}"]


def batch_checkpoint(learning_run: pathlib.Path, seed: int) -> str:
    """The learning run's rows trained as one batch (offline/retrain's training, the fleet learner's: every row
    alike, the normalisation fitted on them all), saved beside the run's online checkpoint. The online DQN samples
    its replay from the start of the run on, so a row of the first seconds is trained on far more often than one
    of the last (on handover: the first edge phase), and its normalisation is its warm-up's."""
    from offload_learner_py.core.checkpoint import save_checkpoint
    from offload_learner_py.core.config import DQNConfig
    from offload_learner_py.data.bags import read_bags
    from offload_learner_py.data.records import cloud_answered, transition_table
    from offload_learner_py.offline.retrain import train_offline
    data = read_bags([str(learning_run / "offload.bag")], workers=1)
    table = transition_table(data.log)
    if not len(table):
        raise RuntimeError(f"the learning run {learning_run} has no probe with both sides measured")
    path = learning_run / "checkpoint_batch.pt"
    agent = train_offline(table, DQNConfig(seed=seed), cloud_answered=cloud_answered(data.log)).agent
    save_checkpoint(agent, str(path))
    return str(path)


def schedule_lag_s(arrivals, nominal) -> float:
    """How late, at most, a run's requests arrived against the open-loop schedule (each run from its first request):
    above one inter-arrival a policy's answers held its requests back, and they met later moments of the link and
    the load than the other policies' did."""
    lags = [arrived - planned + nominal[0] for run in arrivals for arrived, planned in zip(run, nominal)]
    return max(lags) if lags else None


def run_demo(launch: str, runs_dir: pathlib.Path, steps: int, seed: int, map_yaml: str, extra,
             progress: str = "") -> pathlib.Path:
    """One live run of the demo stack; the run directory it wrote. `progress` ("3/8, about 6 min left")
    heads the line that announces it."""
    command = demo_command(launch, runs_dir, steps, seed, map_yaml, extra)
    print(f"bench-policies {progress}:" if progress else "bench-policies:", " ".join(command[3:]), flush=True)
    completed = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    (runs_dir / "demo.log").write_text(completed.stdout)
    runs = sorted(path for path in runs_dir.iterdir() if path.is_dir())
    if completed.returncode != 0 or not runs:
        raise RuntimeError(f"demo run failed (exit {completed.returncode}); see {runs_dir / 'demo.log'}")
    return runs[-1]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--launch", default="launch/offload_demo.launch")
    parser.add_argument("--map", default="", help="map_server YAML (default: the demo's, the nav2 warehouse)")
    parser.add_argument("--scenario", default="stationary",
                        help=f"{', '.join(NAMED)} or a scenario YAML file (offload_demos/scenarios/ shows the form)")
    parser.add_argument("--link", choices=LINK_PROFILES, help="the demo's link profile (default: the scenario's)")
    parser.add_argument("--plan-unknown", action="store_true", help="plan and draw goals through unknown cells")
    parser.add_argument("--steps", type=bounded_int("--steps", 10, 100000), help="requests per run (default: the "
                        "scenario's: 200 for stationary)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--policies", default=",".join(POLICIES), help="comma list of " + ",".join(POLICIES))
    parser.add_argument("--checkpoint", default="", help="DQN checkpoint to deploy (default: a learning run first)")
    parser.add_argument("--seed-bag", default="", help="with --checkpoint: the bag the fleet learner starts from "
                                                        "(default: the learning run's; none with --checkpoint)")
    parser.add_argument("--learning-steps", type=bounded_int("--learning-steps", 10, 100000), default=300)
    parser.add_argument("--learning-probe-rate", type=bounded_float("--learning-probe-rate", 0.0, 1.0, low_open=True),
                        default=1.0, help="1: the learning run probes every request (learning mode, the paper's); "
                        "below 1: it routes by its own greedy policy and probes this share (deployed mode, learning "
                        "on), so it learns the local latencies of the load its own routing leaves on the robot")
    parser.add_argument("--deploy-model", choices=("batch", "online"), default="online",
                        help="the DQN the robot starts from: the learning run's online checkpoint, or its rows trained "
                             "as one batch (the fleet learner's training; on handover 2026-11-27 not better live)")
    parser.add_argument("--outage-policies", default="dqn_hedge",
                        help="policies run again with the link down for --outage-s mid-run ('' to skip)")
    parser.add_argument("--outage-at-s", type=bounded_float("--outage-at-s", 0.0), default=30.0,
                        help="seconds after the WAN emulator starts (requests begin about 15 s after it)")
    parser.add_argument("--outage-steps", type=bounded_int("--outage-steps", 10, 100000), default=400,
                        help="requests of the link-down run: enough that the link comes back before its end (400 "
                             "requests last about 70 s at 0.175 s each)")
    parser.add_argument("--outage-s", type=bounded_float("--outage-s", 0.0, low_open=True), default=30.0)
    parser.add_argument("--jump-trace", default="launch/config/rtt_jump.txt")
    parser.add_argument("--cloud-timeout-s", type=float, default=RouterConfig.cloud_timeout_s,
                        help="the learner's ~cloud_timeout_s in the runs (default: its default)")
    parser.add_argument("--goal-rate-hz", type=bounded_float("--goal-rate-hz", 0.0, 1000.0), default=4.0,
                        help="open-loop request rate (0: each request 0.1 s after the previous answer)")
    parser.add_argument("--start-lead-s", type=bounded_float("--start-lead-s", 0.0, 600.0), default=20.0,
                        help="the run's schedules and goals start together this long after each launch")
    parser.add_argument("--repeats", type=bounded_int("--repeats", 1, 100), default=1,
                        help="runs per policy, interleaved (local, cloud, ..., local, cloud, ...) and pooled: on a "
                             "shared machine one run's mean moves by several per cent")
    parser.add_argument("--runs-dir", default="runs")
    args = parser.parse_args(argv)
    policies = [name for name in args.policies.split(",") if name]
    unknown = sorted(set(policies) - set(POLICIES))
    outage = [name for name in args.outage_policies.split(",") if name]
    if unknown or set(outage) - set(POLICIES):
        parser.error(f"unknown policies {unknown or sorted(set(outage) - set(POLICIES))}; choose from {','.join(POLICIES)}")
    for name in HINDSIGHT:
        before = policies[:policies.index(name)] if name in policies else policies
        if name in policies + outage and "hedge" not in before:
            parser.error(f"{name} is chosen on the hedge run's probes: list hedge before it")
    try:
        scenario = load_scenario(args.scenario)
    except ScenarioError as error:
        parser.error(str(error))
    if scenario.rtt_trace and args.link:
        parser.error(f"scenario {scenario.name} names its own RTT trace: drop --link")
    if scenario.maps and args.map:
        parser.error(f"scenario {scenario.name} names its maps: drop --map")
    args.steps = args.steps or scenario.steps
    out = pathlib.Path(args.runs_dir).resolve() / time.strftime("bench-policies-%Y%m%d-%H%M%S")
    out.mkdir(parents=True)
    map_yaml = os.path.abspath(args.map) if args.map else ""
    scenario_args = conditions(args, scenario)
    threshold_config = str(out / "threshold_best_learner.yaml")
    oracle_config, oracle_actions = str(out / "oracle_learner.yaml"), out / "oracle_actions.txt"
    checkpoint = os.path.abspath(args.checkpoint) if args.checkpoint else ""
    seed_bag = os.path.abspath(args.seed_bag) if args.seed_bag else ""
    if not checkpoint and {"dqn", "dqn_hedge"} & set(policies + outage):
        learning = run_demo(args.launch, out / "learning", args.learning_steps, args.seed, map_yaml,
                            learning_args(args.learning_probe_rate) + scenario_args)
        checkpoint = str(learning / "checkpoint.pt") if args.deploy_model == "online" else \
            batch_checkpoint(learning, args.seed)
        seed_bag = seed_bag or str(learning / "offload.bag")
    results = {"scenario": scenario.name, "scenario_file": str(scenario.path),
               "map": " / ".join(path for path, _ in scenario.maps) or map_yaml or "nav2_warehouse (bundled)",
               "map_name": "+".join(pathlib.Path(path).stem for path, _ in scenario.maps) or pathlib.Path(map_yaml).stem
               or "warehouse", "link": str(scenario.rtt_trace or args.link or scenario.link),
               "plan_unknown": args.plan_unknown, "threshold_best": None, "gap_closed": {},
               "learning_probe_rate": args.learning_probe_rate, "deploy_model": args.deploy_model, "steps": args.steps, "seed": args.seed, "repeats": args.repeats, "checkpoint": checkpoint, "seed_bag": seed_bag,
               "goal_rate_hz": args.goal_rate_hz, "start_lead_s": args.start_lead_s, "policies": {}, "delivered_s": {},
               "oracle_mean_s": None, "oracle_actions": None, "oracle_cloud_share": None, "oracle_robot_cpu_s_per_request": None}
    model = (["--model", checkpoint] if checkpoint else []) + (["--fleet-seed-bag", seed_bag] if seed_bag else [])
    total, began = args.repeats * len(policies) + len(outage), time.monotonic()

    def progress(done: int) -> str:
        if not done:
            return f"{done + 1}/{total}"
        left_s = (time.monotonic() - began) / done * (total - done)
        return f"{done + 1}/{total}, about {left_s / 60:.0f} min left"
    run_dirs = {name: [] for name in policies}
    run_delivered = {}     # name -> each repeat's delivered latencies, for the ratios to always-local
    for repeat in range(args.repeats):
        for index, name in enumerate(policies):
            extra = policy_args(name, scenario_args, model, threshold_config, oracle_config)
            where = out / name if args.repeats == 1 else out / name / f"repeat{repeat + 1}"
            run_dirs[name].append(run_demo(args.launch, where, args.steps, args.seed, map_yaml, extra,
                                           progress(repeat * len(policies) + index)))
            if name == "hedge" and repeat == 0:
                # The best fixed d_t rule on this run's probes, for threshold_best's live runs.
                hedge_figures = measure(run_dirs[name][0], args.cloud_timeout_s)
                probes = hedge_figures.get("probe_rows")
                if probes is None:
                    raise RuntimeError(f"the hedge run {run_dirs[name][0]} has no probe with both sides measured")
                search = best_threshold(*probes)
                results["threshold_best"] = search.as_dict()
                pathlib.Path(threshold_config).write_text(f"threshold_input_size: {search.threshold!r}\n")
                print(f"threshold_best: offload when d_t > {search.threshold:.4g} ({100 * search.cloud_share:.0f} % "
                      f"offloaded), {1e3 * search.mean_s:.1f} ms on the hedge run's probes, best of "
                      f"{len(search.grid)} thresholds", flush=True)
                # The oracle's actions, request k's faster side, for its live replay.
                actions = faster_sides(*hedge_figures["request_sides_s"])
                oracle_actions.write_text("".join(f"{action}\n" for action in actions))
                pathlib.Path(oracle_config).write_text(f"replay_actions: {str(oracle_actions)!r}\n")
                results["oracle_actions"] = {"file": str(oracle_actions), "requests": int(len(actions)),
                                             "cloud_share": float(np.mean(actions)) if len(actions) else None}
            if repeat + 1 < args.repeats:
                continue
            figures = measure(run_dirs[name], args.cloud_timeout_s)
            results["delivered_s"][name] = figures.pop("delivered_s")
            run_delivered[name] = figures.pop("run_delivered_s", None) or [results["delivered_s"][name]]
            figures.pop("probe_rows", None)
            figures.pop("request_sides_s", None)
            lag = schedule_lag_s(figures.pop("arrivals_s", []), scenario.request_times(args.steps, args.goal_rate_hz))
            results["policies"][name] = {**{field: figures.get(field) for field in FIELDS},
                                         "run_dir": figures["run_dir"], "probes": figures.get("probes", 0),
                                         "hedged": figures.get("hedged", 0), "slow_link_local": figures.get("slow_link_local", 0),
                                         "run_means_s": figures.get("run_means_s"), "schedule_lag_max_s": lag}
            if name == "hedge":
                results["oracle_mean_s"] = figures.get("probe_oracle_mean_s")
                results["oracle_cloud_share"] = figures["cloud_share"]
                results["oracle_robot_cpu_s_per_request"] = figures["first_local_cpu_s_per_request"]
            print(format_table({**results, "policies": {name: results["policies"][name]}}).splitlines()[1], flush=True)
    for name, ratio in ratios_to(run_delivered, "local").items():   # each policy against always-local, pair by pair
        results["policies"][name]["mean_ratio_to_local"] = ratio
    results["outage"] = {}
    for index, name in enumerate(outage, start=args.repeats * len(policies)):
        extra = policy_args(name, scenario_args, model, threshold_config, oracle_config) + [
            "--wan-args", f"--outage {args.outage_at_s:g}:{args.outage_s:g}", "--rtt-profile", args.jump_trace]
        figures = measure(run_demo(args.launch, out / f"outage-{name}", args.outage_steps, args.seed, map_yaml, extra,
                                   progress(index)), args.cloud_timeout_s)
        figures.pop("delivered_s")
        figures.pop("probe_rows", None)
        figures.pop("request_sides_s", None)
        figures.pop("arrivals_s", None)
        results["outage"][name] = {key: figures.get(key) for key in (
            "requests", "paths_delivered", "mean_s", "p99_s", "max_s", "waited_the_timeout", "cloud_timeouts",
            "hedged", "breaker_open", "worst_wait_beyond_local_after_trip_s", "max_deadline_s", "run_dir",
            "cloud_failures", "slow_link_local")}
        results["outage"][name].update(outage_at_s=args.outage_at_s, outage_s=args.outage_s,
                                       outage_steps=args.outage_steps)
    results["scenario_table"] = scenario_rows(results)
    results["gap_closed"] = {row["policy"]: row["gap_closed"] for row in results["scenario_table"]}
    with open(out / "results.json", "w") as stream:
        json.dump({key: value for key, value in results.items() if key != "delivered_s"}, stream, indent=2)
    if results["policies"]:
        plot(results, out / "policies.png")
    print()
    print(format_table(results))
    print()
    print(format_scenario_table(results))
    for name, f in results["policies"].items():
        if f.get("schedule_lag_max_s") is not None and f["schedule_lag_max_s"] > 1.0 / args.goal_rate_hz:
            print(f"warning: {name}'s requests arrived up to {f['schedule_lag_max_s']:.2f} s behind the open-loop "
                  "schedule (its answers held them back): they met later moments of the link and the load")
    if args.repeats > 1:
        for name, f in results["policies"].items():
            print(f"{name}: run means " + ", ".join(f"{1e3 * m:.1f}" for m in f["run_means_s"]) + " ms")
    for name, f in results["policies"].items():
        if f.get("mean_ratio_to_local"):
            print(MeanRatio(**f["mean_ratio_to_local"]).describe(name, "local"))
    for name, f in results["outage"].items():
        if not (f.get("cloud_failures") or f.get("breaker_open")):
            print(f"link down {args.outage_s:g} s from {args.outage_at_s:g} s, {name}: no request met the outage (no "
                  "cloud failure, the breaker never opened): the run ended before it or routed around it; its "
                  "figures say nothing of a link failure (--outage-at-s, --outage-steps)")
            continue
        print(f"link down {args.outage_s:g} s mid-run, {name}: {f['paths_delivered']}/{f['requests']} paths, worst "
              f"wait {1e3 * f['max_s']:.0f} ms, {f['waited_the_timeout']} waited the {args.cloud_timeout_s:g} s "
              f"timeout, {f['breaker_open']} routed locally by the open breaker, {f['hedged']} hedged; after the "
              f"breaker opened, the worst wait beyond the request's own local plan was "
              f"{1e3 * (f['worst_wait_beyond_local_after_trip_s'] or 0.0):.0f} ms")
    print(f"\nresults: {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
