#!/usr/bin/env python3
"""rostest of the goal generator's schedule (see goal_generator.test): with ~rate_hz and ~epoch, request k
is sent no earlier than epoch + k / rate_hz however fast the answers come, so every run's request k meets
the same moment of the run's other schedules (the RTT trace, the workload). Lower bounds only: a loaded
machine can only make a request later."""
import subprocess
import sys
import threading
import time
import unittest

import rospy
import rostest
from offload_msgs.srv import PlanPath, PlanPathResponse


class GoalGeneratorScheduleTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        rospy.init_node("rtest_goal_generator")
        cls.lock = threading.Lock()
        cls.calls = []   # time.monotonic() of each request's arrival
        cls.slow = set()

        def answer(request):
            with cls.lock:
                cls.calls.append(time.monotonic())
                slow = len(cls.calls) in cls.slow
            if slow:
                time.sleep(0.5)   # longer than two periods: the next requests are late, the schedule is kept
            return PlanPathResponse(status=PlanPathResponse.OK)
        cls.service = rospy.Service("/fake_plan", PlanPath, answer)

    def run_generator(self, *params: str) -> None:
        generator = subprocess.Popen(
            [sys.executable, "-m", "offload_demos.goal_generator", "__name:=goal_generator",
             "_service:=/fake_plan", "_period_s:=0.02", "_seed:=3", *params],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.assertEqual(generator.wait(90), 0)

    def test_open_loop_requests_keep_their_schedule_from_the_epoch(self):
        rate_hz, count = 5.0, 8
        with self.lock:
            self.calls.clear()
            self.slow.clear()
            self.slow.add(3)
        epoch = time.monotonic() + 4.0   # after the node is up: it waits for the epoch
        self.run_generator(f"_count:={count}", f"_rate_hz:={rate_hz}", f"_epoch:={epoch:.3f}")
        with self.lock:
            calls = list(self.calls)
        self.assertEqual(len(calls), count)
        for k, called in enumerate(calls):
            # 5 ms of slack for the float formatting of the epoch
            self.assertGreaterEqual(called, epoch + k / rate_hz - 0.005, f"request {k} came early")
        # Paced by the answers (0.02 s after each), the last request would come about 0.7 s after the first;
        # on the schedule it is 1.4 s after the epoch.
        self.assertGreaterEqual(calls[-1] - epoch, (count - 1) / rate_hz - 0.005)

    def test_closed_loop_waits_for_the_epoch_only(self):
        with self.lock:
            self.calls.clear()
            self.slow.clear()
        epoch = time.monotonic() + 4.0
        self.run_generator("_count:=4", f"_epoch:={epoch:.3f}")
        with self.lock:
            calls = list(self.calls)
        self.assertEqual(len(calls), 4)
        self.assertGreaterEqual(calls[0], epoch - 0.005, "the first request came before the epoch")


if __name__ == "__main__":
    rostest.rosrun("offload_demos", "rtest_goal_generator", GoalGeneratorScheduleTest)
