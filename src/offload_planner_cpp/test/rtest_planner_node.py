#!/usr/bin/env python3
"""rostest: the planner node on a real map answers ~plan and ~make_plan, reports bad requests with clear
statuses, keeps serving after them, survives malformed and rapidly changing maps, and publishes ~path and
~timing. Expected costs come from the pybind11 module on the same map file."""
import threading
import unittest

import numpy as np
from scipy import ndimage
import rospy
import rostest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid, Path
from nav_msgs.srv import GetPlan
from offload_msgs.msg import PlanTiming
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse
import rospkg

import offload_planner_cpp
from offload_planner_cpp.nodes.map_publisher import NumpyOccupancyGrid, to_message
from offload_planner_cpp.maps import load_map

R = PlanPathResponse


class PlannerNodeTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_planner_node")
        package = rospkg.RosPack().get_path("offload_planner_cpp")
        cls.map = load_map(package + "/maps/turtlebot3_world/map.yaml")
        # Two cells of the arena (the largest free component) and an obstacle cell on its edge.
        labels, _ = ndimage.label(cls.map.grid == 0, structure=np.ones((3, 3)))
        arena = labels == np.argmax(np.bincount(labels.ravel())[1:]) + 1
        cells = np.argwhere(arena)[:, ::-1]
        centre = cells.mean(axis=0)
        order = np.argsort(np.hypot(*(cells - centre).T))
        cls.home = tuple(int(v) for v in cells[order[0]])
        cls.away = tuple(int(v) for v in cells[order[len(order) // 3]])
        edge = (cls.map.grid == 100) & ndimage.binary_dilation(arena, structure=np.ones((3, 3)))
        cls.wall = tuple(int(v) for v in np.argwhere(edge)[0][::-1])
        for name in ("/planner/plan", "/planner/make_plan"):
            rospy.wait_for_service(name, timeout=60)
        cls.plan = rospy.ServiceProxy("/planner/plan", PlanPath)
        cls.make_plan = rospy.ServiceProxy("/planner/make_plan", GetPlan)
        cls.paths, cls.timings = [], []
        rospy.Subscriber("/planner/path", Path, cls.paths.append)
        rospy.Subscriber("/planner/timing", PlanTiming, cls.timings.append)
        # Wait until the node has the map (NO_MAP until then).
        deadline = rospy.Time.now() + rospy.Duration(30)
        while cls.call(cls.home, cls.away).status == R.NO_MAP and rospy.Time.now() < deadline:
            rospy.sleep(0.1)

    @classmethod
    def world(cls, cell):
        m = cls.map
        return m.origin_x + (cell[0] + 0.5) * m.resolution, m.origin_y + (cell[1] + 0.5) * m.resolution

    @staticmethod
    def pose(xy, frame="map"):
        p = PoseStamped()
        p.header.frame_id = frame
        p.pose.position.x, p.pose.position.y = xy
        p.pose.orientation.w = 1.0
        return p

    @classmethod
    def call(cls, start_cell, goal_cell, tolerance=0.0, frame="map"):
        req = PlanPathRequest(start=cls.pose(cls.world(start_cell), frame),
                              goal=cls.pose(cls.world(goal_cell), frame), tolerance=tolerance)
        return cls.plan(req)

    def free_pair(self, rng):
        free = np.argwhere(self.map.grid == 0)[:, ::-1]
        while True:
            s, g = (tuple(int(v) for v in free[i]) for i in rng.choice(len(free), 2, replace=False))
            try:
                return s, g, offload_planner_cpp.plan(self.map.grid, s, g)
            except offload_planner_cpp.NoPathError:
                continue

    def test_plans_match_the_core_on_the_same_map(self):
        rng = np.random.default_rng(5)
        for _ in range(10):
            s, g, expected = self.free_pair(rng)
            res = self.call(s, g)
            self.assertEqual(res.status, R.OK, res.message)
            self.assertEqual(res.path.header.frame_id, "map")
            self.assertEqual(len(res.path.poses), len(expected.path))
            self.assertAlmostEqual(res.cost_m, expected.cost * self.map.resolution, places=6)
            start, goal = res.path.poses[0].pose.position, res.path.poses[-1].pose.position
            self.assertAlmostEqual(start.x, self.world(s)[0], places=6)
            self.assertAlmostEqual(goal.y, self.world(g)[1], places=6)
            self.assertGreater(res.expansions, 0)
            self.assertGreater(res.planning_time_s, 0.0)
            self.assertGreater(res.map_stamp.to_sec(), 0.0)

    def test_make_plan_honours_tolerance(self):
        wall = self.wall
        req = dict(start=self.pose(self.world(self.home)), goal=self.pose(self.world(wall)))
        self.assertEqual(len(self.make_plan(tolerance=0.0, **req).plan.poses), 0)
        plan = self.make_plan(tolerance=0.25, **req).plan
        self.assertGreater(len(plan.poses), 0)
        end = plan.poses[-1].pose.position
        gx, gy = self.world(wall)
        self.assertLessEqual(np.hypot(end.x - gx, end.y - gy), 0.25 + 1e-6)

    def test_bad_requests_get_clear_statuses_and_the_node_keeps_serving(self):
        grid = self.map.grid
        wall = self.wall
        res = self.call(self.home, wall)
        self.assertEqual(res.status, R.GOAL_BLOCKED)
        self.assertIn("obstacle", res.message)
        self.assertEqual(self.call(wall, self.home).status, R.START_BLOCKED)
        off = self.plan(PlanPathRequest(start=self.pose(self.world(self.home)), goal=self.pose((1e3, 0.0))))
        self.assertEqual(off.status, R.GOAL_OFF_MAP)
        self.assertIn("off the map", off.message)
        res = self.call(self.home, self.away, frame="odom")
        self.assertEqual(res.status, R.BAD_FRAME)
        self.assertIn("odom", res.message)
        res = self.call(self.home, self.away, tolerance=float("nan"))
        self.assertEqual(res.status, R.INVALID_REQUEST)
        # A free cell outside the arena's component is unreachable.
        rng = np.random.default_rng(0)
        free = np.argwhere(grid == 0)[:, ::-1]
        for x, y in free[rng.permutation(len(free))]:
            try:
                offload_planner_cpp.plan(grid, self.home, (int(x), int(y)))
            except offload_planner_cpp.NoPathError:
                res = self.call(self.home, (int(x), int(y)))
                self.assertEqual(res.status, R.NO_PATH)
                self.assertIn("unreachable", res.message)
                self.assertEqual(len(res.path.poses), 0)
                break
        else:
            self.fail("no unreachable free cell on the test map")
        self.assertEqual(self.call(self.home, self.away).status, R.OK)

    def test_path_and_timing_are_published(self):
        before = len(self.timings)
        res = self.call(self.home, self.away)
        self.assertEqual(res.status, R.OK)
        deadline = rospy.Time.now() + rospy.Duration(10)
        while (len(self.timings) <= before or not self.paths) and rospy.Time.now() < deadline:
            rospy.sleep(0.05)
        self.assertGreater(len(self.timings), before)
        timing = self.timings[-1]
        self.assertEqual(timing.planner, "local")
        self.assertGreaterEqual(timing.service_time_s, timing.planning_time_s)
        self.assertTrue(self.paths and self.paths[-1].header.frame_id == "map")

    def test_malformed_and_changing_maps(self):
        stamp = self.call(self.home, self.away).map_stamp
        pub = rospy.Publisher("/map", OccupancyGrid, queue_size=10)
        bad = OccupancyGrid()
        bad.header.frame_id = "map"
        bad.info.width, bad.info.height, bad.info.resolution = 10, 10, 0.05
        bad.data = [0] * 7  # declares 100 cells
        deadline = rospy.Time.now() + rospy.Duration(10)
        while pub.get_num_connections() == 0 and rospy.Time.now() < deadline:
            rospy.sleep(0.05)
        pub.publish(bad)
        rospy.sleep(0.5)
        res = self.call(self.home, self.away)
        self.assertEqual(res.status, R.OK, "the last good map keeps serving")
        self.assertEqual(res.map_stamp, stamp)

        # New maps arriving while requests run: every request plans on one whole map.
        np_pub = rospy.Publisher("/map", NumpyOccupancyGrid, queue_size=10)
        while np_pub.get_num_connections() == 0 and rospy.Time.now() < deadline:
            rospy.sleep(0.05)
        stop = threading.Event()

        def publish_maps():
            k = 1
            while not stop.is_set():
                np_pub.publish(to_message(self.map, "map", rospy.Time(1000 + k)))
                k += 1
                rospy.sleep(0.01)

        publisher = threading.Thread(target=publish_maps)
        publisher.start()
        try:
            stamps = set()
            for _ in range(30):
                res = self.call(self.home, self.away)
                self.assertEqual(res.status, R.OK, res.message)
                stamps.add(res.map_stamp.to_sec())
        finally:
            stop.set()
            publisher.join()
        self.assertGreater(len(stamps), 1, "map updates reached the node during the requests")


if __name__ == "__main__":
    rostest.rosrun("offload_planner_cpp", "planner_node", PlannerNodeTest)
