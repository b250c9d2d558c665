"""Paths kept serialized through the learner and the bridge (nodes/path_wire.py): byte for byte genpy's wire
format both ways, the poses genpy would read, other layouts and broken bytes handled as genpy does."""
import io
import struct

import genpy
import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from offload_msgs.srv import PlanPathResponse
from std_msgs.msg import Header

from offload_learner_py.nodes.path_wire import WirePath, WirePlanPath, WirePlanPathResponse, pose_count


def wire(msg) -> bytes:
    out = io.BytesIO()
    msg.serialize(out)
    return out.getvalue()


def genpy_path(rows, frame="map", frames=None, stamp=genpy.Time(12, 345), seq=7) -> Path:
    path = Path(header=Header(seq=seq, stamp=stamp, frame_id=frame))
    for index, row in enumerate(rows):
        pose = PoseStamped(header=Header(stamp=stamp, frame_id=frames[index] if frames else frame))
        p, q = pose.pose.position, pose.pose.orientation
        p.x, p.y, p.z, q.x, q.y, q.z, q.w = row
        path.poses.append(pose)
    return path


def response(path, status=0, message="") -> PlanPathResponse:
    return PlanPathResponse(path=path, status=status, message=message, planning_time_s=0.0123, expansions=98765,
                            cost_m=4.5, map_stamp=genpy.Time(99, 5), cpu_s=0.0007, bytes_sent=321, bytes_received=2 ** 40)


def rows(count, seed=0):
    return np.random.default_rng(seed).normal(size=(count, 7))


@pytest.mark.parametrize("count", [0, 1, 1500])
def test_a_response_passes_through_byte_for_byte_and_reads_as_genpy_does(count):
    original = response(genpy_path(rows(count)), status=0, message="")
    data = wire(original)
    got = WirePlanPathResponse().deserialize(data)
    assert wire(got) == data
    for name in ("status", "message", "planning_time_s", "expansions", "cost_m", "map_stamp", "cpu_s", "bytes_sent",
                 "bytes_received"):
        assert getattr(got, name) == getattr(original, name), name
    assert pose_count(got.path) == count
    assert got.path.header == original.path.header
    assert got.path.poses == original.path.poses       # decoded on first use, as genpy decodes them
    assert wire(got) == data                           # and written the same once decoded


def test_a_verdict_set_on_a_passed_through_response_is_what_the_caller_reads():
    data = wire(response(genpy_path(rows(40))))
    got = WirePlanPathResponse().deserialize(data)
    got.status, got.message = PlanPathResponse.STALE_MAP, "planned on the map of 1.0, the map in force: 2.0 é"
    expected = response(genpy_path(rows(40)), PlanPathResponse.STALE_MAP, got.message)
    assert wire(got) == wire(expected)
    assert PlanPathResponse().deserialize(wire(got)).message == got.message


def test_poses_in_other_frames_are_read_by_genpy():
    frames = ["map", "odom", "map"]
    original = response(genpy_path(rows(3), frames=frames))
    got = WirePlanPathResponse().deserialize(wire(original))
    assert [pose.header.frame_id for pose in got.path.poses] == frames
    assert wire(got) == wire(original)


def test_a_path_written_from_the_planners_rows_is_genpys():
    poses, stamp = rows(300, seed=3), genpy.Time(1700000000, 123456789)
    built = WirePath.from_poses("map", stamp, poses)
    assert wire(built) == wire(genpy_path(poses, stamp=stamp, seq=0))
    assert pose_count(built) == 300 and pose_count(genpy_path(rows(2))) == 2
    built.header.seq = 42                              # rospy numbers what it publishes
    assert Path().deserialize(wire(built)).header.seq == 42
    assert WirePath.from_poses("map", stamp, np.zeros((0, 7))).poses == []


@pytest.mark.parametrize("cut", [1, 5, 20, 100, 10000])
def test_truncated_or_padded_bytes_are_refused(cut):
    data = wire(response(genpy_path(rows(100))))
    with pytest.raises((ValueError, struct.error, genpy.DeserializationError)):
        WirePlanPathResponse().deserialize(data[:-cut])
    with pytest.raises((ValueError, struct.error, genpy.DeserializationError)):
        WirePlanPathResponse().deserialize(data + b"\0" * cut)


def test_a_pose_count_beyond_the_bytes_is_refused_without_allocating_it():
    data = bytearray(wire(response(genpy_path(rows(2)))))
    count_at = 12 + 4 + len("map")
    data[count_at:count_at + 4] = struct.pack("<I", 2 ** 32 - 1)
    with pytest.raises((ValueError, struct.error, genpy.DeserializationError, MemoryError)):
        WirePlanPathResponse().deserialize(bytes(data))


def test_the_service_class_is_plan_path_to_rospy():
    from offload_msgs.srv import PlanPath
    assert (WirePlanPath._type, WirePlanPath._md5sum) == (PlanPath._type, PlanPath._md5sum)
    assert WirePlanPath._response_class._type == PlanPathResponse._type
