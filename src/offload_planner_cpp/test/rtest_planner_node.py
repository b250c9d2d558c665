#!/usr/bin/env python3
"""rostest: the planner node on a real map answers ~plan and ~make_plan, reports bad requests with clear
statuses, keeps serving after them, survives malformed and rapidly changing maps (each request on one whole
map), lets neither a short plan nor a map update wait behind long plans, and publishes ~path and ~timing.
Expected costs come from the pybind11 module on the same map file."""
import dataclasses
import os
import threading
import time
import unittest
import xmlrpc.client

import numpy as np
from scipy import ndimage
import rospy
import rostest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid, Path
from nav_msgs.srv import GetPlan
from std_msgs.msg import UInt64
from offload_msgs.msg import PlanTiming
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse
import rosgraph
import rospkg

import offload_planner_cpp
from offload_planner_cpp.nodes.map_publisher import NumpyOccupancyGrid, to_message
from offload_planner_cpp.maps import load_map

R = PlanPathResponse
SPLIT_SIDE = 7000   # split_map's cells a side: 49 M, under the node's ~max_map_cells (64 M)


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
            # The node's own CPU for the request: at least the core's planning, never the link's bytes.
            self.assertGreater(res.cpu_s, 0.0)
            self.assertEqual((res.bytes_sent, res.bytes_received), (0, 0))

    def test_idle_node_sleeps(self):
        """Waiting for requests costs the robot next to nothing: the node's threads wake about 36 times a second
        (roscpp's own poll loops), not the 115 of AsyncSpinner's 0.1 s polls and waitForShutdown's 0.05 s."""
        api = rosgraph.Master("/rtest_planner_node").lookupNode("/planner")
        pid = xmlrpc.client.ServerProxy(api).getPid("/rtest_planner_node")[2]

        def wakes():
            total = 0
            for task in os.listdir(f"/proc/{pid}/task"):
                with open(f"/proc/{pid}/task/{task}/status") as status:
                    total += sum(int(line.split()[1]) for line in status if line.startswith("voluntary_ctxt"))
            return total

        before, began = wakes(), time.monotonic()
        time.sleep(3.0)
        per_s = (wakes() - before) / (time.monotonic() - began)
        self.assertLess(per_s, 70.0, f"the idle planner node woke {per_s:.0f} times a second")

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

    def test_every_request_gets_a_timing(self):
        """A burst of short plans from four callers: one ~timing message each, none dropped."""
        rospy.sleep(0.5)   # timings of earlier tests' requests have arrived
        began = rospy.Time.now()
        per_caller = 150

        def caller():
            plan = rospy.ServiceProxy("/planner/plan", PlanPath, persistent=True)
            req = PlanPathRequest(start=self.pose(self.world(self.home)), goal=self.pose(self.world(self.home)))
            for _ in range(per_caller):
                self.assertEqual(plan(req).status, R.OK)
            plan.close()

        threads = [threading.Thread(target=caller) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(120)
        count = lambda: sum(1 for t in list(self.timings) if t.header.stamp >= began)   # noqa: E731
        deadline = rospy.Time.now() + rospy.Duration(10)
        while count() < 4 * per_caller and rospy.Time.now() < deadline:
            rospy.sleep(0.05)
        rospy.sleep(0.5)
        self.assertEqual(count(), 4 * per_caller)

    def test_malformed_and_changing_maps(self):
        stamp = self.call(self.home, self.away).map_stamp
        pub = rospy.Publisher("/map", OccupancyGrid, queue_size=10)
        bad = OccupancyGrid()
        bad.header.frame_id = "map"
        bad.info.width, bad.info.height, bad.info.resolution = 10, 10, 0.05
        bad.data = [0] * 7  # declares 100 cells
        connected(pub, 10.0).publish(bad)
        rospy.sleep(0.5)
        res = self.call(self.home, self.away)
        self.assertEqual(res.status, R.OK, "the last good map keeps serving")
        self.assertEqual(res.map_stamp, stamp)

        # Two different maps alternate while requests run (even stamps: the map as it is; odd: with a wall
        # across the straight route): each answer's cost is that of the map its stamp names, so every
        # request planned on one whole map.
        route = offload_planner_cpp.plan(self.map.grid, self.home, self.away)
        mx, my = route.path[len(route.path) // 2]
        for radius in range(1, 20):   # a block on the route's middle, large enough to lengthen the route
            walled = self.map.grid.copy()
            walled[my - radius:my + radius + 1, mx - radius:mx + radius + 1] = 100
            try:
                detour = offload_planner_cpp.plan(walled, self.home, self.away).cost
            except (offload_planner_cpp.NoPathError, offload_planner_cpp.PlanError):
                continue
            if detour > route.cost + 1e-6:
                break
        costs = {0: route.cost, 1: detour}
        self.assertGreater(costs[1], costs[0])
        variants = {0: self.map, 1: dataclasses.replace(self.map, grid=walled)}
        np_pub = connected(rospy.Publisher("/map", NumpyOccupancyGrid, queue_size=10), 10.0)
        stop = threading.Event()

        def publish_maps():
            k = 1
            while not stop.is_set():
                np_pub.publish(to_message(variants[k % 2], "map", rospy.Time(1000 + k)))
                k += 1
                rospy.sleep(0.01)

        publisher = threading.Thread(target=publish_maps)
        publisher.start()
        try:
            seen = set()
            for _ in range(40):
                res = self.call(self.home, self.away)
                self.assertEqual(res.status, R.OK, res.message)
                if not 1000 < res.map_stamp.to_sec() < 5000:
                    continue   # still the map from before the stream (its stamp names no variant)
                variant = int(res.map_stamp.to_sec() - 1000) % 2
                self.assertAlmostEqual(res.cost_m, costs[variant] * self.map.resolution, places=6)
                seen.add(variant)
        finally:
            stop.set()
            publisher.join()
        self.assertEqual(seen, {0, 1}, "both maps reached the node during the requests")
        np_pub.publish(to_message(self.map, "map", rospy.Time(5000)))   # leave the real map in place

    def publish_map(self, grid, stamp_s):
        """Publishes the test map with `grid` and waits until the node plans on it."""
        pub = connected(rospy.Publisher("/map", NumpyOccupancyGrid, queue_size=2))
        deadline = rospy.Time.now() + rospy.Duration(30)
        pub.publish(to_message(dataclasses.replace(self.map, grid=grid), "map", rospy.Time(stamp_s)))
        while self.call(self.home, self.home).map_stamp != rospy.Time(stamp_s) and rospy.Time.now() < deadline:
            rospy.sleep(0.1)
        return pub

    def test_zy_cancel_stops_a_running_plan_and_one_not_yet_begun(self):
        """Of two identical long plans started together, the one cancelled on ~cancel answers CANCELLED
        first; a cancel that arrives before its request makes that request answer CANCELLED at once."""
        self.publish_map(split_map(), 9000)
        cancel = connected(rospy.Publisher("/planner/cancel", UInt64, queue_size=10))
        corner, far = self.world((0, 0)), self.world((SPLIT_SIDE - 1, SPLIT_SIDE - 1))
        finished = {}

        def long_plan(cancel_id):
            req = PlanPathRequest(start=self.pose(corner), goal=self.pose(far), cancel_id=cancel_id)
            res = rospy.ServiceProxy("/planner/plan", PlanPath)(req)
            finished[cancel_id] = (rospy.get_time(), res)

        threads = [threading.Thread(target=long_plan, args=(cancel_id,)) for cancel_id in (4242, 4243)]
        for thread in threads:
            thread.start()
        rospy.sleep(0.2)
        cancel.publish(UInt64(4242))
        for thread in threads:
            thread.join(120)
        self.assertEqual(finished[4242][1].status, R.CANCELLED, finished[4242][1].message)
        self.assertEqual(len(finished[4242][1].path.poses), 0)
        self.assertEqual(finished[4243][1].status, R.NO_PATH, finished[4243][1].message)
        self.assertLess(finished[4242][0], finished[4243][0], "the cancelled plan ran to its end")
        self.assertLess(finished[4242][1].expansions, finished[4243][1].expansions)

        cancel.publish(UInt64(4344))
        rospy.sleep(0.5)
        early = self.plan(PlanPathRequest(start=self.pose(corner), goal=self.pose(far), cancel_id=4344))
        self.assertEqual((early.status, early.expansions), (R.CANCELLED, 0), early.message)
        self.publish_map(self.map.grid, 9001)

    def test_zz_long_plans_starve_neither_short_plans_nor_map_updates(self):
        """Two long plans on a large map run while a new map arrives and a short plan is asked: the
        short one is answered on the new map before either long one ends."""
        # An attempt tests something only when both long plans are running as the short one is asked. On a loaded
        # machine a long plan can reach the node after the map swap (GOAL_OFF_MAP on the small map: CI, 3d17f2f) or,
        # after a longer pause, end before the short plan is asked (fresh-ci, 666b468): such an attempt is run again
        # with the pause moved the other way. A node that makes the short plan wait still fails a valid attempt.
        # (Before 6f7115a "late" was likely the node's own doing as well: the serving thread that woke took both long
        # plans and began the second only after the first had ended. test_serve_queue.cpp now holds that.)
        pause, attempts = 0.4, []
        for attempt in range(6):
            res, short_done, finished, asked = self.long_plans_beside_a_map_swap(7000 + 2000 * attempt, pause)
            late = any(status == R.GOAL_OFF_MAP for _, status in finished.values())
            early = any(end < asked + 0.25 for end, _ in finished.values())
            attempts.append((pause, "late" if late else "early" if early else "valid"))
            if not late and not early:
                break
            pause = min(2 * pause, 1.0) if late else max(pause / 2, 0.02)
        print(f"long-plan attempts (pause s, verdict): {attempts}", flush=True)
        self.assertEqual(attempts[-1][1], "valid", f"no attempt overlapped the long plans: {attempts}")
        self.assertEqual(res.status, R.OK)
        self.assertEqual(res.map_stamp, rospy.Time(8000 + 2000 * attempt),
                         "the new map was taken in during the long plans")
        self.assertEqual([finished[k][1] for k in range(2)], [R.NO_PATH, R.NO_PATH])
        self.assertLess(short_done, min(t for t, _ in finished.values()),
                        "the short plan and the map update waited behind the long plans")

    def long_plans_beside_a_map_swap(self, stamp, pause):
        """Publishes the large map (stamp), starts two long plans on it, waits `pause`, publishes the small map
        (stamp + 1000) and plans on it: (the short plan's response, when it ended, {k: (end, status)}, when the
        small map was published)."""
        big_map = dataclasses.replace(self.map, grid=split_map())
        pub = connected(rospy.Publisher("/map", NumpyOccupancyGrid, queue_size=2))
        deadline = rospy.Time.now() + rospy.Duration(30)
        pub.publish(to_message(big_map, "map", rospy.Time(stamp)))
        corner, far = self.world((0, 0)), self.world((SPLIT_SIDE - 1, SPLIT_SIDE - 1))
        long_req = PlanPathRequest(start=self.pose(corner), goal=self.pose(far))
        while self.plan(PlanPathRequest(start=self.pose(corner), goal=self.pose(self.world((1, 1))))) \
                .map_stamp != rospy.Time(stamp) and rospy.Time.now() < deadline:
            rospy.sleep(0.1)
        finished = {}
        # Each long plan's proxy is made and connected before the clock starts: made inside the thread, the second
        # one's master lookup and connection once took longer than the pause below.
        proxies = [rospy.ServiceProxy("/planner/plan", PlanPath, persistent=True) for _ in range(2)]
        for proxy in proxies:
            proxy.wait_for_service(30)
            proxy(PlanPathRequest(start=self.pose(corner), goal=self.pose(self.world((1, 1)))))   # connects it
        ready = threading.Barrier(3)

        def long_plan(name):
            ready.wait(30)
            res = proxies[name](long_req)
            finished[name] = (rospy.get_time(), res.status)

        threads = [threading.Thread(target=long_plan, args=(k,)) for k in range(2)]
        for thread in threads:
            thread.start()
        ready.wait(30)
        rospy.sleep(pause)
        asked = rospy.get_time()
        pub.publish(to_message(self.map, "map", rospy.Time(stamp + 1000)))
        res = self.call(self.home, self.away)
        while res.map_stamp != rospy.Time(stamp + 1000) and rospy.Time.now() < deadline:
            res = self.call(self.home, self.away)
        short_done = rospy.get_time()
        for thread in threads:
            thread.join(120)
        for proxy in proxies:
            proxy.close()
        pub.unregister()
        return res, short_done, finished, asked


def connected(pub, timeout_s: float = 30.0):
    """`pub` once the node has subscribed to it (or after timeout_s): a message published before is lost."""
    deadline = time.monotonic() + timeout_s
    while pub.get_num_connections() == 0 and time.monotonic() < deadline:
        rospy.sleep(0.05)
    return pub


def split_map() -> np.ndarray:
    """SPLIT_SIDE x SPLIT_SIDE cells, a wall down the middle: a plan from one corner to the other is the longest
    this map has, whichever way it searches (both ends flood their half before NO_PATH). A plan thread's first
    plan on it also pays for its buffers; an empty map's corner-to-corner plan was no longer than that. At 7000
    cells a side the Dijkstra waves take about 1.7 s on this machine (0.7 s at 5000, too close to the pauses the
    tests need on a loaded machine)."""
    grid = np.zeros((SPLIT_SIDE, SPLIT_SIDE), np.int8)
    grid[:, SPLIT_SIDE // 2] = 100
    return grid


if __name__ == "__main__":
    rostest.rosrun("offload_planner_cpp", "planner_node", PlannerNodeTest)
