"""`make bench-fleet-learning`: robots that differ learning through one fleet learner against each learning alone
(#30 item 8).

Each robot configuration (map, link profile, CPU budget) runs the demo's whole stack live (as bench-policies: the
robot's processes on one core inside its budget with the seeded workload, the cloud side on the other core
behind the WAN emulator, open-loop seeded requests), one run at a time (the machine's two cores are one robot and
one cloud host). Per robot, the arms:
- oracle: both sides on every request (learning mode, the policy frozen): request k's faster side, the oracle
  the others are measured against (request k of every run of a robot meets the same conditions);
- alone: the DQN deployed on the robot from nothing (probe rate 0.05), learning on the robot from its own rows;
- fleet: the robot deciding with the fleet learner's models, its rows streamed to the one fleet learner all the
  robots share (needs the fleet learner service and the robot's fleet mode: the arm says n/a until both are
  there).
It prints, per robot and arm, the requests until the delivered mean over a trailing window is within 5 % of the
oracle's over the same requests (fleet_metrics.requests_to_within) and the mean over the first 300 requests;
then the bad model pushed to the fleet (always-cloud, to a robot where local wins): the requests until the
robot's guard rolls it back and the latency it cost. runs/bench-fleet-learning-<time>/results.json."""
import argparse
import importlib.util
import json
import os
import pathlib
import re
import sys
import time
from dataclasses import asdict, dataclass
from typing import Dict, List, Optional

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


def arm_figures(run_dir: pathlib.Path, oracle_s: np.ndarray, first: int, tolerance: float, window: int) -> Dict:
    arrays = load_run(run_dir)
    delivered = arrays["delivered_s"]
    return {"requests": len(delivered), "mean_s": float(np.mean(delivered)),
            "requests_to_within": fleet_metrics.requests_to_within(delivered, oracle_s, tolerance, window),
            "first": fleet_metrics.first_mean(delivered, first), "run_dir": str(run_dir)}


def load_run(run_dir: pathlib.Path) -> Dict[str, np.ndarray]:
    data = read_bags([str(run_dir / "offload.bag")], workers=1)
    if data.report.failed:
        raise RuntimeError(data.report.failed[0].error)
    return fleet_metrics.run_arrays(data.log)


def robot_figures(runs: Dict[str, pathlib.Path], first: int, tolerance: float, window: int) -> Dict:
    """One robot's figures from its arms' run directories: the oracle pooled over every run's both-sides
    requests, then each learning arm against it."""
    arrays = {arm: load_run(run_dir) for arm, run_dir in runs.items()}
    oracle = fleet_metrics.request_oracle(list(arrays.values()))
    figures = {"oracle_mean_s": float(np.nanmean(oracle)) if np.isfinite(oracle).any() else None,
               "oracle_known": int(np.isfinite(oracle).sum()), "arms": {}}
    for arm, run_dir in runs.items():
        if arm != "oracle":
            figures["arms"][arm] = arm_figures(run_dir, oracle, first, tolerance, window)
    return figures


def bad_model_figures(runs, robot: Optional[RobotConfig], push: Optional[DelayedPush], store: pathlib.Path,
                      missing: str) -> Dict:
    """What the bad model cost `robot` and how soon its guard rolled it back, from its bad_model run's bag and its
    oracle run (the version pushed: the push's, or on --analyse the store's fleet pin)."""
    if robot is None or "bad_model" not in runs[robot.name]:
        return {"skipped": "not run: " + (missing or "no bad-model robot among the robots run")}
    version = push.version if push else ModelStore(str(store)).state().get("current", "")
    if not version:
        return {"skipped": f"the push failed: {push.error if push else 'no version in the store'}"}
    arrays = load_run(runs[robot.name]["bad_model"])
    oracle = fleet_metrics.request_oracle([load_run(runs[robot.name]["oracle"])] if "oracle" in runs[robot.name]
                                          else [arrays], len(arrays["delivered_s"]))
    rolled_back_at = fleet_metrics.rollback_index(arrays["model_version"], version)
    return {"robot": robot.name, "version": version, **fleet_metrics.bad_model_cost(
        arrays["model_version"], version, arrays["delivered_s"], oracle, rolled_back_at)}


def format_table(results: Dict) -> str:
    window, first = results["window"], results["first"]
    lines = [f"{'robot':<16}{'map':<24}{'link':>5}{'cores':>6}{'oracle ms':>10}{'arm':>7}{'to 5 %':>8}"
             f"{f'first {first} ms':>15}   (to 5 %: requests until the mean over the last {window} is within 5 % "
             "of the oracle's over the same requests; the oracle: the faster side where both were measured)"]
    for name, robot in results["robots"].items():
        config = robot["config"]
        oracle = robot.get("oracle_mean_s")
        head = (f"{name:<16}{pathlib.Path(config['map']).stem[:23]:<24}{config['link']:>5}{config['budget_cores']:>6g}"
                f"{'n/a' if oracle is None else f'{1e3 * oracle:.1f}':>10}")
        for arm in ("alone", "fleet"):
            f = robot["arms"].get(arm)
            if f is None:
                lines.append(f"{head}{arm:>7}{'n/a':>8}{'n/a':>15}   ({robot.get('skipped', {}).get(arm, 'not run')})")
            else:
                reached = f["requests_to_within"]
                lines.append(f"{head}{arm:>7}{'never' if reached is None else reached:>8}"
                             f"{1e3 * f['first']['mean_s']:>11.1f} ({f['first']['requests']})")
            head = " " * len(head)
    bad = results.get("bad_model")
    lines.append("bad model pushed to the fleet: " + (bad["skipped"] if "skipped" in bad else
                 f"{bad['robot']}: {bad['requests_to_rollback']} requests to rollback, "
                 f"{1e3 * (bad['excess_s'] or 0.0):.0f} ms cost over the oracle"))
    fleet_wins = results.get("fleet_fewer_requests")
    if fleet_wins is not None:
        lines.append(f"fleet fewer requests to 5 % than alone: {fleet_wins} of {len(results['robots'])} robots")
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
    for robot in robots:
        entry: Dict = {"config": asdict(robot), "arms": {}, "skipped": {}}
        if "oracle" in runs[robot.name]:
            entry.update(robot_figures(runs[robot.name], args.first, args.tolerance, args.window))
        if "fleet" in arms and missing:
            entry["skipped"]["fleet"] = f"not run: {missing}"
        results["robots"][robot.name] = entry
    results["fleet_fewer_requests"] = fleet_fewer(results) if "fleet" in arms and not missing else None
    results["bad_model"] = bad_model_figures(runs, bad_robot, push, store, missing)
    with open(out / "results.json", "w") as stream:
        json.dump(results, stream, indent=2)
    print()
    print(format_table(results))
    print(f"\nresults: {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
