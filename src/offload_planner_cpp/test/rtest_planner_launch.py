#!/usr/bin/env python3
"""rostest: launch/planner.launch as a user runs it plans on the bundled Husky playpen map, with the node's
defaults (launch/config/planner.yaml ships no override) and a user's overlay file on top."""
import unittest

import rospy
import rostest
from geometry_msgs.msg import PoseStamped
from offload_msgs.msg import PlanTiming
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

R = PlanPathResponse


def pose(x, y):
    p = PoseStamped()
    p.header.frame_id = "map"
    p.pose.position.x, p.pose.position.y = x, y
    p.pose.orientation.w = 1.0
    return p


class PlannerLaunchTest(unittest.TestCase):
    def test_plans_with_the_yaml_configuration(self):
        rospy.init_node("rtest_planner_launch")
        self.assertFalse(rospy.has_param("/planner/lethal_threshold"), "config/planner.yaml restates no default")
        self.assertEqual(rospy.get_param("/planner/planner_name"), "overlaid", "the overlay file wins")
        timings = []
        rospy.Subscriber("/planner/timing", PlanTiming, timings.append)
        rospy.wait_for_service("/planner/plan", timeout=60)
        plan = rospy.ServiceProxy("/planner/plan", PlanPath)
        deadline = rospy.Time.now() + rospy.Duration(60)
        # The playpen's origin area is free space; wait for the map, then plan 1 m.
        res = plan(PlanPathRequest(start=pose(0.0, 0.0), goal=pose(1.0, 0.0)))
        while res.status == R.NO_MAP and rospy.Time.now() < deadline:
            rospy.sleep(0.2)
            res = plan(PlanPathRequest(start=pose(0.0, 0.0), goal=pose(1.0, 0.0)))
        self.assertEqual(res.status, R.OK, res.message)
        self.assertAlmostEqual(res.cost_m, 1.0, delta=0.051)   # one cell of slack: ends snap to cell centres
        while not timings and rospy.Time.now() < deadline:
            rospy.sleep(0.05)
        self.assertEqual(timings[-1].planner, "overlaid")


if __name__ == "__main__":
    rostest.rosrun("offload_planner_cpp", "planner_launch", PlannerLaunchTest)
