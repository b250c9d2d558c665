#!/usr/bin/env python3
"""rostest of the online system (see online_stack.test): the learner between the local planner node
and the cloud bridge, with the goal generator and rosbag, then a learner restart and a cloud failure."""
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
import unittest

import rosbag
import rospy
import rostest
from offload_msgs.msg import OffloadDecision, OffloadOutcome, RequestRejected, TrainingStats
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse

from offload_learner_py.core.checkpoint import load_checkpoint
from offload_learner_py.data.records import NO_PATH_DELIVERED, pair_records, transition_table

WORKSPACE = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))
CLOUD_TIMEOUT_S = 1.0
FIRST_RUN = 24
RECORDED_TOPICS = ("/offload_learner/decision", "/offload_learner/outcome", "/offload_learner/stats", "/offload_learner/config",
                   "/offload_learner/goal", "/cloud_bridge/latency", "/cloud_bridge/timing", "/planner/timing",
                   "/goal_generator/goal", "/map_metadata", "/planner/parameter_updates")


def launch_file(name):
    """record.launch from the workspace's launch/ (the test may run from devel/ or from the source)."""
    for base in (WORKSPACE, os.environ.get("OFFLOAD_WORKSPACE", ""), os.getcwd()):
        path = os.path.join(base, "launch", name)
        if os.path.exists(path):
            return path
    raise FileNotFoundError(f"launch/{name} not found from {WORKSPACE}")


def start_learner_node(checkpoint: str, *params: str) -> subprocess.Popen:
    """The learner node in learning mode with a small warm-up, checkpointing every 5 steps, waiting for the
    recorder, ~stats after every request; `params` add or override private parameters (`_name:=value`). Returns once it serves."""
    learner = subprocess.Popen(
        [sys.executable, "-m", "offload_learner_py.nodes.learner", "__name:=offload_learner",
         f"_checkpoint:={checkpoint}", "_checkpoint_every:=5", f"_cloud_timeout_s:={CLOUD_TIMEOUT_S}",
         "_mode:=learning", "_wait_for_recorder_s:=30", "_dqn:={learning_starts: 8, train_frequency: 1}",
         "_stats_period_s:=0", *params],   # ~stats after every request: the tests wait for them one by one
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rospy.wait_for_service("/offload_learner/plan", timeout=90)
    return learner


def spawn_cloud_server(port: int = 0):
    """The cloud server as its own process, plaintext, one worker, on a loopback port (0: any free one);
    (process, endpoint) once it listens."""
    server = subprocess.Popen([sys.executable, "-m", "offload_cloud", "--bind",
                               f"tcp://127.0.0.1:{port}", "--insecure", "--workers", "1", "--log-level", "WARNING"],
                              stdout=subprocess.PIPE, text=True)
    line = server.stdout.readline()
    assert line.startswith("listening on "), line
    return server, line.split()[-1]


def stop(process, sig=signal.SIGINT, timeout_s=20):
    if process is None or process.poll() is not None:
        return
    process.send_signal(sig)
    try:
        process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


class WaitsForRecords(unittest.TestCase):
    """A test whose subscribers fill records under `lock`: wait until a predicate on them holds."""
    wait_timeout_s = 90

    def wait_for(self, predicate, timeout_s=None, what="condition"):
        deadline = time.monotonic() + (timeout_s or self.wait_timeout_s)
        while time.monotonic() < deadline:
            with self.lock:
                if predicate():
                    return
            time.sleep(0.05)
        self.fail(f"timed out waiting for {what}")


class OnlineStackTest(WaitsForRecords):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_online_stack")
        cls.tmp = tempfile.TemporaryDirectory()
        cls.checkpoint = os.path.join(cls.tmp.name, "learner.pt")
        cls.bag = os.path.join(cls.tmp.name, "online.bag")
        cls.processes = {}
        cls.addClassCleanup(cls.stop_all)
        cls.start_server()
        cls.processes["bridge"] = subprocess.Popen(
            [sys.executable, "-m", "offload_learner_py.nodes.cloud_bridge", "__name:=cloud_bridge",
             f"_endpoint:={cls.endpoint}", "_insecure:=true", f"_timeout_s:={CLOUD_TIMEOUT_S}", "_retries:=0",
             "_heartbeat_period_s:=0.2", "_heartbeat_timeout_s:=0.5"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cls.decisions, cls.outcomes, cls.stats, cls.rejected = [], [], [], []
        cls.lock = threading.Lock()
        rospy.Subscriber("/offload_learner/decision", OffloadDecision, cls.keep(cls.decisions))
        rospy.Subscriber("/offload_learner/outcome", OffloadOutcome, cls.keep(cls.outcomes))
        rospy.Subscriber("/offload_learner/stats", TrainingStats, cls.keep(cls.stats))
        rospy.Subscriber("/offload_learner/rejected", RequestRejected, cls.keep(cls.rejected))
        cls.processes["record"] = subprocess.Popen(["roslaunch", launch_file("record.launch"), f"bag:={cls.bag}"],
                                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        cls.start_learner()

    @classmethod
    def keep(cls, into):
        def callback(msg):
            with cls.lock:
                into.append(msg)
        return callback

    @classmethod
    def start_server(cls):
        cls.processes["server"], cls.endpoint = spawn_cloud_server()

    @classmethod
    def start_learner(cls):
        cls.processes["learner"] = start_learner_node(cls.checkpoint)

    @classmethod
    def stop_all(cls):
        for name in ("learner", "record", "bridge", "server"):
            stop(cls.processes.get(name))
        cls.tmp.cleanup()


    def call(self, goal_xy):
        plan = rospy.ServiceProxy("/offload_learner/plan", PlanPath)
        request = PlanPathRequest()
        for pose, xy in ((request.start, (-1.0, 0.5)), (request.goal, goal_xy)):
            pose.header.frame_id = "map"
            pose.pose.position.x, pose.pose.position.y = xy
            pose.pose.orientation.w = 1.0
        request.tolerance = 0.3
        return plan(request)

    GOALS = [(1.0, 0.5), (-0.5, -1.5), (0.5, 1.7), (1.8, -0.2), (-1.8, 0.1), (-0.5, -1.5)]

    def test_1_requests_answered_and_recorded(self):
        generator = subprocess.Popen(
            [sys.executable, "-m", "offload_demos.goal_generator", "__name:=goal_generator",
             f"_count:={FIRST_RUN}", "_period_s:=0.05", "_seed:=3", "_start_x:=-1.0", "_start_y:=0.5"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.assertEqual(generator.wait(120), 0)
        self.wait_for(lambda: len(self.outcomes) >= FIRST_RUN, what=f"{FIRST_RUN} outcomes")
        with self.lock:
            decisions, outcomes = list(self.decisions), list(self.outcomes)
        self.assertEqual(len(decisions), FIRST_RUN)
        self.assertTrue(all(o.delivered != NO_PATH_DELIVERED for o in outcomes), "a reachable goal got no path")
        self.assertTrue(all(o.local_measured and o.cloud_measured and o.reward_valid for o in outcomes))
        for o in outcomes:
            self.assertEqual(o.local_status, PlanPathResponse.OK)
            self.assertEqual(o.cloud_status, PlanPathResponse.OK)
            self.assertGreater(o.local_s, 0.0)
            self.assertGreater(o.cloud_s, 0.0)
        # p_t: "not measured" (0) until the local planner has timed a plan, then its measured rate (d_t/s)
        rates = [d.local_plan_rate for d in decisions]
        self.assertEqual(rates[0], 0.0)
        self.assertTrue(all(0.0 <= rate < 1e6 for rate in rates), rates)
        self.assertTrue(any(rate > 0.0 for rate in rates[1:]), rates)
        # the caller got the first good path: never slower than the slower side
        self.assertTrue(all(o.delivered_s <= max(o.local_s, o.cloud_s) + 0.05 for o in outcomes))
        stop(self.processes.pop("record"))
        with rosbag.Bag(self.bag) as bag:
            counts = {topic: info.message_count for topic, info in bag.get_type_and_topic_info().topics.items()}
            bag_decisions = [m for _, m, _ in bag.read_messages(topics=["/offload_learner/decision"])]
            bag_outcomes = [m for _, m, _ in bag.read_messages(topics=["/offload_learner/outcome"])]
        for topic in RECORDED_TOPICS:
            self.assertGreater(counts.get(topic, 0), 0, f"{topic} missing from the bag: {sorted(counts)}")
        log = pair_records(bag_decisions, bag_outcomes)   # raises unless they pair by id and agree
        self.assertEqual(len(log), FIRST_RUN)
        table = transition_table(log)
        self.assertEqual(len(table), FIRST_RUN)
        by_id = {o.request_id: o for o in bag_outcomes}
        for row in range(len(table)):
            self.assertAlmostEqual(table.reward[row], by_id[int(table.t[row])].reward)

    def test_1b_refused_input_is_answered_but_not_a_decision(self):
        """A goal off the map or a non-finite goal gets the planners' status at once; neither planner is called
        (no timing), nothing is decided or learned, and the refusal is recorded."""
        with self.lock:
            decisions, rejected = len(self.decisions), len(self.rejected)
        self.assertEqual(self.call((1e15, 0.5)).status, PlanPathResponse.GOAL_OFF_MAP)
        self.assertEqual(self.call((float("nan"), 0.5)).status, PlanPathResponse.INVALID_REQUEST)
        self.wait_for(lambda: len(self.rejected) >= rejected + 2, what="the refusals")
        self.assertEqual(self.call(self.GOALS[0]).status, PlanPathResponse.OK)
        self.wait_for(lambda: len(self.decisions) > decisions, what="the next decision")
        with self.lock:
            self.assertEqual(len(self.decisions), decisions + 1)   # only the plannable request was decided
            self.assertEqual([r.status for r in self.rejected[rejected:]],
                             [PlanPathResponse.GOAL_OFF_MAP, PlanPathResponse.INVALID_REQUEST])

    def test_2_learner_restarts_from_its_checkpoint(self):
        self.wait_for(lambda: os.path.exists(self.checkpoint), what="a checkpoint")
        with self.lock:
            steps_before = self.stats[-1].steps
        os.kill(self.processes["learner"].pid, signal.SIGKILL)   # no shutdown hook: the periodic checkpoint
        self.processes["learner"].wait(10)
        saved_steps = load_checkpoint(self.checkpoint).steps
        self.assertGreater(saved_steps, 0)
        self.assertLessEqual(saved_steps, steps_before)
        self.start_learner()
        with self.lock:
            seen = len(self.stats)
        for k, goal in enumerate(self.GOALS, start=1):
            self.assertEqual(self.call(goal).status, PlanPathResponse.OK)
            # The next request waits for this one's outcome: a request arriving while this probe's slower side
            # still runs would cancel it (a newer request takes the local planner), and an unmeasured side
            # teaches nothing. Back to back, a loaded machine lost 2 of the probes this counts (46 != 50).
            self.wait_for(lambda: len(self.stats) >= seen + k, what=f"stats of request {k} after the restart")
        with self.lock:
            resumed = [s.steps for s in self.stats[seen:]]
        # Every probe teaches both actions (two transitions); the pending transition is stored when the
        # next one arrives, so steps trail by one. Outcomes may finish out of order (a probe's slower side
        # runs on while the next request is served), so the counts are compared as a set.
        self.assertGreaterEqual(min(resumed), saved_steps + 1)
        self.assertEqual(max(resumed), saved_steps + 2 * len(self.GOALS) - 1)

    def test_3_cloud_killed_mid_run(self):
        with self.lock:
            seen_outcomes, steps_before = len(self.outcomes), self.stats[-1].steps
        self.assertEqual(self.call(self.GOALS[0]).status, PlanPathResponse.OK)
        self.processes["server"].kill()
        self.processes["server"].wait(10)
        for goal in self.GOALS:
            self.assertEqual(self.call(goal).status, PlanPathResponse.OK, "no path with the cloud down")
        self.wait_for(lambda: len(self.outcomes) >= seen_outcomes + 1 + len(self.GOALS), what="outcomes")
        with self.lock:
            after = self.outcomes[seen_outcomes + 1:]
            steps_after = self.stats[-1].steps
        self.assertTrue(all(o.delivered == OffloadOutcome.LOCAL for o in after))
        timeouts = [o for o in after if o.cloud_timeout or o.cloud_status == PlanPathResponse.CLOUD_ERROR]
        self.assertTrue(timeouts, "no cloud failure recorded")
        for o in timeouts:
            self.assertEqual(o.cloud_s, CLOUD_TIMEOUT_S)
            self.assertTrue(o.reward_valid)
        self.assertTrue(any(o.cloud_timeout for o in after), "the bridge never reported CLOUD_TIMEOUT")
        self.assertGreater(steps_after, steps_before, "learning stopped when the cloud went away")


if __name__ == "__main__":
    rostest.rosrun("offload_learner_py", "online_stack", OnlineStackTest)
