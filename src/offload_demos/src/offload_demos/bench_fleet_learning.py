"""`make bench-fleet-learning`: robots that differ learning through one fleet learner against each learning alone
(#30 item 8).

Each robot configuration (map, link profile, CPU budget) runs the demo's whole stack live (as bench-policies: the
robot's processes on one core inside its budget with the seeded workload, the cloud side on the other core
behind the WAN emulator, open-loop seeded requests), one run at a time (the machine's two cores are one robot and
one cloud host). Per robot, the arms:
- oracle: both sides on every request (learning mode, the policy frozen): the backbone of the robot's side table
  every arm's decisions are scored with (request k of every run of a robot meets the same conditions);
- alone: the DQN deployed on the robot from nothing (probe rate 0.05), learning on the robot from its own rows;
- fleet: the robot deciding with the fleet learner's models, its rows streamed to the one fleet learner all the
  robots share (needs the fleet learner service and the robot's fleet mode: the arm says n/a until both are
  there).
It prints, per robot and arm, the requests until the arm's decisions over a trailing window are within 5 % of the
best decisions over the same requests, both scored with one table of the two sides' own latencies per request
pooled over the robot's runs (fleet_metrics: like with like, free of the routing and of one run's machine noise),
the decisions' and the best decisions' mean over the first 300 requests and, beside them, the run's live delivered
mean; then the bad model pushed to the fleet (always-cloud, to a robot where local wins): the requests until the
robot's guard rolls it back and what its decisions cost over the best ones.
runs/bench-fleet-learning-<time>/results.json."""
import argparse
import importlib.util
import json
import os
import pathlib
import re
import sys
import time
from dataclasses import asdict, dataclass
from typing import Dict, Optional

import numpy as np

from offload_cloud.cli_args import bounded_float, bounded_int
from offload_demos import fleet_metrics
from offload_cloud.learner.store import ModelStore
from offload_demos.bench_policies import run_demo
from offload_demos.fleet_bad_model import DelayedPush
from offload_demos.keys import ensure_demo_robots
from offload_learner_py.data.bags import read_bags

ROOT = pathlib.Path(__file__).resolve().parents[4]     # the workspace (src/offload_demos/src/offload_demos/..)


@dataclass(frozen=True)
class RobotConfig:
    name: str
    map: str            # map_server YAML, relative to the workspace
    link: str           # launch/config/link_<link>.txt
    budget_cores: float
    seed: int


# Four robots that differ in map (size and layout), link and CPU budget.
ROBOTS = (
    RobotConfig("turtlebot-edge", "src/offload_planner_cpp/maps/turtlebot3_world/map.yaml", "edge", 0.5, 11),
    RobotConfig("husky-wan", "src/offload_planner_cpp/maps/husky_playpen/playpen_map.yaml", "wan", 0.25, 12),
    RobotConfig("warehouse-edge", "src/offload_planner_cpp/maps/nav2_warehouse/warehouse.yaml", "edge", 0.5, 13),
    RobotConfig("willow-wan", "../shared/data/maps/ros/willow_garage_2010/willow-2010-02-18-0.10.yaml", "wan", 1.0,
                14),
)
# The fleet learner trains often enough that a robot's run sees several rounds (a fielded one: every 200 rows or
# 5 minutes) and the robots ask for the current version every 5 s (fielded: 30 s).
FLEET_LEARNER = "--train-every-rows 50 --train-every-s 20 --min-robot-rows 20"
ARMS = {
    "oracle": ["--policy", "local", "--mode", "learning", "--learn", "false"],
    "alone": ["--policy", "dqn", "--mode", "deployed", "--probe-rate", "0.05"],
    # the store (--fleet-store) is the bench's one fleet learner store, added per run
    "fleet": ["--policy", "dqn", "--mode", "deployed", "--probe-rate", "0.05", "--fleet", "--fleet-period-s", "5",
              "--fleet-args", FLEET_LEARNER],
}


def fleet_missing(root: pathlib.Path = ROOT) -> str:
    """Why the fleet arm cannot run on this checkout ("" when it can): the fleet learner service
    (offload_cloud.learner) and the robot's fleet mode (robot.launch's fleet_endpoint) must both be there."""
    missing = []
    if importlib.util.find_spec("offload_cloud.learner") is None:
        missing.append("no fleet learner service (offload_cloud.learner)")
    robot_launch = root / "launch" / "robot.launch"
    if not robot_launch.exists() or not re.search(r'<arg\s+name="fleet_endpoint"', robot_launch.read_text()):
        missing.append("no robot fleet mode (robot.launch has no fleet_endpoint argument)")
    return "; ".join(missing)


def load_run(run_dir: pathlib.Path) -> Dict[str, np.ndarray]:
    data = read_bags([str(run_dir / "offload.bag")], workers=1)
    if data.report.failed:
        raise RuntimeError(data.report.failed[0].error)
    return fleet_metrics.run_arrays(data.log)


def robot_figures(runs: Dict[str, pathlib.Path], first: int, tolerance: float, window: int) -> Dict:
    """One robot's figures from its arms' run directories: the side table pooled over every run (the oracle's
    both sides on every request, the others' sides and probes), then each learning arm's decisions scored with
    it (fleet_metrics.arm_figures), and the table itself for the bad model."""
    arrays = {arm: load_run(run_dir) for arm, run_dir in runs.items()}
    table = fleet_metrics.side_table(list(arrays.values()))
    best = fleet_metrics.best_latency(table)
    figures = {"best_mean_s": float(np.nanmean(best)) if np.isfinite(best).any() else None,
               "both_sides_known": int(np.isfinite(best).sum()), "arms": {}}
    for arm, run_dir in runs.items():
        if arm != "oracle":
            figures["arms"][arm] = {**fleet_metrics.arm_figures(arrays[arm], table, first, tolerance, window),
                                    "run_dir": str(run_dir)}
    return figures, arrays, table


def bad_model_figures(arrays: Dict[str, Dict], table: Optional[np.ndarray], robot: Optional[RobotConfig],
                      push: Optional[DelayedPush], store: pathlib.Path, missing: str) -> Dict:
    """What the bad model's decisions cost `robot` over the best decisions and how soon its guard rolled it back,
    from its bad_model run and its robot's side table (the version pushed: the push's, or on --analyse the
    store's fleet pin)."""
    if robot is None or "bad_model" not in arrays.get(robot.name, {}) or table is None:
        return {"skipped": "not run: " + (missing or "no bad-model robot among the robots run")}
    version = push.version if push else ModelStore(str(store)).state().get("current", "")
    if not version:
        return {"skipped": f"the push failed: {push.error if push else 'no version in the store'}"}
    run = arrays[robot.name]["bad_model"]
    rolled_back_at = fleet_metrics.rollback_index(run["model_version"], version)
    cost = fleet_metrics.bad_model_cost(run["model_version"], version,
                                        fleet_metrics.decision_latency(run["action"], table),
                                        fleet_metrics.best_latency(table), rolled_back_at)
    return {"robot": robot.name, "version": version, **cost}


def format_table(results: Dict) -> str:
    window, first = results["window"], results["first"]
    within = f"{100 * results['tolerance']:g} %"
    lines = ["Decisions scored like with like: per request, both sides' own latencies averaged over the robot's runs",
             "that measured both (the oracle run: every request); a decision costs its side's latency there, the best",
             f"decision the faster side's. to {within}: requests until the mean of the arm's decisions over the last "
             f"{window}",
             f"is within {within} of the best decisions' over the same requests. decided, best, local: over the first "
             f"{first} requests.",
             "delivered live: the run's own delivered mean (side + routing, under that run's machine load), not the "
             "decisions' measure.",
             f"{'robot':<16}{'map':<24}{'link':>5}{'cores':>6}{'arm':>7}{'to ' + within:>8}"
             f"{'decided ms':>12}{'best ms':>9}{'local':>7}{'delivered live ms':>19}"]
    for name, robot in results["robots"].items():
        config = robot["config"]
        head = f"{name:<16}{pathlib.Path(config['map']).stem[:23]:<24}{config['link']:>5}{config['budget_cores']:>6g}"
        for arm in ("alone", "fleet"):
            f = robot["arms"].get(arm)
            if f is None:
                lines.append(f"{head}{arm:>7}{'n/a':>8}   ({robot.get('skipped', {}).get(arm, 'not run')})")
            else:
                reached, head300 = f["requests_to_within"], f["first"]
                ms = lambda value: "n/a" if value is None else f"{1e3 * value:.1f}"  # noqa: E731
                lines.append(f"{head}{arm:>7}{'never' if reached is None else reached:>8}"
                             f"{ms(head300['decided_mean_s']):>12}{ms(head300['best_mean_s']):>9}"
                             f"{100 * head300['local_share']:>6.0f}%{ms(head300['mean_s']):>13}"
                             f" ({head300['requests']})")
            head = " " * len(head)
    bad = results.get("bad_model")
    lines.append("bad model pushed to the fleet: " + (bad["skipped"] if "skipped" in bad else
                 f"{bad['robot']}: {bad['requests_to_rollback']} requests to rollback, its decisions "
                 f"{1e3 * (bad['excess_s'] or 0.0):.0f} ms over the best decisions in all"))
    fleet_wins = results.get("fleet_fewer_requests")
    if fleet_wins is not None:
        lines.append(f"fleet fewer requests to {within} than alone: {fleet_wins} of {len(results['robots'])} "
                     f"robots")
    return "\n".join(lines)


def fleet_fewer(results: Dict) -> Optional[int]:
    counted = 0
    for robot in results["robots"].values():
        alone, fleet = robot["arms"].get("alone"), robot["arms"].get("fleet")
        if alone is None or fleet is None:
            return None
        reached_fleet, reached_alone = fleet["requests_to_within"], alone["requests_to_within"]
        counted += reached_fleet is not None and (reached_alone is None or reached_fleet < reached_alone)
    return counted


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--launch", default="launch/offload_demo.launch")
    parser.add_argument("--robots", default=",".join(r.name for r in ROBOTS),
                        help="comma list of " + ",".join(r.name for r in ROBOTS))
    parser.add_argument("--arms", default="oracle,alone,fleet", help="comma list of " + ",".join(ARMS))
    parser.add_argument("--steps", type=bounded_int("--steps", 10, 100000), default=400)
    parser.add_argument("--first", type=bounded_int("--first", 1, 100000), default=300,
                        help="the mean over a robot's first this many requests")
    parser.add_argument("--window", type=bounded_int("--window", 1, 100000), default=50)
    parser.add_argument("--tolerance", type=bounded_float("--tolerance", 0.0, 1.0), default=0.05)
    parser.add_argument("--goal-rate-hz", type=bounded_float("--goal-rate-hz", 0.0, 1000.0), default=4.0)
    parser.add_argument("--start-lead-s", type=bounded_float("--start-lead-s", 0.0, 600.0), default=20.0)
    parser.add_argument("--bad-model-robot", default=ROBOTS[0].name,
                        help="the robot (one where local wins) the bad model is pushed to ('' to skip)")
    parser.add_argument("--bad-model-after-s", type=bounded_float("--bad-model-after-s", 0.0, 3600.0), default=40.0,
                        help="seconds after the requests begin")
    parser.add_argument("--runs-dir", default="runs")
    parser.add_argument("--analyse", metavar="BENCH_DIR", help="figures of an earlier bench directory, no run")
    args = parser.parse_args(argv)
    chosen = [name for name in args.robots.split(",") if name]
    robots = [robot for robot in ROBOTS if robot.name in chosen]
    arms = [arm for arm in args.arms.split(",") if arm]
    if len(robots) != len(chosen) or set(arms) - set(ARMS) or "oracle" not in arms:
        parser.error(f"robots from {','.join(r.name for r in ROBOTS)}; arms from {','.join(ARMS)}, oracle among them")
    out = pathlib.Path(args.analyse) if args.analyse else \
        pathlib.Path(args.runs_dir).resolve() / time.strftime("bench-fleet-learning-%Y%m%d-%H%M%S")
    out.mkdir(parents=True, exist_ok=bool(args.analyse))
    missing = fleet_missing()
    results = {"steps": args.steps, "first": args.first, "window": args.window, "tolerance": args.tolerance,
               "goal_rate_hz": args.goal_rate_hz, "robots": {}, "fleet_missing": missing}
    bad_robot = next((robot for robot in robots if robot.name == args.bad_model_robot), None) \
        if "fleet" in arms and not missing else None
    plan = [(robot, arm) for robot in robots for arm in arms if not (arm == "fleet" and missing)]
    plan += [(bad_robot, "bad_model")] if bad_robot else []
    began = time.monotonic()
    runs: Dict[str, Dict[str, pathlib.Path]] = {robot.name: {} for robot in robots}
    store = out / "fleet-store"      # the one fleet learner's, every robot's fleet runs one after another
    if not args.analyse:
        ensure_demo_robots(pathlib.Path(os.environ.get("ROS_HOME", pathlib.Path.home() / ".ros")) / "offload_demo_keys",
                           [robot.name for robot in robots])
    push = None
    for done, (robot, arm) in enumerate(plan):
        where = out / robot.name / arm
        if args.analyse:
            found = sorted(p for p in where.iterdir() if p.is_dir()) if where.is_dir() else []
            if found:
                runs[robot.name][arm] = found[-1]
            continue
        left = f", about {(time.monotonic() - began) / done * (len(plan) - done) / 60:.0f} min left" if done else ""
        extra = ARMS["fleet" if arm == "bad_model" else arm] + [
            "--link", robot.link, "--budget-cores", f"{robot.budget_cores:g}", "--goal-rate-hz",
            f"{args.goal_rate_hz:g}", "--start-lead-s", f"{args.start_lead_s:g}", "--robot-key", robot.name]
        if arm in ("fleet", "bad_model"):
            extra += ["--fleet-store", str(store)]
        if arm == "bad_model":   # the launch takes a few seconds more than the lead: pushed a little late at worst
            push = DelayedPush(str(store), time.monotonic() + args.start_lead_s + args.bad_model_after_s,
                               robot=robot.name)
        runs[robot.name][arm] = run_demo(args.launch, where, args.steps, robot.seed, str((ROOT / robot.map).resolve()),
                                         extra, f"{robot.name} {arm}, {done + 1}/{len(plan)}{left}")
    arrays, tables = {}, {}
    for robot in robots:
        entry: Dict = {"config": asdict(robot), "arms": {}, "skipped": {}}
        if "oracle" in runs[robot.name]:
            figures, arrays[robot.name], tables[robot.name] = robot_figures(runs[robot.name], args.first,
                                                                            args.tolerance, args.window)
            entry.update(figures)
        if "fleet" in arms and missing:
            entry["skipped"]["fleet"] = f"not run: {missing}"
        results["robots"][robot.name] = entry
    results["fleet_fewer_requests"] = fleet_fewer(results) if "fleet" in arms and not missing else None
    results["bad_model"] = bad_model_figures(arrays, tables.get(bad_robot.name) if bad_robot else None, bad_robot,
                                             push, store, missing)
    with open(out / "results.json", "w") as stream:
        json.dump(results, stream, indent=2)
    print()
    print(format_table(results))
    print(f"\nresults: {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
