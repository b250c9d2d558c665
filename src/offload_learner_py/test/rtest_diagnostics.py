#!/usr/bin/env python3
"""rostest (diagnostics.test): the planner, the cloud bridge and the learner publish /diagnostics; with the cloud
server stopped the bridge's status is ERROR and the learner's shows the breaker open within 3 s (the bridge's and the
learner's default heartbeat and breaker settings), and both return to OK once the server is back on its port; the
analyzers of launch/config/diagnostics_agg.yaml group them under one offload entry."""
import subprocess
import sys
import threading
import time
import unittest

import rospy
import rostest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from offload_demos.loopback import free_port, stop_process as stop

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
BRIDGE, LEARNER, PLANNER = "cloud_bridge: cloud link", "offload_learner: offload decisions", "planner: planner"


class DiagnosticsTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_diagnostics")
        cls.lock = threading.Lock()
        cls.latest = {}                     # status name -> (arrival time, DiagnosticStatus)
        rospy.Subscriber("/diagnostics", DiagnosticArray, cls.on_diagnostics, queue_size=100)
        rospy.Subscriber("/diagnostics_agg", DiagnosticArray, cls.on_diagnostics, queue_size=100)
        cls.port = free_port()
        cls.processes = {}
        cls.addClassCleanup(lambda: [stop(p) for p in cls.processes.values()])
        cls.start_server()
        cls.processes["bridge"] = subprocess.Popen(
            [sys.executable, "-m", "offload_learner_py.nodes.cloud_bridge", "__name:=cloud_bridge",
             f"_endpoint:=tcp://127.0.0.1:{cls.port}", "_insecure:=true"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cls.processes["learner"] = subprocess.Popen(
            [sys.executable, "-m", "offload_learner_py.nodes.learner", "__name:=offload_learner", "_policy:=local",
             "_mode:=deployed"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    @classmethod
    def start_server(cls):
        cls.processes["server"] = subprocess.Popen(
            [sys.executable, "-m", "offload_cloud", "--bind", f"tcp://127.0.0.1:{cls.port}", "--insecure", "--workers",
             "1", "--log-level", "WARNING"], stdout=subprocess.PIPE, text=True)
        line = cls.processes["server"].stdout.readline()
        assert line.startswith("listening on "), line

    @classmethod
    def on_diagnostics(cls, msg):
        now = time.monotonic()
        with cls.lock:
            for status in msg.status:
                cls.latest[status.name] = (now, status)

    def wait_for(self, want, timeout_s, what):
        """Until every name in `want` has a status meeting its predicate, published after this call began; the time
        it took."""
        began = time.monotonic()
        while time.monotonic() - began < timeout_s:
            with self.lock:
                seen = {name: self.latest.get(name) for name in want}
            if all(entry is not None and entry[0] >= began and test(entry[1]) for name, test in want.items()
                   for entry in [seen[name]]):
                return time.monotonic() - began
            time.sleep(0.02)
        with self.lock:
            got = {name: (s.level, s.message) for name, (_, s) in self.latest.items()}
        self.fail(f"{what} not within {timeout_s} s: {got}")

    def test_link_down_and_back(self):
        level = lambda wanted: (lambda status: status.level == wanted)   # noqa: E731
        self.wait_for({BRIDGE: level(OK), LEARNER: level(OK), PLANNER: level(OK)}, 60, "all three OK at start")
        with self.lock:
            planner = dict((v.key, v.value) for v in self.latest[PLANNER][1].values)
            bridge = dict((v.key, v.value) for v in self.latest[BRIDGE][1].values)
        self.assertEqual(planner["map size (cells)"], "384 x 384")
        self.assertNotEqual(bridge["round trip (ms)"], "n/a")

        stop(self.processes.pop("server"))
        took = self.wait_for({BRIDGE: level(ERROR),
                              LEARNER: lambda s: s.level == WARN and "breaker open" in s.message},
                             10, "bridge ERROR and learner breaker open")
        self.assertLessEqual(took, 3.0, f"the link's loss took {took:.2f} s to show")
        with self.lock:
            learner = dict((v.key, v.value) for v in self.latest[LEARNER][1].values)
        self.assertEqual(learner["breaker"], "open")
        # launch/config/diagnostics_agg.yaml: one offload entry, the link under it, its level the worst below it
        self.wait_for({"/offload/Cloud link": level(ERROR), "/offload": level(ERROR),
                       "/offload/Cloud link/cloud link": level(ERROR),
                       "/offload/Local planner/planner": level(OK)}, 5, "the aggregated offload entry")

        self.start_server()
        self.wait_for({BRIDGE: level(OK), LEARNER: level(OK)}, 15, "both OK with the server back")


if __name__ == "__main__":
    rostest.rosrun("offload_learner_py", "diagnostics_rtest", DiagnosticsTest)
