#!/usr/bin/env python3
"""rostest (reconfigure.test): `dynparam set` on the running robot side. The learner's probe rate: the next decisions
are probes, the latched ~config (recorded in the bag) says so from then on. The planner's inflation radius: the next
local plan and the next cloud plan (the bridge follows the planner's ~parameter_updates) detour round the pillars.
An invalid value (the same rules as the YAML's) is refused and the old one kept on both nodes."""
import subprocess
import sys
import threading
import time
import unittest

import roslib.packages
import rospy
import rostest
from dynamic_reconfigure.client import Client
from dynamic_reconfigure.msg import Config
from offload_msgs.msg import LearnerConfig, OffloadDecision
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

from offload_demos.loopback import free_port, stop_process as stop

# Cells (170, 200) and (230, 200) of turtlebot3_world (0.05 m, origin -10, -10): between the pillars, where a
# cost-aware path keeps away from them once the map is inflated (length 63.3 -> 72.7 cells at 0.3 m).
START, GOAL = (-1.475, 0.025), (1.525, 0.025)


def dynparam_set(node: str, name: str, value: str) -> None:
    """`rosrun dynamic_reconfigure dynparam set NODE NAME VALUE`, with this interpreter: dynparam's shebang takes the
    python3 first on PATH, which in a pyenv or conda shell cannot import rospy."""
    dynparam = roslib.packages.find_node("dynamic_reconfigure", "dynparam")[0]
    subprocess.run([sys.executable, dynparam, "set", node, name, value], check=True, timeout=60,
                   stdout=subprocess.DEVNULL)


def request() -> PlanPathRequest:
    req = PlanPathRequest(tolerance=0.0)
    for pose, (x, y) in ((req.start, START), (req.goal, GOAL)):
        pose.header.frame_id = "map"
        pose.pose.position.x, pose.pose.position.y = x, y
        pose.pose.orientation.w = 1.0
    return req


class ReconfigureTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_reconfigure")
        cls.lock = threading.Lock()
        cls.decisions, cls.configs, cls.planner_updates = [], [], []
        rospy.Subscriber("/offload_learner/decision", OffloadDecision, cls.keep(cls.decisions), queue_size=100)
        rospy.Subscriber("/offload_learner/config", LearnerConfig, cls.keep(cls.configs), queue_size=10)
        rospy.Subscriber("/planner/parameter_updates", Config, cls.keep(cls.planner_updates), queue_size=10)
        port = free_port()
        cls.processes = {}
        cls.addClassCleanup(lambda: [stop(p) for p in cls.processes.values()])
        cls.processes["server"] = subprocess.Popen(
            [sys.executable, "-m", "offload_cloud", "--bind", f"tcp://127.0.0.1:{port}", "--insecure", "--workers", "1",
             "--log-level", "WARNING"], stdout=subprocess.PIPE, text=True)
        line = cls.processes["server"].stdout.readline()
        assert line.startswith("listening on "), line
        cls.processes["bridge"] = subprocess.Popen(
            [sys.executable, "-m", "offload_learner_py.nodes.cloud_bridge", "__name:=cloud_bridge",
             f"_endpoint:=tcp://127.0.0.1:{port}", "_insecure:=true"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cls.processes["learner"] = subprocess.Popen(
            [sys.executable, "-m", "offload_learner_py.nodes.learner", "__name:=offload_learner", "_policy:=local",
             "_mode:=deployed", "_probe_rate:=0.0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for service in ("/planner/plan", "/cloud_bridge/plan", "/offload_learner/plan",
                        "/planner/set_parameters", "/offload_learner/set_parameters"):
            rospy.wait_for_service(service, timeout=90)
        cls.local = rospy.ServiceProxy("/planner/plan", PlanPath)
        cls.cloud = rospy.ServiceProxy("/cloud_bridge/plan", PlanPath)
        cls.learner = rospy.ServiceProxy("/offload_learner/plan", PlanPath)

    @classmethod
    def keep(cls, into):
        def on_message(msg):
            with cls.lock:
                into.append((time.monotonic(), msg))
        return on_message

    def plans(self):
        """(local, cloud) path lengths in m of the test's request, each side asked directly."""
        answers = self.local(request()), self.cloud(request())
        for answer in answers:
            self.assertEqual(answer.status, PlanPathResponse.OK, answer.message)
        return tuple(round(answer.cost_m, 6) for answer in answers)

    def decided(self, count=3):
        """The probe flags of the learner's next `count` decisions."""
        with self.lock:
            before = len(self.decisions)
        for _ in range(count):
            self.assertEqual(self.learner(request()).status, PlanPathResponse.OK)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            with self.lock:
                if len(self.decisions) >= before + count:
                    return [msg.probe for _, msg in self.decisions[before:before + count]]
            time.sleep(0.02)
        self.fail("the learner's decisions did not arrive")

    def latest(self, messages):
        with self.lock:
            return messages[-1] if messages else (None, None)

    def test_1_probe_rate(self):
        self.assertEqual(self.decided(), [False] * 3, "deployed, probe_rate 0, a fixed policy: no probes")
        began = time.monotonic()
        dynparam_set("/offload_learner", "probe_rate", "1.0")
        self.assertEqual(self.decided(), [True] * 3, "probe_rate 1: every next decision a probe")
        at, config = self.latest(self.configs)
        self.assertGreaterEqual(at, began, "the change was not republished on ~config")
        self.assertEqual((config.probe_rate, config.mode), (1.0, "deployed"))

        client = Client("/offload_learner", timeout=30)
        kept = client.update_configuration({"probe_rate": 1.5})
        self.assertEqual(kept["probe_rate"], 1.0, "an invalid probe rate must leave the old one in force")
        kept = client.update_configuration({"cloud_timeout_s": -2.0, "probe_rate": 0.5})   # refused whole
        self.assertEqual((kept["probe_rate"], kept["cloud_timeout_s"]), (1.0, 5.0))
        self.assertEqual(self.decided(), [True] * 3)
        self.assertEqual(self.latest(self.configs)[0], at, "a refused change is no new setting in the bag")
        self.assertEqual(rospy.get_param("/offload_learner/probe_rate"), 1.0)

    def test_2_inflation_radius(self):
        before = self.plans()
        self.assertEqual(before[0], before[1], "both sides plan alike")
        client = Client("/planner", timeout=30)
        began = time.monotonic()
        dynparam_set("/planner", "inflation_radius", "0.3")
        self.assertEqual(client.get_configuration(timeout=10)["inflation_radius"], 0.3)
        deadline = time.monotonic() + 5   # the bridge hears the planner's update as a topic: a moment later
        while time.monotonic() < deadline and self.plans()[1] == before[1]:
            time.sleep(0.05)
        after = self.plans()
        self.assertGreater(after[0], before[0] + 0.3, f"the local plan did not detour: {before} -> {after}")
        self.assertEqual(after[1], after[0], f"the cloud did not get the new inflation: {before} -> {after}")
        at, update = self.latest(self.planner_updates)
        self.assertGreaterEqual(at, began)
        self.assertIn(0.3, [p.value for p in update.doubles if p.name == "inflation_radius"])

        kept = client.update_configuration({"inflation_radius": -1.0})
        self.assertEqual(kept["inflation_radius"], 0.3, "an invalid radius must leave the old one in force")
        in_force = client.get_configuration(timeout=10)["algorithm"]
        kept = client.update_configuration({"algorithm": "jps"})   # jps with cost_factor 3: the table's pair rule
        self.assertNotEqual(in_force, "jps")
        self.assertEqual(kept["algorithm"], in_force, "a refused algorithm must leave the one in force")
        time.sleep(0.5)   # the bridge would have heard a change by now
        self.assertEqual(self.plans(), after)


if __name__ == "__main__":
    rostest.rosrun("offload_learner_py", "reconfigure_rtest", ReconfigureTest)
