"""The demo's non-ROS processes started by roslaunch (which appends __name:= and __log:= arguments
that their own command lines would reject): the cloud server and the fleet learner with demo keys made on first
run, the WAN emulator, and the robot workload."""
import math
import multiprocessing
import sys
import threading
import time
from dataclasses import dataclass

import rospy
from std_msgs.msg import Float64

from offload_demos.keys import ensure_demo_keys
from offload_learner_py.nodes import params
from offload_demos.workload import LoadSchedule, parse_levels, run_workload


@dataclass(frozen=True)
class WorkloadNodeConfig:
    """robot_workload's settings beside its LoadSchedule (levels, phase_s, seed)."""
    budget_cores: float = 1.0
    """the robot's CPU budget in cores (its cgroup quota / period)."""
    processes: int = 1
    """processes sharing the burn: the kernel shares a cgroup's quota between runnable tasks, so more of them
    leave the planner less."""
    epoch: float = 0.0
    """CLOCK_MONOTONIC second at which the schedule starts, shared with the run's other schedules (goal
    generator, WAN emulator); 0: this node's start."""
    scenario: str = ""
    """a bench-policies scenario file (offload_demos.scenario): its load schedule replaces levels and phase_s
    (a scenario without one keeps them)."""


# robot_workload's ~name -> (dataclass, field), its default the field's.
WORKLOAD_PARAMETERS = {**{name: (LoadSchedule, name) for name in ("levels", "phase_s", "seed")},
                       **{name: (WorkloadNodeConfig, name) for name in WorkloadNodeConfig.__dataclass_fields__}}


def cloud_server_main():
    """demo_cloud_server [--demo-keys DIR] SERVER_ARGS...: offload_cloud's server command line (server_cli), with
    --keys-dir DIR/server added after generating DIR on first run."""
    from offload_cloud import server_cli

    sys.exit(server_cli.main(_with_demo_keys(rospy.myargv(sys.argv)[1:])))


def _with_demo_keys(argv):
    """A leading `--demo-keys DIR` becomes `--keys-dir DIR/server`, DIR generated on first run."""
    if argv[:1] == ["--demo-keys"] and len(argv) >= 2:
        root = ensure_demo_keys(argv[1])
        argv = argv[2:] + ["--keys-dir", str(root / "server")]
    return argv


def fleet_learner_main():
    """demo_fleet_learner [--demo-keys DIR] LEARNER_ARGS...: `offload-cloud-learner serve` (offload_cloud.learner.cli)
    with --keys-dir DIR/server, the demo's keys (the cloud server's), made on first run."""
    from offload_cloud.learner import cli

    sys.exit(cli.main(["serve", *_with_demo_keys(rospy.myargv(sys.argv)[1:])]))


def wan_emulator_main():
    """demo_wan_emulator EMULATOR_ARGS...: offload_demos.wan_emulator."""
    from offload_demos import wan_emulator

    sys.exit(wan_emulator.main(rospy.myargv(sys.argv)[1:]))


def _burn(schedule, budget_share, stop_event, began):
    run_workload(schedule, budget_share, stop_event.is_set, began=began)


def workload_main():
    """Robot workload node: burns a varying share of the robot's CPU budget.

    Parameters (private): WORKLOAD_PARAMETERS, LoadSchedule's levels (shares of the budget, one drawn per
    phase), phase_s (seconds per level) and seed, and WorkloadNodeConfig's fields.
    Topics: publishes ~load (std_msgs/Float64, latched): the current level, for the bag.
    """
    rospy.init_node("robot_workload")
    try:
        values = params.read(lambda name, default: rospy.get_param("~" + name, default), WORKLOAD_PARAMETERS)
        values["levels"] = parse_levels(values["levels"])
        schedule = LoadSchedule(**params.for_class(values, WORKLOAD_PARAMETERS, LoadSchedule))
        node = WorkloadNodeConfig(**params.for_class(values, WORKLOAD_PARAMETERS, WorkloadNodeConfig))
        budget_cores, processes, epoch = node.budget_cores, node.processes, node.epoch
        if node.scenario:
            from offload_demos.scenario import load_scenario
            schedule = load_scenario(node.scenario).load_schedule(schedule.seed, schedule)
        if not budget_cores > 0 or processes < 1:
            raise ValueError(f"~budget_cores must be positive and ~processes >= 1, got {budget_cores}, {processes}")
        if not (math.isfinite(epoch) and epoch >= 0):
            raise ValueError(f"~epoch must be a finite CLOCK_MONOTONIC time >= 0, got {epoch}")
    except ValueError as error:
        rospy.logfatal("%s", error)
        raise SystemExit(1) from None
    load_pub = rospy.Publisher("~load", Float64, queue_size=1, latch=True)
    # Forked helpers inherit the pinning and the cgroup; each burns its share of every level, in step
    # with this process because the schedule is a function of time since start and the seed.
    context = multiprocessing.get_context("fork")
    stop_helpers = context.Event()
    began = epoch if epoch > 0 else time.monotonic()
    helpers = [context.Process(target=_burn, args=(schedule, budget_cores / processes, stop_helpers, began),
                               daemon=True)
               for _ in range(processes - 1)]
    for helper in helpers:
        helper.start()
    stopped = threading.Event()
    rospy.on_shutdown(stopped.set)
    try:
        run_workload(schedule, budget_cores / processes, stopped.is_set,
                     on_level=lambda level: load_pub.publish(Float64(level)), began=began)
    finally:
        stop_helpers.set()
        for helper in helpers:
            helper.join(5)
