#!/usr/bin/env python3
"""rostest: the cloud_bridge node answers ~plan exactly as the local planner node does on the same map
(statuses, poses, costs, expansions), with costs checked against the independent scipy oracle for both,
also with non-default ~lethal_threshold and ~unknown_is_obstacle; serves ~make_plan and ~path; publishes
~latency heartbeats and per-request latencies; and answers CLOUD_TIMEOUT within its timeout once the
cloud server is gone."""
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
from nav_msgs.msg import Path
from nav_msgs.srv import GetPlan, GetPlanRequest
from offload_msgs.msg import LinkLatency, PlanTiming
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse
from scipy.sparse import csgraph

from offload_cloud import keys
from offload_cloud.server import CloudServer, ServerConfig
from offload_demos.grid_graph import grid_graph
from offload_demos.loopback import stop_process
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
        common = [sys.executable, "-m", "offload_learner_py.nodes.cloud_bridge", f"_endpoint:={endpoint}",
                  f"_keys_dir:={os.path.join(cls.keys_dir.name, 'robot')}", f"_timeout_s:={TIMEOUT_S}"]
        # Their logs are in ROS_HOME/log.
        cls.bridges = [subprocess.Popen(common + ["__name:=cloud_bridge", "_heartbeat_period_s:=0.2"],
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL),
                       subprocess.Popen(common + ["__name:=lenient_bridge", "_lethal_threshold:=101",
                                                  "_unknown_is_obstacle:=false"],
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
        # Runs even when setUpClass fails: an orphaned node would outlive the test's master.
        cls.addClassCleanup(cls.stop_processes)
        package = rospkg.RosPack().get_path("offload_planner_cpp")
        cls.map = load_map(package + "/maps/turtlebot3_world/map.yaml")
        cls.paths = []
        rospy.Subscriber("/cloud_bridge/path", Path, cls.paths.append)
        cls.latencies, cls.timings = [], []
        rospy.Subscriber("/cloud_bridge/latency", LinkLatency, cls.latencies.append)
        rospy.Subscriber("/cloud_bridge/timing", PlanTiming, cls.timings.append)
        for name in ("/planner/plan", "/cloud_bridge/plan", "/lenient_planner/plan", "/lenient_bridge/plan"):
            rospy.wait_for_service(name, timeout=60)
        cls.local = rospy.ServiceProxy("/planner/plan", PlanPath)
        cls.cloud = rospy.ServiceProxy("/cloud_bridge/plan", PlanPath)
        cls.lenient_local = rospy.ServiceProxy("/lenient_planner/plan", PlanPath)
        cls.lenient_cloud = rospy.ServiceProxy("/lenient_bridge/plan", PlanPath)
        cls.local_make_plan = rospy.ServiceProxy("/planner/make_plan", GetPlan)
        cls.cloud_make_plan = rospy.ServiceProxy("/cloud_bridge/make_plan", GetPlan)
        deadline = time.monotonic() + 30
        services = (cls.local, cls.cloud, cls.lenient_local, cls.lenient_cloud)
        while time.monotonic() < deadline and R.NO_MAP in [s(cls.request((0, 0), (0, 0))).status for s in services]:
            rospy.sleep(0.1)

    @classmethod
    def stop_processes(cls):
        for bridge in cls.bridges:
            bridge.terminate()   # all at once, then each waited for
        for bridge in cls.bridges:
            stop_process(bridge, grace_s=10.0)
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

    def assert_same_answer(self, req, local_service=None, cloud_service=None):
        local, cloud = (local_service or self.local)(req), (cloud_service or self.cloud)(req)
        self.assertEqual(cloud.status, local.status, cloud.message)
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
        for answer in self.free_cell_pairs(rng, 30, self.local, self.cloud):
            statuses.add(answer.status)
        self.assert_same_answer(self.request((0, 0), (1, 1), frame="odom"))
        self.assert_same_answer(self.request((0, 0), (1, 1), tolerance=float("nan")))
        self.assert_same_answer(self.request((0, 0), (1e3, 0)))
        # Huge but finite coordinates: off the map on both nodes (no overflow in the bridge's conversion).
        self.assertEqual(self.assert_same_answer(self.request((1e308, 0), (1, 1))).status, R.START_OFF_MAP)
        self.assertEqual(self.assert_same_answer(self.request((0, 0), (-1e308, 1e308))).status, R.GOAL_OFF_MAP)
        self.assertIn(R.OK, statuses)
        self.assertGreater(len(statuses), 1)

    def test_1d_link_bytes_and_cpu_are_reported(self):
        """The bridge says what a plan cost the link and its own CPU; a request refused on the robot
        never touches the link."""
        free = np.argwhere(self.map.grid == 0)[:, ::-1]
        world = lambda cell: (self.map.origin_x + (cell[0] + 0.5) * self.map.resolution,  # noqa: E731
                              self.map.origin_y + (cell[1] + 0.5) * self.map.resolution)
        answer = self.cloud(self.request(world(free[0]), world(free[-1])))
        self.assertIn(answer.status, (R.OK, R.NO_PATH), answer.message)
        self.assertGreater(answer.bytes_sent, 0)
        self.assertGreater(answer.bytes_received, 0)
        self.assertGreater(answer.cpu_s, 0.0)
        refused = self.cloud(self.request((0, 0), (1, 1), frame="odom"))
        self.assertEqual((refused.status, refused.bytes_sent, refused.bytes_received), (R.BAD_FRAME, 0, 0))

    def free_cell_pairs(self, rng, count, local_service, cloud_service, **options):
        """Same answers on random pairs of free cells, and the cost is the scipy oracle's (in metres)."""
        grid_map = self.map
        free = np.argwhere(grid_map.grid == 0)[:, ::-1]
        graph = grid_graph(grid_map.grid, **options)
        width = grid_map.grid.shape[1]
        answers = []
        for _ in range(count):
            a, b = free[rng.choice(len(free), 2, replace=False)]
            start, goal = ((grid_map.origin_x + (cell[0] + rng.uniform()) * grid_map.resolution,
                            grid_map.origin_y + (cell[1] + rng.uniform()) * grid_map.resolution) for cell in (a, b))
            answer = self.assert_same_answer(self.request(start, goal), local_service, cloud_service)
            oracle = csgraph.dijkstra(graph, indices=int(a[1] * width + a[0]))[b[1] * width + b[0]]
            if np.isinf(oracle):
                self.assertEqual(answer.status, R.NO_PATH)
            else:
                self.assertEqual(answer.status, R.OK, answer.message)
                self.assertAlmostEqual(answer.cost_m, oracle * grid_map.resolution, delta=1e-6)
            answers.append(answer)
        return answers

    def test_1b_options_reach_node_and_bridge(self):
        """With lethal_threshold 101 and unknown cells free every cell is passable: the answers follow
        the oracle with those options, and differ from the defaults' on the same requests."""
        rng = np.random.default_rng(11)
        options = dict(lethal_threshold=101, unknown_is_obstacle=False)
        answers = self.free_cell_pairs(rng, 8, self.lenient_local, self.lenient_cloud, **options)
        self.assertTrue(all(a.status == R.OK for a in answers))
        # Through the walls: from one corner of the map to the other, impossible with the defaults.
        corner = (self.map.origin_x + 0.5 * self.map.resolution, self.map.origin_y + 0.5 * self.map.resolution)
        far = (self.map.origin_x + (self.map.grid.shape[1] - 0.5) * self.map.resolution,
               self.map.origin_y + (self.map.grid.shape[0] - 0.5) * self.map.resolution)
        straight = self.assert_same_answer(self.request(corner, far), self.lenient_local, self.lenient_cloud)
        self.assertEqual(straight.status, R.OK)
        diagonal = min(self.map.grid.shape) - 1
        self.assertAlmostEqual(straight.cost_m, (np.sqrt(2) * diagonal + max(self.map.grid.shape) - 1 - diagonal)
                               * self.map.resolution, delta=1e-6)
        self.assertNotEqual(self.local(self.request(corner, far)).status, R.OK)

    def test_1c_make_plan_and_path(self):
        home, away = (-1.0, -0.5), (1.0, 0.5)   # inside the TurtleBot3 world arena
        req = self.request(home, away)
        planned = self.cloud(req)
        self.assertEqual(planned.status, R.OK)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not (self.paths and self.paths[-1].poses == planned.path.poses):
            rospy.sleep(0.05)
        self.assertEqual(self.paths[-1].poses, planned.path.poses, "~path publishes the delivered path")
        made = self.cloud_make_plan(GetPlanRequest(start=req.start, goal=req.goal, tolerance=0.0)).plan
        self.assertEqual([p.pose for p in made.poses], [p.pose for p in planned.path.poses])
        self.assertEqual(made.header.frame_id, "map")
        # Failure: an empty plan in the global frame, stamped now, from both nodes alike.
        before = rospy.Time.now()
        for service in (self.cloud_make_plan, self.local_make_plan):
            failed = service(GetPlanRequest(start=req.start, goal=self.request(home, (1e3, 0)).goal)).plan
            self.assertEqual(failed.poses, [])
            self.assertEqual(failed.header.frame_id, "map")
            self.assertGreaterEqual(failed.header.stamp, before)

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
    rostest.rosrun("offload_learner_py", "cloud_bridge_rtest", CloudBridgeTest)
