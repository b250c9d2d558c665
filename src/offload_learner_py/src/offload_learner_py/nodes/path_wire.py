"""Paths that cross the robot's nodes without being taken apart (#30 item 7: pay almost nothing to decide).

genpy builds a Python PoseStamped, Header and two Time objects per pose to read a nav_msgs/Path and walks them
again to write one: about 2.9 ms to read and 0.8 ms to write a 1000-pose path on this machine. The learner node
only passes a planner's path on (to its caller, to its latched ~path_* topics) and the bridge only writes one, so
both spent more CPU on paths than on deciding. Here a path keeps its poses as the serialized bytes they arrived
in (WirePath), read and written with numpy in one pass, and genpy's own code decodes them the first time
anything asks for `poses`. The layout is ROS 1's (genpy's) and nothing else: a path whose poses do not all carry
the path's one frame id (never from this project's planners, possible from another) is read by genpy as before.

No rospy: the message classes are genpy's (offload_msgs, nav_msgs), testable without a master."""
import struct
from io import BytesIO

import numpy as np
from genpy import Time
from nav_msgs.msg import Path
from offload_msgs.srv import PlanPath, PlanPathRequest, PlanPathResponse
from std_msgs.msg import Header

_HEADER = struct.Struct("<3II")          # seq, stamp secs, nsecs, frame_id length
_COUNT = struct.Struct("<I")
# after the path: status, message (length, bytes), then planning_time_s .. bytes_received
_TAIL = struct.Struct("<dQdIIdQQ")
_POSES_SLOT = Path.poses                 # genpy's slot, beneath WirePath's lazy property


def _pose_dtype(frame_bytes: int) -> np.dtype:
    """One serialized PoseStamped whose frame id is `frame_bytes` long (ROS 1 packs fields, little-endian)."""
    return np.dtype({"names": ["seq", "secs", "nsecs", "frame_len", "pose"],
                     "formats": ["<u4", "<u4", "<u4", "<u4", ("<f8", 7)],
                     "offsets": [0, 4, 8, 12, 16 + frame_bytes], "itemsize": 16 + frame_bytes + 56})


def _read_header(buffer, offset: int):
    if offset + _HEADER.size > len(buffer):
        raise ValueError("truncated header")
    seq, secs, nsecs, length = _HEADER.unpack_from(buffer, offset)
    end = offset + _HEADER.size + length
    if end > len(buffer):
        raise ValueError("truncated frame id")
    frame = bytes(buffer[offset + _HEADER.size:end]).decode("utf-8")
    return Header(seq=seq, stamp=Time(secs, nsecs), frame_id=frame), end


class WirePath(Path):
    """A nav_msgs/Path whose poses are kept serialized until something reads `poses`. (No __slots__ of its own:
    genpy's equality, repr and type checks walk `self.__slots__`, which must stay Path's.)"""

    def __init__(self, *args, **kwds):
        self._poses_wire, self._count = None, 0
        super().__init__(*args, **kwds)

    @property
    def poses(self):
        if self._poses_wire is not None:
            decoded = Path()
            decoded.deserialize(_encode_header(self.header) + self._poses_wire)
            _POSES_SLOT.__set__(self, decoded.poses)
            self._poses_wire = None
        return _POSES_SLOT.__get__(self)

    @poses.setter
    def poses(self, value):
        self._poses_wire = None
        _POSES_SLOT.__set__(self, value)

    def pose_count(self) -> int:
        """Poses, without decoding them."""
        return self._count if self._poses_wire is not None else len(self.poses)

    def serialize(self, buff):
        if self._poses_wire is None:
            return super().serialize(buff)
        buff.write(_encode_header(self.header))
        buff.write(self._poses_wire)

    def deserialize(self, str):
        end = read_path(self, memoryview(str), 0)
        if end != len(str):
            raise ValueError(f"{len(str) - end} bytes after the path")
        return self

    @classmethod
    def from_poses(cls, frame_id: str, stamp: Time, poses: np.ndarray) -> "WirePath":
        """A path of (n, 7) rows (x, y, z, qx, qy, qz, qw), every pose stamped like the path (as the planners
        stamp theirs), serialized in one numpy pass."""
        poses = np.ascontiguousarray(poses, dtype="<f8").reshape(-1, 7)
        frame = frame_id.encode("utf-8")
        # Every pose's header is the same bytes (seq 0, the stamp, the frame id): one row, repeated, then the
        # poses' own bytes beside it: two copies in all, not one per field.
        header = _HEADER.pack(0, stamp.secs, stamp.nsecs, len(frame)) + frame
        wire = np.empty(_COUNT.size + len(poses) * (len(header) + 56), np.uint8)   # the count, then the rows
        wire[:_COUNT.size] = np.frombuffer(_COUNT.pack(len(poses)), np.uint8)
        raw = wire[_COUNT.size:].reshape(len(poses), len(header) + 56)
        raw[:, :len(header)] = np.frombuffer(header, np.uint8)
        raw[:, len(header):] = poses.view(np.uint8)
        # Built without genpy's keyword __init__ (which validates every keyword and goes through the poses property
        # twice): on the bridge's path of every cloud plan, where each call meets a cold cache.
        path = cls.__new__(cls)
        path.header = Header(0, stamp, frame_id)
        _POSES_SLOT.__set__(path, [])
        path._poses_wire, path._count = wire.tobytes(), len(poses)
        return path


def pose_row_prefix(stamp: Time, frame_id: str) -> bytes:
    """What precedes each pose of a path stamped `stamp` in `frame_id`: its PoseStamped's header (seq 0)."""
    frame = frame_id.encode("utf-8")
    return _HEADER.pack(0, stamp.secs, stamp.nsecs, len(frame)) + frame


def path_of_rows(prefix: bytes, rows: bytes) -> WirePath:
    """The path whose poses are `rows` (offload_planner_cpp.path_poses with `prefix` = pose_row_prefix(stamp,
    frame_id): a uint32 count, then each pose after the prefix), stamped and framed as its poses, without a copy."""
    path = WirePath.__new__(WirePath)   # as from_poses builds it
    path.header = _prefix_header(prefix)
    _POSES_SLOT.__set__(path, [])
    (path._count,) = _COUNT.unpack_from(rows)
    if len(rows) != _COUNT.size + path._count * (len(prefix) + 56):
        raise ValueError(f"{len(rows)} bytes are not {path._count} rows after a {len(prefix)}-byte prefix")
    path._poses_wire = rows
    return path


def _prefix_header(prefix: bytes) -> Header:
    """The Header of pose_row_prefix's bytes, set slot by slot: they are pose_row_prefix's own, so canonical, and
    genpy's Time and Header constructors (a numbers.Integral check per field, keyword parsing) cost the bridge's
    thread a dozen calls on a cold cache per cloud plan."""
    seq, secs, nsecs, length = _HEADER.unpack_from(prefix)
    stamp = Time.__new__(Time)
    stamp.secs, stamp.nsecs = secs, nsecs
    header = Header.__new__(Header)
    header.seq, header.stamp, header.frame_id = seq, stamp, prefix[_HEADER.size:_HEADER.size + length].decode()
    return header


def pose_count(path: Path) -> int:
    """A path's poses, a WirePath's without decoding them."""
    return path.pose_count() if isinstance(path, WirePath) else len(path.poses)


def _encode_header(header) -> bytes:
    frame = header.frame_id.encode("utf-8")
    return _HEADER.pack(header.seq, header.stamp.secs, header.stamp.nsecs, len(frame)) + frame


def read_path(path: WirePath, buffer, offset: int) -> int:
    """Fill `path` from a serialized nav_msgs/Path at `offset`; the offset after it. Poses that all carry the
    path's frame id stay serialized; any other path is decoded by genpy."""
    header, end = _read_header(buffer, offset)
    if end + _COUNT.size > len(buffer):
        raise ValueError("truncated pose count")
    (count,) = _COUNT.unpack_from(buffer, end)
    frame = header.frame_id.encode("utf-8")
    dtype = _pose_dtype(len(frame))
    poses_end = end + _COUNT.size + count * dtype.itemsize
    uniform = poses_end <= len(buffer)
    if uniform and count:
        raw = np.frombuffer(buffer, dtype=np.uint8, count=count * dtype.itemsize, offset=end + _COUNT.size)
        raw = raw.reshape(count, dtype.itemsize)
        lengths = raw[:, 12:16].copy().view("<u4").ravel()
        uniform = bool((lengths == len(frame)).all()) and \
            bool((raw[:, 16:16 + len(frame)] == np.frombuffer(frame, dtype=np.uint8)).all())
    if not uniform:    # another layout: genpy reads it (and raises on a truncated one)
        decoded = Path().deserialize(bytes(buffer[offset:]))   # genpy stops where the path ends
        path.header, path.poses = decoded.header, decoded.poses
        return offset + _genpy_end(decoded)
    path.header = header
    path._poses_wire, path._count = bytes(buffer[end:poses_end]), count
    return poses_end


def _genpy_end(path: Path) -> int:
    """The serialized length of a decoded path (where genpy stopped reading)."""
    out = BytesIO()
    path.serialize(out)
    return out.tell()


class WirePlanPathResponse(PlanPathResponse):
    """A PlanPath response read and written around a WirePath: the fields after the path are parsed, the poses
    pass through as bytes. Its path may be any nav_msgs/Path (a WirePath writes its bytes back)."""

    def serialize(self, buff):
        self.path.serialize(buff)
        message = self.message.encode("utf-8")
        buff.write(struct.pack(f"<BI{len(message)}s", self.status, len(message), message))
        buff.write(_TAIL.pack(self.planning_time_s, self.expansions, self.cost_m, self.map_stamp.secs,
                              self.map_stamp.nsecs, self.cpu_s, self.bytes_sent, self.bytes_received))

    def deserialize(self, str):
        buffer = memoryview(str)
        path = WirePath()
        end = read_path(path, buffer, 0)
        if end + 5 > len(buffer):
            raise ValueError("truncated status")
        status, length = struct.unpack_from("<BI", buffer, end)
        end += 5
        if end + length + _TAIL.size != len(buffer):
            raise ValueError("the response's length does not match its fields")
        self.path, self.status = path, status
        self.message = bytes(buffer[end:end + length]).decode("utf-8")
        (self.planning_time_s, self.expansions, self.cost_m, secs, nsecs, self.cpu_s, self.bytes_sent,
         self.bytes_received) = _TAIL.unpack_from(buffer, end + length)
        self.map_stamp = Time(secs, nsecs)
        return self


class WirePlanPath:
    """offload_msgs/PlanPath for a rospy.ServiceProxy whose responses keep their paths serialized."""
    _type, _md5sum = PlanPath._type, PlanPath._md5sum
    _request_class, _response_class = PlanPathRequest, WirePlanPathResponse
