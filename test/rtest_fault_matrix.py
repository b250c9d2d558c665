#!/usr/bin/env python3
"""rostest of the fault matrix (see fault_matrix.test and the README's "Faults" section): the whole
online system on a ROS master of the test's own, then one fault after another, each followed by
recovery: the map replaced, the cloud server crashed and restarted, a WAN outage longer than the cloud
timeout, a bandwidth collapse, the bridge restarted, the learner and the recorder SIGKILLed and
restarted, roscore restarted. After each: every request answered, no path from a map older than the
one the learner had when it answered, every decision and outcome in a bag."""
import os
import signal
import subprocess
import sys
import threading
import time

sys.path.insert(0, os.path.dirname(os.path.realpath(__file__)))
from fault_stack import GOALS, START, FaultStack, replacement_map, start_master  # noqa: E402  (names the master)
from rtest_online_stack import CLOUD_TIMEOUT_S, stop  # noqa: E402

import rosbag  # noqa: E402
import rospy  # noqa: E402
import rostest  # noqa: E402
from offload_msgs.msg import OffloadOutcome  # noqa: E402
from offload_msgs.srv import PlanPathResponse  # noqa: E402

from offload_learner_py.core.checkpoint import load_checkpoint  # noqa: E402
from offload_learner_py.core.state import input_size  # noqa: E402
from offload_learner_py.data import bags  # noqa: E402
from offload_planner_cpp.nodes.map_publisher import to_message  # noqa: E402


class FaultMatrixTest(FaultStack):
    def serve_all(self, goals=GOALS):
        """Every goal answered with a path on the map in force; the request ids the learner gave them."""
        ids = []
        for goal in goals:
            decision, response = self.call_with_decision(goal)
            self.assert_path_on(response, *self.map_in_force)
            ids.append(decision.request_id)
        self.wait_for(lambda: all(i in self.outcomes for i in ids), what="every outcome")
        return ids

    def outcomes_of(self, ids):
        with self.lock:
            return [self.outcomes[i] for i in ids]

    def cloud_back(self, timeout_s=60):
        """Requests until the cloud plans again (bounded): each of them answered meanwhile."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            ids = self.serve_all(GOALS[:1])
            outcome = self.outcomes_of(ids)[0]
            if outcome.cloud_measured and outcome.cloud_status == PlanPathResponse.OK:
                return
        self.fail("the cloud never planned again")

    def assert_cloud_failed_locally_served(self, outcomes):
        """Each request got the local path; the cloud side of it is a recorded failure costing the timeout, or
        was dropped before it started because a newer request needed the link (the breaker is off here, so
        every request reaches the failing link; test_router and make bench-policies cover the breaker)."""
        for o in outcomes:
            self.assertEqual(o.delivered, OffloadOutcome.LOCAL)
            self.assertEqual(o.local_status, PlanPathResponse.OK)
            with self.lock:
                decision = self.decisions[o.request_id]
            if not o.cloud_measured:
                self.assertTrue(decision.probe, "the cloud side of a request was skipped")
                continue
            self.assertTrue(o.reward_valid)
            if o.cloud_status != PlanPathResponse.OK:
                self.assertEqual(o.cloud_s, CLOUD_TIMEOUT_S)
                self.assertIn(o.cloud_status, (PlanPathResponse.CLOUD_TIMEOUT, PlanPathResponse.CLOUD_ERROR))

    # --- the faults, in order -------------------------------------------------------------------
    def test_0_baseline(self):
        ids = self.serve_all()
        self.assertTrue(any(o.cloud_status == PlanPathResponse.OK for o in self.outcomes_of(ids)))

    def test_1_map_replaced(self):
        """map_server publishes map_metadata before the grid; a request in between finds the learner
        knowing the new map while both planners still hold the old one. The learner must not deliver
        their old-map paths: it asks again until a planner has the new grid (published here 1 s later)."""
        old, old_stamp = self.map_in_force
        new = replacement_map(old, START, GOALS[0])
        msg = to_message(new, "map", rospy.Time.now())
        new_stamp = msg.header.stamp
        grid_published = threading.Event()

        def publish_grid_later():
            time.sleep(1.0)
            self.__class__.map_in_force = (new, new_stamp)
            self.map_pub.publish(msg)
            grid_published.set()

        self.meta_pub.publish(msg.info)
        publisher = threading.Thread(target=publish_grid_later)
        publisher.start()
        expected = input_size(START, GOALS[0], new.resolution, new.width * new.height)
        raced = False
        try:
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                before_grid = not grid_published.is_set()
                decision, response = self.call_with_decision(GOALS[0])
                if abs(decision.input_size - expected) < 1e-4 * expected:   # the message's float32 resolution
                    # the learner had the new map's metadata: only a path on the new map may come back
                    self.assert_path_on(response, new, new_stamp)
                    raced = raced or before_grid
                    break
                # it did not know yet: the old map is right, and so is the new one once a planner has its grid
                # (on a loaded machine the metadata can reach the learner after the grid reached a planner)
                if response.map_stamp == new_stamp:
                    self.assert_path_on(response, new, new_stamp)
                else:
                    self.assert_path_on(response, old, old_stamp)
            else:
                self.fail("the learner never took the new map's metadata")
        finally:
            publisher.join()
        self.assertTrue(raced, "no request met the learner knowing the new map before the planners had it")
        ids = self.serve_all()
        self.assertEqual(len(self.outcomes_of(ids)), len(GOALS))
        self.cloud_back()
        with self.lock:
            timings = [t for t in self.cloud_timings if t.map_stamp == new_stamp and t.status == PlanPathResponse.OK]
        self.assertTrue(timings, "the cloud never planned on the new map (no re-upload of the new hash)")

    def call_with_decision(self, goal):
        with self.lock:
            known = set(self.decisions)
        response = self.plan(self.request(goal))
        self.wait_for(lambda: set(self.decisions) - known, what="the decision of the request")
        with self.lock:
            return self.decisions[max(set(self.decisions) - known)], response

    def test_2_cloud_server_crash_and_restart(self):
        self.processes["server"].kill()
        self.processes["server"].wait(10)
        down = self.outcomes_of(self.serve_all())
        self.assert_cloud_failed_locally_served(down)
        self.assertFalse(any(o.cloud_measured and o.cloud_status == PlanPathResponse.OK for o in down))
        self.start_server()   # same port, empty map cache: the bridge uploads the map again
        self.cloud_back()

    def test_3_wan_outage_longer_than_the_timeout(self):
        outage_s = 4 * CLOUD_TIMEOUT_S
        # From a second ago, as outage_now sets it: an outage placed at our "now" began later on the emulator's
        # clock, and a request in between got its cloud path (fresh-ci, 5c6ae10: delivered CLOUD).
        self.outage_now(outage_s)
        began = time.monotonic()
        during = []
        while time.monotonic() - began < outage_s - 1.5 * CLOUD_TIMEOUT_S:
            during += self.serve_all(GOALS[:2])
        during = self.outcomes_of(during)
        self.assert_cloud_failed_locally_served(during)
        self.assertTrue(any(o.cloud_timeout for o in during), "no cloud timeout recorded during the outage")
        for o in during:
            self.assertLessEqual(o.delivered_s, CLOUD_TIMEOUT_S + 2.0, "the caller waited for the dead link")
        self.cloud_back()

    def test_4_bandwidth_collapse(self):
        self.link.bandwidth_bps = 2000.0     # 2 kbit/s: a path reply of a few hundred bytes outlasts the timeout
        try:
            collapsed = self.outcomes_of(self.serve_all())
        finally:
            self.link.bandwidth_bps = 0.0
        self.assert_cloud_failed_locally_served(collapsed)
        self.assertTrue(any(o.cloud_timeout for o in collapsed), "no cloud timeout at 2 kbit/s")
        self.cloud_back()

    def outage_now(self, duration_s):
        """An outage from a second ago (the emulator's clock starts a moment after ours) for duration_s."""
        self.link.outages.append((max(0.0, time.monotonic() - self.emulator_started_at - 1.0), 1.0 + duration_s))

    def test_5_bridge_restarted(self):
        # Killed with a cloud call in flight: a WAN outage holds the probe's cloud side inside the bridge
        # after the caller already has the local path.
        self.outage_now(3 * CLOUD_TIMEOUT_S)
        (in_flight,) = self.serve_all(GOALS[:1])
        self.processes["bridge"].kill()
        self.processes["bridge"].wait(10)
        self.wait_for(lambda: in_flight in self.outcomes, what="the outcome of the request in flight")
        down = self.outcomes_of([in_flight] + self.serve_all())
        self.assert_cloud_failed_locally_served(down)
        # the call in flight died with the bridge (CLOUD_ERROR) unless the bridge had timed out first
        self.assertIn(down[0].cloud_status, (PlanPathResponse.CLOUD_ERROR, PlanPathResponse.CLOUD_TIMEOUT))
        self.assertTrue(all(o.cloud_status == PlanPathResponse.CLOUD_ERROR for o in down[1:] if o.cloud_measured))
        self.start_bridge()
        self.cloud_back()

    def test_6_learner_sigkilled(self):
        self.serve_all(GOALS[:3])
        self.wait_for(lambda: os.path.exists(self.checkpoint), what="a checkpoint")
        # A request waiting inside the learner when it dies: the previous probe's cloud side is held by a
        # WAN outage, so the next request waits for it. Its caller must get an error, not wait forever.
        self.outage_now(3 * CLOUD_TIMEOUT_S)
        self.call_with_decision(GOALS[0])   # its path is back; its cloud side waits out the bridge's timeout
        waiting = {}

        def call():
            try:
                waiting["response"] = self.plan(self.request(GOALS[1]))
            except Exception as error:   # the connection dies with the learner
                waiting["error"] = error

        caller = threading.Thread(target=call)
        caller.start()
        time.sleep(0.2)   # let it reach the learner (if it has not, it fails on the dead learner alike)
        os.kill(self.processes["learner"].pid, signal.SIGKILL)
        self.processes["learner"].wait(10)
        caller.join(30)
        self.assertFalse(caller.is_alive(), "a caller still waits on the dead learner")
        self.assertTrue("error" in waiting or waiting["response"].status == PlanPathResponse.OK, waiting)
        print(f"request waiting in the SIGKILLed learner: {waiting}", file=sys.stderr)
        self.plan.close()
        with self.lock:
            self.__class__.before_learner_kill = set(self.outcomes)

        agent = load_checkpoint(self.checkpoint)   # intact: the CRC-checked load raises on a torn file
        self.assertGreater(agent.steps, 0)
        self.start_learner()
        decision, response = self.call_with_decision(GOALS[0])
        self.assert_path_on(response, *self.map_in_force)
        self.assertEqual(decision.model_steps, agent.steps, "the learner did not resume from its checkpoint")
        self.assertEqual(len(self.serve_all()), len(GOALS))

    def test_7_learner_and_recorder_sigkilled(self):
        """The whole robot side dies: the recorder's .bag.active is read as it is (no index), with every
        outcome up to the records the recorder still held in memory."""
        self.serve_all(GOALS[:2])
        with self.lock:
            recorded = set(self.outcomes)
        for name in ("learner", "record"):
            os.kill(self.processes[name].pid, signal.SIGKILL)
            self.processes[name].wait(10)
        self.plan.close()
        load_checkpoint(self.checkpoint)
        crashed_bag = self.bag_paths[-1]
        self.assertFalse(os.path.exists(crashed_bag))
        active = crashed_bag + ".active"
        data = bags.read_bags([active])
        self.assertTrue(data.report.bags[0].ok, data.report.format())
        self.assertFalse(data.report.bags[0].indexed)
        in_bag = {int(i) for i in data.log["request_id"]}   # requests with both decision and outcome
        # Everything from before the learner's SIGKILL and restart is there: the recorder outlived it.
        self.assertEqual(self.before_learner_kill - in_bag, set(), "outcomes lost across the learner's SIGKILL")
        # What a SIGKILLed recorder loses is its unwritten tail only (its stdio buffer): never a hole.
        lost = recorded - in_bag
        self.assertTrue(all(i > max(in_bag) for i in lost), f"a hole in the recovered bag: {sorted(lost)}")
        # ROS's own recovery: rosbag reindex keeps the complete chunks only (here none may be complete),
        # so it never finds more than the reader.
        out_dir = os.path.join(self.tmp.name, "reindexed")
        os.makedirs(out_dir)
        subprocess.run(["rosbag", "reindex", "--output-dir", out_dir, active], check=True,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=120)
        with rosbag.Bag(os.path.join(out_dir, os.path.basename(active))) as reindexed:
            ids = {m.request_id for _, m, _ in reindexed.read_messages(topics=["/offload_learner/outcome"])}
        self.assertLessEqual(ids, in_bag | lost)
        self.assertLessEqual(len(ids), len(in_bag))
        print(f"recorder SIGKILLed: {len(in_bag)} of {len(recorded)} outcomes read from its .bag.active, "
              f"{len(lost)} lost from its unwritten tail; rosbag reindex keeps {len(ids)}", file=sys.stderr)

        # Restarted with a recorder slow to come up (stopped until the first decision or for 5 s) while
        # other subscribers (this test's) connect at once: the learner must wait for the recorder.
        self.__class__.last_session_after = max(recorded)
        self.start_recorder()
        recorder = self.processes["record"]
        os.kill(recorder.pid, signal.SIGSTOP)

        def resume_recorder():
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline and not any(i > self.last_session_after for i in list(self.decisions)):
                time.sleep(0.02)
            os.kill(recorder.pid, signal.SIGCONT)

        resumer = threading.Thread(target=resume_recorder)
        resumer.start()
        try:
            self.start_learner()
        finally:
            resumer.join()
        self.assertEqual(len(self.serve_all()), len(GOALS))   # test_9 finds all of them in the bag

    def test_8_roscore_restarted(self):
        self.serve_all(GOALS[:1])
        master = self.processes.pop("master")
        master.kill()
        master.wait(10)
        self.processes["master"] = start_master()
        # Connections made before the restart are peer to peer and survive it: the caller's persistent
        # connection to the learner, the learner's to both planners, every topic connection (the
        # recorder's, this test's subscribers).
        after = self.outcomes_of(self.serve_all())
        self.assertTrue(all(o.local_status == PlanPathResponse.OK for o in after))
        self.assertTrue(any(o.cloud_status == PlanPathResponse.OK for o in after))
        # A new connection needs the master, and ROS 1 nodes do not register again with a new one.
        with self.assertRaises(rospy.ROSException):
            rospy.wait_for_service("/offload_learner/plan", timeout=2.0)

    def test_9_nothing_recorded_lost(self):
        stop(self.processes.pop("record"))   # SIGINT: the recorder closes the bag
        data = bags.read_bags(self.bag_paths[-1:])
        self.assertTrue(data.report.bags[0].ok and data.report.bags[0].indexed, data.report.format())
        in_bag = {int(i) for i in data.log["request_id"]}
        with self.lock:
            since_restart = {i for i in self.outcomes if i > self.last_session_after}
        self.assertGreaterEqual(len(since_restart), 2 * len(GOALS))
        self.assertEqual(since_restart - in_bag, set(), "outcomes missing from the bag")


if __name__ == "__main__":
    rostest.rosrun("offload_learner_py", "fault_matrix", FaultMatrixTest)
