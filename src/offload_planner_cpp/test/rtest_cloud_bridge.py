#!/usr/bin/env python3
"""rostest: the cloud_bridge node answers ~plan exactly as the local planner node does on the same map
(statuses, messages, poses, costs), publishes ~latency heartbeats and per-request latencies, and answers
CLOUD_TIMEOUT within its timeout once the cloud server is gone."""
import os
import subprocess
import sys
import tempfile
import time
import unittest

import numpy as np
import rospkg
import rospy
import rostest
from geometry_msgs.msg import PoseStamped
from offload_msgs.msg import LinkLatency, PlanTiming
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

from offload_planner_cpp.cloud import keys
from offload_planner_cpp.cloud.server import CloudServer, ServerConfig
from offload_planner_cpp.maps import load_map

R = PlanPathResponse
TIMEOUT_S = 2.0


class CloudBridgeTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_cloud_bridge")
        cls.keys_dir = tempfile.TemporaryDirectory()
        server_keys = keys.generate(cls.keys_dir.name, ["robot"])
        cls.server = CloudServer(ServerConfig(bind="tcp://127.0.0.1:0", keys_dir=str(server_keys), workers=2))
        endpoint = cls.server.start()
        cls.bridge = subprocess.Popen(
            [sys.executable, "-m", "offload_planner_cpp.nodes.cloud_bridge", "__name:=cloud_bridge",
             f"_endpoint:={endpoint}", f"_keys_dir:={os.path.join(cls.keys_dir.name, 'robot')}",
             f"_timeout_s:={TIMEOUT_S}", "_heartbeat_period_s:=0.2"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)   # its log is in ROS_HOME/log
        # Runs even when setUpClass fails: an orphaned node would outlive the test's master.
        cls.addClassCleanup(cls.stop_processes)
        cls.latencies, cls.timings = [], []
        rospy.Subscriber("/cloud_bridge/latency", LinkLatency, cls.latencies.append)
        rospy.Subscriber("/cloud_bridge/timing", PlanTiming, cls.timings.append)
        for name in ("/planner/plan", "/cloud_bridge/plan"):
            rospy.wait_for_service(name, timeout=60)
        cls.local = rospy.ServiceProxy("/planner/plan", PlanPath)
        cls.cloud = rospy.ServiceProxy("/cloud_bridge/plan", PlanPath)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and R.NO_MAP in (cls.local(cls.request((0, 0), (0, 0))).status,
                                                           cls.cloud(cls.request((0, 0), (0, 0))).status):
            rospy.sleep(0.1)

    @classmethod
    def stop_processes(cls):
        cls.bridge.terminate()
        try:
            cls.bridge.wait(10)
        except subprocess.TimeoutExpired:
            cls.bridge.kill()
        cls.server.stop()
        cls.keys_dir.cleanup()

    @staticmethod
    def request(start, goal, tolerance=0.0, frame="map"):
        def pose(xy):
            p = PoseStamped()
            p.header.frame_id = frame
            p.pose.position.x, p.pose.position.y = xy
            p.pose.orientation.z, p.pose.orientation.w = 0.6, 0.8
            return p
        return PlanPathRequest(start=pose(start), goal=pose(goal), tolerance=tolerance)

    def assert_same_answer(self, req):
        local, cloud = self.local(req), self.cloud(req)
        self.assertEqual(cloud.status, local.status, cloud.message)
        self.assertEqual(cloud.message, local.message)
        self.assertEqual(cloud.expansions, local.expansions)
        self.assertEqual(cloud.cost_m, local.cost_m)
        self.assertEqual(cloud.map_stamp, local.map_stamp)
        self.assertEqual(cloud.path.header.frame_id, local.path.header.frame_id)
        self.assertEqual([p.pose for p in cloud.path.poses], [p.pose for p in local.path.poses])
        return cloud

    def test_1_same_answers_as_the_local_planner(self):
        rng = np.random.default_rng(3)
        statuses = set()
        # Random world points over and around the map, plus the edge cases of the local node's tests.
        for _ in range(40):
            start, goal = rng.uniform(-12, 12, 2), rng.uniform(-12, 12, 2)
            statuses.add(self.assert_same_answer(self.request(start, goal, rng.choice([0.0, 0.3]))).status)
        # Pairs of free cells, so most requests plan; a point anywhere inside a cell, not only its centre.
        package = rospkg.RosPack().get_path("offload_planner_cpp")
        grid_map = load_map(package + "/maps/turtlebot3_world/map.yaml")
        free = np.argwhere(grid_map.grid == 0)[:, ::-1]
        for _ in range(30):
            a, b = free[rng.choice(len(free), 2, replace=False)]
            start, goal = ((grid_map.origin_x + (cell[0] + rng.uniform()) * grid_map.resolution,
                            grid_map.origin_y + (cell[1] + rng.uniform()) * grid_map.resolution) for cell in (a, b))
            statuses.add(self.assert_same_answer(self.request(start, goal)).status)
        self.assert_same_answer(self.request((0, 0), (1, 1), frame="odom"))
        self.assert_same_answer(self.request((0, 0), (1, 1), tolerance=float("nan")))
        self.assert_same_answer(self.request((0, 0), (1e3, 0)))
        # Huge but finite coordinates: off the map on both nodes (no overflow in the bridge's conversion).
        self.assertEqual(self.assert_same_answer(self.request((1e308, 0), (1, 1))).status, R.START_OFF_MAP)
        self.assertEqual(self.assert_same_answer(self.request((0, 0), (-1e308, 1e308))).status, R.GOAL_OFF_MAP)
        self.assertIn(R.OK, statuses)
        self.assertGreater(len(statuses), 1)

    def test_2_latency_is_published(self):
        before = len([m for m in self.latencies if m.source == LinkLatency.REQUEST])
        self.assertEqual(self.cloud(self.request((-1.0, -0.5), (1.0, 0.5))).status, R.OK)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and (
                len([m for m in self.latencies if m.source == LinkLatency.REQUEST]) <= before
                or not any(m.source == LinkLatency.HEARTBEAT for m in self.latencies)):
            rospy.sleep(0.05)
        heartbeats = [m for m in self.latencies if m.source == LinkLatency.HEARTBEAT]
        requests = [m for m in self.latencies if m.source == LinkLatency.REQUEST]
        self.assertTrue(heartbeats and heartbeats[-1].reachable and heartbeats[-1].round_trip_s > 0)
        self.assertTrue(requests and requests[-1].reachable)
        self.assertTrue(self.timings and self.timings[-1].planner == "cloud")

    def test_3_timeout_when_the_cloud_is_gone(self):
        self.server.stop()
        started = time.monotonic()
        res = self.cloud(self.request((-1.0, -0.5), (1.0, 0.5)))
        self.assertEqual(res.status, R.CLOUD_TIMEOUT)
        self.assertLess(time.monotonic() - started, TIMEOUT_S + 1.5)
        rospy.sleep(1.5)
        self.assertFalse(self.latencies[-1].reachable)


if __name__ == "__main__":
    rostest.rosrun("offload_planner_cpp", "cloud_bridge_rtest", CloudBridgeTest)
