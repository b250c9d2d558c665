"""`make bench-online`: what the learner node adds to a request over calling the chosen planner
directly, measured in the same run.

A private master runs map_publisher and planner_node on the TurtleBot3 map, a cloud server and bridge
(for a real b_t), and the learner with a frozen DQN, probe rate 0 and both of its sides pointed at the
local planner node, so whatever it decides the chosen planner is the one the direct call uses. Requests
alternate direct / through the learner on the same goals; the overhead of each pair is the routed time
minus the direct time. Both are persistent service connections, as a robot's caller would hold. rosbag
records the learner's topics as on a robot (record.launch's), and the learner process's own CPU (all its
threads, /proc) over the routed requests is what the robot pays per request to decide."""
import argparse
import math
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from offload_planner_cpp import free_cells
from offload_planner_cpp._core import check_map
from offload_demos.loopback import free_port
from offload_demos.robot_cpu import process_cpu_s
from offload_demos.goals import GoalSampler, default_start_cell


# record.launch's topics that the learner publishes
RECORDED = ("/offload_learner/decision", "/offload_learner/outcome", "/offload_learner/stats", "/offload_learner/config",
            "/offload_learner/rejected", "/offload_learner/path_local", "/offload_learner/path_cloud",
            "/offload_learner/goal")


def learner_cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as stat:
        return process_cpu_s(stat.read())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=400, help="pairs of requests (default 400)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--policy", default="dqn", help="the learner's policy (default a frozen DQN)")
    parser.add_argument("--map", help="map_server YAML (default: the bundled TurtleBot3 world)")
    parser.add_argument("--rate-hz", type=float, default=0.0,
                        help="pairs per second (default 0: back to back). A robot asks a few times a second, and "
                             "a process woken four times a second pays more per request than one kept busy")
    args = parser.parse_args(argv)

    import rospkg

    map_yaml = args.map or os.path.join(rospkg.RosPack().get_path("offload_planner_cpp"), "maps", "turtlebot3_world",
                                        "map.yaml")
    port = free_port()
    env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}")
    os.environ["ROS_MASTER_URI"] = env["ROS_MASTER_URI"]
    quiet = dict(stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    processes = [subprocess.Popen(["roscore", "-p", str(port)], **quiet)]
    try:
        time.sleep(2.0)   # roscore has no readiness signal short of polling the master
        import rospy
        from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

        from offload_planner_cpp.maps import load_map

        server = subprocess.Popen([sys.executable, "-m", "offload_cloud", "--bind",
                                   "tcp://127.0.0.1:0", "--insecure", "--workers", "1", "--log-level", "WARNING"],
                                  stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
        processes.append(server)
        endpoint = server.stdout.readline().split()[-1]
        processes += [
            subprocess.Popen(["rosrun", "offload_planner_cpp", "map_publisher", f"_map:={map_yaml}"], **quiet),
            subprocess.Popen(["rosrun", "offload_planner_cpp", "planner_node", "__name:=planner"], **quiet),
            subprocess.Popen([sys.executable, "-m", "offload_learner_py.nodes.cloud_bridge", "__name:=cloud_bridge",
                              f"_endpoint:={endpoint}", "_insecure:=true"], **quiet),
            subprocess.Popen([sys.executable, "-m", "offload_learner_py.nodes.learner", "__name:=offload_learner",
                              f"_policy:={args.policy}", "_learn:=false", "_probe_rate:=0.0", "_cloud_service:=/planner/plan",
                              "_progress_every:=0"], **quiet),
        ]
        bag_dir = tempfile.mkdtemp(prefix="bench-online-")
        processes.append(subprocess.Popen(["rosbag", "record", "-O", os.path.join(bag_dir, "run.bag"), *RECORDED],
                                          **quiet))
        learner_pid, planner_pid = processes[-2].pid, processes[-4].pid
        rospy.init_node("bench_online", anonymous=True)
        for service in ("/planner/plan", "/offload_learner/plan"):
            rospy.wait_for_service(service, timeout=120)
        occupancy = load_map(map_yaml)
        height, width = occupancy.grid.shape
        yaw = occupancy.origin_yaw
        _, frame = check_map(width, height, occupancy.grid.size, occupancy.resolution, occupancy.origin_x,
                             occupancy.origin_y, (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)))
        free = free_cells(occupancy.grid)
        start = default_start_cell(free)
        sampler = GoalSampler(free, start, seed=args.seed)
        from offload_msgs.msg import OffloadDecision

        decisions = []
        rospy.Subscriber("/offload_learner/decision", OffloadDecision, decisions.append)
        direct = rospy.ServiceProxy("/planner/plan", PlanPath, persistent=True)
        routed = rospy.ServiceProxy("/offload_learner/plan", PlanPath, persistent=True)

        def request(goal_cell):
            req = PlanPathRequest()
            for pose, cell in ((req.start, start), (req.goal, goal_cell)):
                pose.header.frame_id = "map"
                pose.pose.position.x, pose.pose.position.y = frame.cell_to_world(*cell)
                pose.pose.orientation.w = 1.0
            return req

        planner_accounted = [0.0]

        def timed(proxy, req):
            began = time.perf_counter()
            response = proxy(req)
            elapsed = time.perf_counter() - began
            if response.status != PlanPathResponse.OK:
                raise RuntimeError(f"planning failed: {response.message}")
            planner_accounted[0] += response.cpu_s
            return elapsed

        deadline = time.monotonic() + 30
        while direct(request(sampler.draw())).status == PlanPathResponse.NO_MAP and time.monotonic() < deadline:
            time.sleep(0.1)
        for _ in range(20):   # warm both paths (connections, caches) before measuring
            req = request(sampler.draw())
            timed(direct, req)
            timed(routed, req)
        direct_s, routed_s = [], []
        cpu_began, planner_began = learner_cpu_s(learner_pid), learner_cpu_s(planner_pid)
        planner_accounted[0] = 0.0
        next_at = time.monotonic()
        for k in range(args.requests):
            if args.rate_hz > 0:
                next_at += 1.0 / args.rate_hz
                time.sleep(max(0.0, next_at - time.monotonic()))
            req = request(sampler.draw())
            first, second = (direct, routed) if k % 2 == 0 else (routed, direct)   # alternate the order
            a, b = timed(first, req), timed(second, req)
            direct_s.append(a if first is direct else b)
            routed_s.append(b if first is direct else a)
        learner_cpu_ms = (learner_cpu_s(learner_pid) - cpu_began) * 1e3 / args.requests
        planner_cpu_ms = (learner_cpu_s(planner_pid) - planner_began) * 1e3 / (2 * args.requests)
        planner_own_ms = planner_accounted[0] * 1e3 / (2 * args.requests)
        direct_s, routed_s = np.array(direct_s) * 1e3, np.array(routed_s) * 1e3
        overhead = routed_s - direct_s
        pace = f"{args.rate_hz:g} pairs/s" if args.rate_hz > 0 else "back to back"
        print(f"bench-online: {args.requests} request pairs on {map_yaml} ({width} x {height}), {pace}, same goals, "
              f"same run")
        print(f"{'':34}{'median (ms)':>12}{'p99 (ms)':>10}")
        print(f"{'direct to /planner/plan':34}{np.median(direct_s):12.3f}{np.percentile(direct_s, 99):10.3f}")
        print(f"{'through /offload_learner/plan':34}{np.median(routed_s):12.3f}{np.percentile(routed_s, 99):10.3f}")
        print(f"{'added by the learner (per pair)':34}{np.median(overhead):12.3f}{np.percentile(overhead, 99):10.3f}")
        time.sleep(0.5)
        print(f"decisions the learner published: {len(decisions)} (a decision per routed request)")
        print(f"learner process CPU per routed request (every thread, rosbag recording): {learner_cpu_ms:.2f} ms")
        print(f"planner process CPU per plan: {planner_cpu_ms:.2f} ms, of which its planning thread accounted "
              f"{planner_own_ms:.2f} ms")
        print(f"budget: 2 ms median -> {'within' if np.median(overhead) <= 2.0 else 'OVER'}")
        return 0
    finally:
        for process in reversed(processes):
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


if __name__ == "__main__":
    sys.exit(main())
