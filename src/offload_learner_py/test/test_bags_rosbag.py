"""The reader against bags from ROS's own writer (Debian's rosbag and the generated offload_msgs
classes; skipped where ROS is not installed): a closed bag, and a copy taken while the writer still
had it open, which is what a crashed `rosbag record` leaves as .bag.active."""
import os
import shutil

import pytest

from bagtools import make_requests
from offload_learner_py.data import bags

rosbag = pytest.importorskip("rosbag")
offload_msgs = pytest.importorskip("offload_msgs.msg")
rospy = pytest.importorskip("rospy")


def _messages(n):
    for decision, outcome in make_requests(n, seed=11, probe_every=2):
        yield offload_msgs.OffloadDecision(**decision), offload_msgs.OffloadOutcome(**outcome)


@pytest.mark.parametrize("compression", ["none", "lz4"])
def test_rosbag_written_bags_closed_and_still_open(tmp_path, compression):
    path = str(tmp_path / "run.bag")
    active = str(tmp_path / "crashed.bag.active")
    bag = rosbag.Bag(path, "w", compression=compression, chunk_threshold=2048)
    for index, (decision, outcome) in enumerate(_messages(200)):
        stamp = rospy.Time(1_700_000_000 + index)
        decision.header.stamp = outcome.header.stamp = stamp
        bag.write("/offload_learner/decision", decision, stamp)
        bag.write("/offload_learner/outcome", outcome, stamp + rospy.Duration(0, 1000))
        bag.write("/rosout_like", offload_msgs.LinkLatency(round_trip_s=0.03), stamp)
        if index == 150:
            bag._file.flush()
            shutil.copy(path, active)   # what the disk holds if the recorder dies now
    bag.close()

    closed = bags.read_bags([path]).report.bags[0]
    assert closed.ok and closed.indexed and closed.requests == 200 and closed.rewarded_steps == 100
    assert closed.ignored_topics == {"/rosout_like": 200}

    columns, crashed = bags.read_bag(active)
    assert not crashed.indexed and "rosbag reindex" in crashed.recovered_note
    assert 100 <= crashed.requests <= 151
    assert list(columns["request_id"]) == list(range(1000, 1000 + crashed.requests))
    assert os.path.getsize(active) < os.path.getsize(path)
