"""`make demo`: the whole offloading system on one machine, with a real trade-off.

The robot's processes (planner, bridge, learner, workload) run pinned to one core inside a cgroup v1
CPU budget; the cloud server and the WAN emulator run on the other core. roslaunch runs
launch/offload_demo.launch on a master port of its own; when the goal generator has sent its requests
the launch ends, and the bag it recorded is read back into the transition table, summarised, plotted
and written to runs/<timestamp>/ with the checkpoint. Ctrl-C stops everything cleanly (and still
summarises what was recorded)."""
import argparse
import ctypes
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

from offload_cloud.cli_args import bounded_float, bounded_int
from offload_demos.loopback import free_port
from offload_demos.keys import ensure_demo_keys
from offload_demos.robot_cpu import PIDS_ENV, PIDS_FILE, SAMPLES_FILE, CpuSampler, format_robot_cpu, run_robot_cpu
from offload_learner_py.data.bags import read_bags
from offload_learner_py.offline.report import report_run
from offload_learner_py.offline.summary import format_summary, summarise
from offload_learner_py.online.router_types import MODES
from offload_learner_py.online.session import SessionConfig

CGROUP_ROOT = "/sys/fs/cgroup"
CGROUP_PERIOD_US = 4000   # the kernel's smallest quota is 1 ms, so 4 ms is the shortest period for 25 %


class RobotBudget:
    """A cgroup v1 group (cpu + cpuacct) with a CPU quota of `cores` cores, removed on close."""

    def __init__(self, name: str, cores: float):
        self.name = name
        self.dirs = [os.path.join(CGROUP_ROOT, controller, name) for controller in ("cpu", "cpuacct")]
        for directory in self.dirs:
            os.makedirs(directory, exist_ok=True)
        with open(os.path.join(self.dirs[0], "cpu.cfs_period_us"), "w") as period:
            period.write(str(CGROUP_PERIOD_US))
        with open(os.path.join(self.dirs[0], "cpu.cfs_quota_us"), "w") as quota:
            quota.write(str(max(1000, int(round(cores * CGROUP_PERIOD_US)))))

    def close(self) -> None:
        for directory in self.dirs:
            self.remove(directory)

    @staticmethod
    def remove(directory: str) -> None:
        # Stray processes (none after a clean shutdown) go back to the root group so rmdir works.
        try:
            with open(os.path.join(directory, "cgroup.procs")) as procs:
                pids = procs.read().split()
            for pid in pids:
                with open(os.path.join(os.path.dirname(directory), "cgroup.procs"), "w") as root:
                    root.write(pid)
        except OSError:
            pass
        try:
            os.rmdir(directory)
        except OSError:
            pass


def remove_stale_budgets() -> list:
    """The cgroups `offload_robot_<pid>` of demo drivers that died without cleaning up (SIGKILL)."""
    removed = []
    for controller in ("cpu", "cpuacct"):
        root = pathlib.Path(CGROUP_ROOT) / controller
        for group in root.glob("offload_robot_*") if root.is_dir() else ():
            pid = group.name.rsplit("_", 1)[-1]
            if pid.isdigit() and not pathlib.Path(f"/proc/{pid}").exists():
                RobotBudget.remove(str(group))
                removed.append(str(group))
    return removed


def end_with_parent() -> None:
    """In the child before exec: SIGTERM when the driver dies, however it dies (roslaunch then shuts its
    nodes down), so a killed driver leaves no launch running. Linux prctl(PR_SET_PDEATHSIG)."""
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0)


# launch/config/link_<name>.txt: the named round-trip profiles of the emulated link
LINK_PROFILES = ("edge", "wan")


def check_options(args) -> str:
    """Why the options cannot make a run, in one line, or "" (checked before anything starts)."""
    if args.steps is not None and args.steps < 1:
        return f"STEPS must be a positive integer, got {args.steps}"
    if args.map:
        from offload_planner_cpp.maps import MapFormatError, load_map_server_yaml
        try:
            load_map_server_yaml(args.map)
        except (MapFormatError, OSError, ValueError) as error:
            return f"MAP {args.map}: {error}"
    if args.model and not os.path.isfile(args.model):
        return f"MODEL {args.model}: no such file"
    if args.fleet and (args.policy != "dqn" or args.mode != "deployed"):
        return "--fleet is the deployed DQN's: pass --policy dqn --mode deployed"
    learner_config, scenario_name = getattr(args, "learner_config", ""), getattr(args, "scenario", "")
    if learner_config and not os.path.isfile(learner_config):
        return f"--learner-config {learner_config}: no such file"
    if scenario_name:
        from offload_demos.scenario import ScenarioError, load_scenario
        try:
            scenario = load_scenario(scenario_name)
        except ScenarioError as error:
            return str(error)
        if scenario.maps and args.map:
            return f"scenario {scenario.name} names its maps: drop MAP"
    if args.fleet_seed_bag and not os.path.isfile(args.fleet_seed_bag):
        return f"--fleet-seed-bag {args.fleet_seed_bag}: no such file"
    return ""


def analyse(out_dir: pathlib.Path, policy: str) -> dict:
    """Bag -> transition table -> summary.json and transitions.npz; prints the summary table. The figures are
    the report's (report/figures/, drawn once by offline.report)."""
    from offload_learner_py.core.checkpoint import load_checkpoint

    bag = out_dir / "offload.bag"
    if not bag.exists():
        active = out_dir / "offload.bag.active"
        if active.exists():
            subprocess.run(["rosbag", "reindex", str(active)], capture_output=True)
            active.rename(bag)
        else:
            raise FileNotFoundError(f"no bag in {out_dir}")
    # The one bag reader (also behind retrain and report): each bag's own message definitions.
    data = read_bags([str(bag)], workers=1)
    if data.report.failed:
        raise ValueError(data.report.failed[0].error)
    log = data.log
    table = data.transition_table({"policy": policy})
    topics = {**data.report.bags[0].ignored_topics, **data.report.bags[0].topics}
    table.save_npz(str(out_dir / "transitions.npz"))
    q_values = None
    checkpoint = out_dir / "checkpoint.pt"
    if policy == "dqn" and checkpoint.exists():
        q_values = load_checkpoint(str(checkpoint)).q_values
    summary = summarise(log, table, q_values)
    summary["bag_topics"] = topics
    # Everything the robot's processes spent over the requests' span (the workload apart), beside the nodes' own
    # accounting of their planning, bridge and learner CPU.
    summary["robot_cpu"] = run_robot_cpu(out_dir / SAMPLES_FILE, log["stamp_ns"],
                                                log["outcome_delivered_s"])
    with open(out_dir / "summary.json", "w") as out:
        json.dump(summary, out, indent=2, default=float)
    print(format_summary(summary))
    print(format_robot_cpu(summary["robot_cpu"]))
    return summary


def build_parser() -> argparse.ArgumentParser:
    """The driver's command line (bench-policies' tests read back the runs' conditions with it)."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--launch", required=True, help="launch/offload_demo.launch")
    parser.add_argument("--steps", type=bounded_int("--steps", 1, 10_000_000),
                        help="requests (default: offload_demo.launch's steps)")
    parser.add_argument("--map", default="", help="map_server YAML (default: the bundled nav2 warehouse)")
    parser.add_argument("--link", choices=LINK_PROFILES,
                        help="link profile: edge (on-site Wi-Fi to an edge server, 8-120 ms) or wan (a cloud region, "
                             "20-400 ms); default: offload_demo.launch's")
    parser.add_argument("--plan-unknown", action="store_true",
                        help="plan through unknown cells and draw goals there too (default: known free space only)")
    # Unset options pass nothing: the launch's value, else the node's default (its config dataclass's).
    parser.add_argument("--policy", default=SessionConfig.policy)
    parser.add_argument("--mode", choices=MODES,
                        help="learning: both sides on every request (the paper, the demo's default); deployed: the "
                             "chosen side alone")
    parser.add_argument("--probe-rate", type=bounded_float("--probe-rate", 0.0, 1.0),
                        help="deployed: share of requests run on both sides")
    parser.add_argument("--hedge", action="store_true", help="deadline hedge (deployed)")
    parser.add_argument("--model", default="", help="checkpoint to start the DQN from")
    parser.add_argument("--learn", choices=("true", "false"))
    parser.add_argument("--fleet", action="store_true",
                        help="deployed DQN with a fleet learner on the cloud side: the robot decides, the cloud learns")
    parser.add_argument("--fleet-seed-bag", default="", help="--fleet: a learning run's bag the fleet learner starts from")
    parser.add_argument("--fleet-store", default="", help="--fleet: its store (default: the run directory's fleet/)")
    parser.add_argument("--fleet-args", default="", help="--fleet: more offload-cloud-learner serve options")
    parser.add_argument("--fleet-period-s", type=bounded_float("--fleet-period-s", 0.1, 86400.0),
                        help="--fleet: how often the robot asks for the current model version")
    parser.add_argument("--robot-key", default="", help="the robot's key under the demo's keys (its fleet name)")
    parser.add_argument("--wan-args", default="", help="extra WAN emulator options, e.g. '--outage 40:30'")
    parser.add_argument("--no-report", action="store_true", help="skip the HTML report (benchmarks)")
    parser.add_argument("--seed", type=int, help="the run's seed (default: offload_demo.launch's)")
    parser.add_argument("--runs-dir", default="runs")
    parser.add_argument("--budget-cores", type=float, default=0.5,
                        help="robot CPU budget in cores (cgroup quota), 0 for none")
    parser.add_argument("--robot-core", default="0")
    parser.add_argument("--cloud-core", default="1")
    parser.add_argument("--rtt-profile", default="")
    parser.add_argument("--scenario", default="",
                        help="a bench-policies scenario (a name or a YAML file): its RTT trace, load schedule and maps")
    parser.add_argument("--learner-config", default="", help="the learner's YAML in place of launch/config/learner.yaml")
    parser.add_argument("--goal-rate-hz", type=bounded_float("--goal-rate-hz", 0.0, 1000.0),
                        help="open-loop requests at this rate (unset or 0: the goal generator's pause after each "
                             "answer)")
    parser.add_argument("--start-lead-s", type=bounded_float("--start-lead-s", 0.0, 600.0), default=0.0,
                        help="start the RTT trace, the workload schedule and the goals together, this long after "
                             "the launch (time for every node to come up; 0: each on its own)")
    parser.add_argument("--rviz", action="store_true")
    parser.add_argument("--analyse-only", metavar="RUN_DIR", help="summarise an existing run directory")
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.analyse_only:
        analyse(pathlib.Path(args.analyse_only), args.policy)
        return 0
    problem = check_options(args)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    for group in remove_stale_budgets():
        print(f"demo: removed {group}, left by a demo driver that died", flush=True)
    out_dir = pathlib.Path(args.runs_dir).resolve() / time.strftime("%Y%m%d-%H%M%S")
    out_dir.mkdir(parents=True)
    ros_home = os.environ.get("ROS_HOME", str(pathlib.Path.home() / ".ros"))
    keys_root = ensure_demo_keys(pathlib.Path(ros_home) / "offload_demo_keys")
    budget = None
    cgroup = f"offload_robot_{os.getpid()}"
    if args.budget_cores > 0:
        try:
            budget = RobotBudget(cgroup, args.budget_cores)
        except OSError as error:
            print(f"warning: no robot CPU budget ({error}); local planning runs at full speed of core "
                  f"{args.robot_core}", file=sys.stderr)
    confine = os.path.join(os.path.dirname(os.path.abspath(args.launch)), "..", "src", "offload_demos",
                           "scripts", "robot_confine")
    robot_prefix = f"{os.path.abspath(confine)} {args.robot_core} {cgroup if budget else '-'}"
    master_port = free_port()
    launch_args = [f"policy:={args.policy}", f"out_dir:={out_dir}", f"wan_args:={args.wan_args}",
                   f"keys_root:={keys_root}", f"server_port:={free_port()}", f"wan_port:={free_port()}",
                   f"robot_prefix:={robot_prefix}", f"cloud_prefix:=taskset -c {args.cloud_core}",
                   f"cpu_cgroup:={cgroup if budget else ''}", f"cpu_cores:={args.robot_core}",
                   f"rviz:={str(args.rviz).lower()}"]
    given = {"steps": args.steps, "seed": args.seed, "mode": args.mode, "probe_rate": args.probe_rate,
             "learn": args.learn, "goal_rate_hz": args.goal_rate_hz, "link": args.link,
             "budget_cores": args.budget_cores if budget else None, "hedge": "true" if args.hedge else None}
    launch_args += [f"{name}:={value}" for name, value in given.items() if value is not None]
    if args.map:
        launch_args.append(f"map:={os.path.abspath(args.map)}")
    if args.model:
        launch_args.append(f"model:={os.path.abspath(args.model)}")
    if args.scenario:
        from offload_demos.scenario import load_scenario
        scenario = load_scenario(args.scenario)
        launch_args.append(f"scenario:={scenario.path}")
        if scenario.maps:
            launch_args.append("publish_map:=false")
        if scenario.rtt_trace and not args.rtt_profile:
            args.rtt_profile = str(scenario.rtt_trace)
        elif scenario.link and not args.link:
            launch_args.append(f"link:={scenario.link}")
    if args.learner_config:
        launch_args.append(f"learner_config:={os.path.abspath(args.learner_config)}")
    if args.rtt_profile:
        launch_args.append(f"rtt_profile:={os.path.abspath(args.rtt_profile)}")
    if args.fleet:
        launch_args += ["fleet:=true", f"fleet_port:={free_port()}", f"fleet_args:={args.fleet_args}"]
        if args.fleet_period_s:
            launch_args.append(f"fleet_period_s:={args.fleet_period_s:g}")
        launch_args += [f"{name}:={os.path.abspath(value)}" for name, value in (
            ("fleet_seed_bag", args.fleet_seed_bag), ("fleet_store", args.fleet_store)) if value]
    if args.robot_key:
        launch_args.append(f"robot_key:={args.robot_key}")
    if args.plan_unknown:
        launch_args.append("unknown_is_obstacle:=false")
    env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{master_port}", ROS_HOME=ros_home,
               **{PIDS_ENV: str(out_dir / PIDS_FILE)})
    sampler = CpuSampler(budget.dirs[1] if budget else None, str(out_dir / PIDS_FILE)).start()
    launch_default = "the launch's"
    print(f"demo: {args.steps or launch_default} requests, policy {args.policy}, {args.mode or launch_default} mode, "
          f"{'trace ' + args.rtt_profile if args.rtt_profile else (args.link or launch_default) + ' link'}, goals in "
          f"{'known and unknown' if args.plan_unknown else 'known'} free space, robot on core {args.robot_core} with "
          f"{args.budget_cores if budget else 'no'} core budget, cloud on core {args.cloud_core}; output {out_dir}",
          flush=True)
    if args.start_lead_s > 0:
        # CLOCK_MONOTONIC is one clock for every process on the machine.
        launch_args.append(f"epoch:={time.monotonic() + args.start_lead_s:.3f}")
    launch = subprocess.Popen(["roslaunch", "-p", str(master_port), args.launch]
                              + launch_args, env=env, start_new_session=True, preexec_fn=end_with_parent)
    interrupted = False
    try:
        while launch.poll() is None:
            try:
                launch.wait(timeout=1.0)
            except subprocess.TimeoutExpired:
                pass
            except KeyboardInterrupt:
                interrupted = True
                print("\ndemo: stopping (Ctrl-C)...", flush=True)
                os.killpg(launch.pid, signal.SIGINT)
    finally:
        if launch.poll() is None:
            try:
                launch.wait(timeout=40)
            except subprocess.TimeoutExpired:
                os.killpg(launch.pid, signal.SIGKILL)
                launch.wait()
        sampler.stop()       # before the cgroup goes: its last reading of the group's counter
        sampler.save(out_dir / SAMPLES_FILE)
        if budget:
            budget.close()
    try:
        summary = analyse(out_dir, args.policy)
    except (FileNotFoundError, ValueError) as error:
        print(f"error: cannot summarise the run: {error}", file=sys.stderr)
        return 1
    if not args.no_report:
        try:
            print("demo: writing the report (the paper's section V from the bag)...", flush=True)
            report = report_run(str(out_dir), progress=True)
            print(f"report (the paper's section V from this run's bag): {report}")
        except (OSError, ValueError) as error:
            print(f"warning: no report: {error}", file=sys.stderr)
    print(f"\nrun directory: {out_dir}")
    if interrupted:
        return 130
    if summary.get("paths_delivered", 0) == 0:
        print("error: no request got a path in this run", file=sys.stderr)
        return 1
    if summary["paths_delivered"] < summary["requests"]:
        print(f"warning: {summary['requests'] - summary['paths_delivered']} requests got no path", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
