#!/usr/bin/env python3
"""rostest (bag_recorder.test): offload_record, which becomes offload_bag_recorder, records what `rosbag record`
records: every message of its topics in order, a latched message published before it started with its latching
kept, a large path whole, and a bag closed under its own name on SIGINT and on SIGTERM. And it does so with one
callback thread that wakes about once a second when nothing arrives (rosbag record's ten threads waking ten times a
second each cost the robot 5-7 ms of CPU a second, 1.4 ms a request at the bench's 4 Hz). Below its minimum free
space it records nothing and says so."""
import os
import signal
import subprocess
import sys
import time
import unittest

import rosbag
import rospy
import rostest
from nav_msgs.msg import Path
from geometry_msgs.msg import PoseStamped
from std_msgs.msg import String, UInt64

from offload_demos.loopback import stop_process as stop
from offload_learner_py.nodes.record import recorder_path

LATCHED, COUNTED, PATHS = "/rtest_recorder/latched", "/rtest_recorder/counted", "/rtest_recorder/path"


def start_recorder(bag: str, *options: str, name: str = "offload_record") -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "offload_learner_py.nodes.record", "--bag", bag, *options, "--",
                             LATCHED, COUNTED, PATHS, f"__name:={name}"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_subscribed(publisher, node: str, timeout_s: float = 20.0) -> None:
    """Until `node` is connected to `publisher` (an earlier test's recorder may still count among its connections)."""
    deadline = time.monotonic() + timeout_s
    while not any(connection.endpoint_id == "/" + node for connection in publisher.impl.connections):
        if time.monotonic() > deadline:
            raise AssertionError(f"{node} did not subscribe to {publisher.resolved_name} in {timeout_s} s")
        time.sleep(0.05)


def big_path(poses: int) -> Path:
    path = Path()
    path.header.frame_id = "map"
    for i in range(poses):
        pose = PoseStamped()
        pose.header.frame_id = "map"
        pose.pose.position.x, pose.pose.orientation.w = 0.05 * i, 1.0
        path.poses.append(pose)
    return path


def thread_stats(pid: int):
    """(threads, the main thread's voluntary context switches): how often the thread that runs callbacks wakes."""
    tasks = os.listdir(f"/proc/{pid}/task")
    with open(f"/proc/{pid}/task/{pid}/status") as status:
        switches = next(int(line.split()[1]) for line in status if line.startswith("voluntary_ctxt_switches"))
    return len(tasks), switches


def recorder_pid(wrapper: subprocess.Popen) -> int:
    """offload_record execs the recorder: the same process, once its command line is the recorder's."""
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        with open(f"/proc/{wrapper.pid}/cmdline", "rb") as cmdline:
            if b"offload_bag_recorder" in cmdline.read():
                return wrapper.pid
        time.sleep(0.05)
    raise AssertionError("offload_record did not become offload_bag_recorder")


class BagRecorderTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_bag_recorder")
        cls.latched = rospy.Publisher(LATCHED, String, queue_size=1, latch=True)
        cls.counted = rospy.Publisher(COUNTED, UInt64, queue_size=1000)
        cls.paths = rospy.Publisher(PATHS, Path, queue_size=10)
        cls.latched.publish(String(data="published before the recorder started"))
        cls.dir = os.environ.get("ROS_HOME", "/tmp")

    def bag_name(self, name: str) -> str:
        path = os.path.join(self.dir, f"rtest_recorder_{os.getpid()}_{name}.bag")
        self.addCleanup(lambda: [os.remove(p) for p in (path, path + ".active") if os.path.exists(p)])
        return path

    def record_and_stop(self, bag: str, stop_signal: int, name: str, messages: int = 200):
        recorder = start_recorder(bag, name=name)
        self.addCleanup(stop, recorder)
        pid = recorder_pid(recorder)
        wait_subscribed(self.counted, name)
        wait_subscribed(self.paths, name)
        for i in range(messages):
            self.counted.publish(UInt64(data=i))
            time.sleep(0.002)
        self.paths.publish(big_path(20000))
        time.sleep(1.0)
        self.assertTrue(os.path.exists(bag + ".active"), "recording goes into BAG.active")
        os.kill(pid, stop_signal)
        self.assertEqual(recorder.wait(timeout=20), 0, recorder.stderr.read())
        return recorder

    def read(self, bag: str):
        with rosbag.Bag(bag) as recorded:
            return [(topic, message, header) for topic, message, _, header in
                    recorded.read_messages(return_connection_header=True)]

    def test_every_message_recorded_and_the_bag_closed_on_sigint(self):
        bag = self.bag_name("sigint")
        self.record_and_stop(bag, signal.SIGINT, "recorder_sigint")
        self.assertFalse(os.path.exists(bag + ".active"))
        records = self.read(bag)
        counted = [message.data for topic, message, _ in records if topic == COUNTED]
        self.assertEqual(counted, list(range(200)), "every message, in order")
        latched = [(message.data, header) for topic, message, header in records if topic == LATCHED]
        self.assertEqual(len(latched), 1)
        self.assertEqual(latched[0][0], "published before the recorder started")
        self.assertIn(latched[0][1].get("latching"), ("1", b"1"), "a latched topic plays back latched")
        paths = [message for topic, message, _ in records if topic == PATHS]
        self.assertEqual(len(paths), 1)
        self.assertEqual(len(paths[0].poses), 20000)
        self.assertAlmostEqual(paths[0].poses[-1].pose.position.x, 0.05 * 19999)

    def test_sigterm_closes_the_bag_too(self):
        bag = self.bag_name("sigterm")
        self.record_and_stop(bag, signal.SIGTERM, "recorder_sigterm", messages=20)
        self.assertFalse(os.path.exists(bag + ".active"))
        self.assertEqual(len([1 for topic, _, _ in self.read(bag) if topic == COUNTED]), 20)

    def test_one_thread_runs_the_callbacks_and_it_sleeps(self):
        """rosbag record: 16 threads, ten of them spinners waking 10 times a second. roscpp itself keeps four
        (the main thread, its internal queue, the poll manager, XML-RPC) and rosout's."""
        bag = self.bag_name("threads")
        recorder = start_recorder(bag, name="recorder_idle")
        self.addCleanup(stop, recorder)
        pid = recorder_pid(recorder)
        wait_subscribed(self.counted, "recorder_idle")
        time.sleep(1.0)
        threads, before = thread_stats(pid)
        time.sleep(5.0)
        _, after = thread_stats(pid)
        self.assertLessEqual(threads, 6, "no spinner pool")
        # ros::spin() wakes the main thread about 50 times in 5 s; the recorder's loop about 5 times.
        self.assertLess(after - before, 25, "the callback thread wakes about once a second when idle")

    def test_below_its_free_space_it_records_nothing_and_says_so(self):
        """A disk that fills while it runs: the recorder itself, with a floor above the disk's free space (offload_record
        refuses to start one below it)."""
        bag = self.bag_name("floor")
        recorder = subprocess.Popen([recorder_path(), "--min-free-mib", str(1 << 40), bag, COUNTED,
                                     "__name:=offload_record_floor"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                    text=True)
        self.addCleanup(stop, recorder)
        wait_subscribed(self.counted, "offload_record_floor")
        for i in range(10):
            self.counted.publish(UInt64(data=i))
        time.sleep(0.5)
        recorder.send_signal(signal.SIGINT)
        self.assertEqual(recorder.wait(timeout=20), 0)
        self.assertIn("recording stopped", recorder.stderr.read())
        self.assertEqual(len(self.read(bag)), 0, "nothing written below the floor")
        self.assertFalse(os.path.exists(bag + ".active"))


    def test_a_garbage_floor_is_refused_with_one_line(self):
        """The recorder alone (offload_record passes a checked number): a floor that is not a whole number of MiB is
        refused, never read as 0 (record everything until the disk is full)."""
        for floor in ("abc", "12x", "-1", ""):
            done = subprocess.run([recorder_path(), "--min-free-mib", floor, self.bag_name("garbage"), COUNTED],
                                  capture_output=True, text=True, timeout=20)
            self.assertEqual(done.returncode, 2, floor)
            self.assertIn("--min-free-mib wants a whole number", done.stderr)


if __name__ == "__main__":
    rostest.rosrun("offload_learner_py", "bag_recorder_rtest", BagRecorderTest, sys.argv)
