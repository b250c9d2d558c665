"""The demo's non-ROS processes started by roslaunch (which appends __name:= and __log:= arguments
that their own command lines would reject): the cloud server with demo keys made on first run, the WAN
emulator, and the robot workload."""
import math
import multiprocessing
import sys
import threading
import time

import rospy
from std_msgs.msg import Float64

from offload_demos.keys import ensure_demo_keys
from offload_demos.workload import LoadSchedule, parse_levels, run_workload


def cloud_server_main():
    """demo_cloud_server [--demo-keys DIR] SERVER_ARGS...: offload_cloud's server command line (server_cli), with
    --keys-dir DIR/server added after generating DIR on first run."""
    from offload_cloud import server_cli

    argv = rospy.myargv(sys.argv)[1:]
    if argv[:1] == ["--demo-keys"] and len(argv) >= 2:
        root = ensure_demo_keys(argv[1])
        argv = argv[2:] + ["--keys-dir", str(root / "server")]
    sys.exit(server_cli.main(argv))


def wan_emulator_main():
    """demo_wan_emulator EMULATOR_ARGS...: offload_demos.wan_emulator."""
    from offload_demos import wan_emulator

    sys.exit(wan_emulator.main(rospy.myargv(sys.argv)[1:]))


def _burn(schedule, budget_share, stop_event, began):
    run_workload(schedule, budget_share, stop_event.is_set, began=began)


def workload_main():
    """Robot workload node: burns a varying share of the robot's CPU budget.

    Parameters (private):
      ~levels (list of float, [0.0, 0.3, 0.55, 0.75])  shares of the budget, one drawn per phase
      ~phase_s (float, 8.0)          seconds per level
      ~budget_cores (float, 1.0)     the robot's CPU budget in cores (its cgroup quota / period)
      ~processes (int, 1)            processes sharing the burn: the kernel shares a cgroup's quota
                                     between runnable tasks, so more of them leave the planner less
      ~seed (int, 1)
      ~epoch (float, 0.0)            CLOCK_MONOTONIC second at which the schedule starts, shared with the
                                     run's other schedules (goal generator, WAN emulator); 0: this node's start
    Topics: publishes ~load (std_msgs/Float64, latched): the current level, for the bag.
    """
    rospy.init_node("robot_workload")
    try:
        schedule = LoadSchedule(parse_levels(rospy.get_param("~levels", [0.0, 0.3, 0.55, 0.75])),
                                float(rospy.get_param("~phase_s", 8.0)), int(rospy.get_param("~seed", 1)))
        budget_cores = float(rospy.get_param("~budget_cores", 1.0))
        processes = int(rospy.get_param("~processes", 1))
        epoch = float(rospy.get_param("~epoch", 0.0))
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
