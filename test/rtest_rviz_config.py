#!/usr/bin/env python3
"""rostest of launch/config/offload.rviz against the demo stack (see rviz_config.test): every display
names a topic the stack publishes, with the message type the display draws, and its messages come in a
frame RViz can place: one that exists in TF and reaches the fixed frame, which exists in TF too (else
RViz's Global Status says "Fixed Frame: No TF data")."""
import os
import sys
import time
import unittest

import rospy
import rostest
import tf2_ros
import yaml
from roslib.message import get_message_class

sys.path.insert(0, os.path.dirname(os.path.realpath(__file__)))
from rtest_online_stack import launch_file  # noqa: E402  (shared helper)

# offload_demos.rviz_view reads the same configuration: one walk over its displays
from offload_demos.rviz_view import displays  # noqa: E402

# The message type each RViz display class subscribes to (rviz's default plugins).
DISPLAY_TYPES = {"rviz/Map": "nav_msgs/OccupancyGrid", "rviz/Path": "nav_msgs/Path",
                 "rviz/Pose": "geometry_msgs/PoseStamped", "rviz/PoseArray": "geometry_msgs/PoseArray",
                 "rviz/Marker": "visualization_msgs/Marker", "rviz/MarkerArray": "visualization_msgs/MarkerArray",
                 "rviz/Odometry": "nav_msgs/Odometry", "rviz/LaserScan": "sensor_msgs/LaserScan",
                 "rviz/PointStamped": "geometry_msgs/PointStamped", "rviz/PolygonStamped": "geometry_msgs/PolygonStamped"}
WAIT_S = 90.0    # for the stack to come up and for both sides to deliver a path (random policy)


def rviz_config():
    with open(os.path.join(os.path.dirname(launch_file("offload_demo.launch")), "config", "offload.rviz")) as f:
        return yaml.safe_load(f)


def tf_frames(buffer):
    """Every frame TF knows: the children and their parents."""
    tree = yaml.safe_load(buffer.all_frames_as_yaml()) or {}
    return set(tree) | {entry["parent"] for entry in tree.values()}


class RvizConfigTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_rviz_config")
        cls.config = rviz_config()
        cls.fixed_frame = cls.config["Visualization Manager"]["Global Options"]["Fixed Frame"]
        cls.tf_buffer = tf2_ros.Buffer()
        cls.tf_listener = tf2_ros.TransformListener(cls.tf_buffer)

    def test_every_display_is_a_published_topic_of_its_type_in_a_frame_that_exists(self):
        shown = [d for d in displays(self.config) if d.get("Enabled", True) and "Topic" in d]
        self.assertTrue(any(d["Class"] == "rviz/Map" for d in shown), "no map display")
        deadline = time.monotonic() + WAIT_S
        published = {}
        wanted = {d["Topic"] for d in shown}
        while time.monotonic() < deadline and not wanted <= set(published):
            published = dict(rospy.get_published_topics())
            time.sleep(0.5)
        # Problems are collected, not asserted one by one: rosunit's result file drops subTest failures.
        problems = []
        for display in shown:
            name, topic = display["Name"], display["Topic"]
            expected = DISPLAY_TYPES.get(display["Class"])
            if expected is None:
                problems.append(f"{name}: add the message type of {display['Class']} to DISPLAY_TYPES")
            elif topic not in published:
                problems.append(f"display '{name}' shows {topic}, which nothing publishes")
            elif published[topic] != expected:
                problems.append(f"display '{name}' draws {expected}, but {topic} carries {published[topic]}")
            else:
                problems.extend(self.frame_problems(name, topic, get_message_class(expected), deadline))
        self.assertFalse(problems, "\n".join(problems + [f"published: {sorted(published)}"]))

    def frame_problems(self, name, topic, message_class, deadline):
        try:
            message = rospy.wait_for_message(topic, message_class, timeout=max(1.0, deadline - time.monotonic()))
        except rospy.ROSException:
            return [f"display '{name}': no message on {topic} within {WAIT_S:g} s"]
        frame = message.header.frame_id.lstrip("/")
        if not frame:
            return [f"display '{name}': {topic} has an empty frame_id"]
        if frame not in tf_frames(self.tf_buffer) or not self.tf_buffer.can_transform(
                self.fixed_frame, frame, rospy.Time(0), rospy.Duration(10.0)):
            return [f"display '{name}': {topic} is in frame '{frame}', which TF does not take to the fixed frame "
                    f"'{self.fixed_frame}' (TF frames: {sorted(tf_frames(self.tf_buffer))})"]
        return []

    def test_the_fixed_frame_exists_in_tf(self):
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline and self.fixed_frame not in tf_frames(self.tf_buffer):
            time.sleep(0.5)
        self.assertIn(self.fixed_frame, tf_frames(self.tf_buffer),
                      f"RViz would warn 'Fixed Frame: No TF data': nothing in TF names '{self.fixed_frame}'")


if __name__ == "__main__":
    rostest.rosrun("offload_demos", "rviz_config", RvizConfigTest)
