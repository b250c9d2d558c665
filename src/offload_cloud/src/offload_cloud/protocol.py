"""Wire protocol between the robot-side client and the cloud planner, defined once for both ends.

Every message is a ZeroMQ multipart message. Frame 0 is a fixed 14-byte envelope that every version
keeps, so a server can always tell an old client which version it speaks:

    magic b"OFPL" | version u8 | kind u8 | request_id u64        (little endian)

Plan request (kind PLAN), after the envelope:
    frame 1: body, struct PLAN_BODY: map hash (16 bytes), start x, y, goal x, y (int32 cells),
             goal tolerance (float64 cells), lethal threshold (int16), flags (u8: unknown_is_obstacle,
             stop_at_goal, any_angle), then, only when a planner option differs from its default, the
             struct PLANNER_TAIL: algorithm (u8: its index in the core's ALGORITHM_NAMES, 0 dijkstra,
             1 astar, 2 jps, 3 auto), cost_factor, neutral_cost,
             robot_radius_cells, inflation_radius_cells, inflation_decay (float64 each). Added within
             version 2: a server that predates the tail answers BAD_REQUEST about the body's size, and a
             request with default options is byte for byte what it was.
    frames 2, 3.. (only when uploading the map): JSON metadata {"width", "height", "dtype": "int8"} and
             the raw C-order int8 buffer, never pickle, in frames of at most map_frames.FRAME_MAX_BYTES (1 MiB;
             map_frames.py says why). The hash is map_hash() of the metadata and the whole buffer. Added within
             version 2: a server that predates it answers BAD_REQUEST or drops a map of more than one frame,
             and a server of this release cuts a connection that sends a frame over its --max-frame-mib.
Upload only (kind UPLOAD): frames 1, 2.. are the metadata and buffer; the reply acknowledges the hash.
Ping (kind PING): the envelope alone.
Stats (kind STATS): the envelope alone; the reply is a REPLY with status OK whose message frame is the
server's counters as one flat-ish JSON object (encode_stats_reply / decode_stats). Added within version 2:
a server that predates it answers BAD_REQUEST "unknown message kind 5", which the client reports as is.

Reply (kind REPLY): envelope with the request's id, then
    frame 1: struct REPLY_BODY: status u8, reached goal x, y (int32), expansions u64,
             planning time (float64 s, inside the server's planner), cost (float64 cells)
    frame 2: message, UTF-8 (empty when OK)
    frame 3: path, raw int32 buffer of N x 2 cells (x, y), start to goal

A plan on a cached map is therefore 14 + 43 = 57 bytes of payload.

A connection's first message is at most FIRST_MESSAGE_MAX_BYTES: a client sends a ping ahead of any larger
message on the same socket, so the server knows whose connection it is (the CURVE key of its first message)
before it holds more than that of it, and bounds each key's connections together from the start. A larger
first message makes the server cut the connection (its --max-first-message-mib admits larger ones while
robots from before the rule remain). Added within version 2: every client of this package pings first; a
server that predates the rule answers the extra ping.

Fleet learner kinds ROWS, MODEL_QUERY, MODEL_FETCH (offload-cloud-learner; added within version 2, a planner
server answers BAD_REQUEST): numbered and bounded here, their frames coded in protocol_fleet.py (split out by size).
"""
import enum
import hashlib
import json
import struct
from dataclasses import dataclass, field
from typing import List, Optional, Sequence, Tuple

import numpy as np

from offload_planner_cpp._core import PlanStatus
from offload_cloud import map_frames
from offload_cloud.plan_options import (ALGORITHMS, FLAG_ANY_ANGLE, FLAG_STOP_AT_GOAL,  # noqa: F401 (protocol's names)
                                        FLAG_UNKNOWN_IS_OBSTACLE, OPTIONS_HEAD, PLANNER_TAIL, PlanOptions,
                                        algorithm_code, decode_options, encode_options)

MAGIC = b"OFPL"
# 2: planner outcomes carry the PlanPath codes (version 1 had its own numbering).
VERSION = 2
ENVELOPE = struct.Struct("<4sBBQ")
# The plan body: what changes every request (hash, start, goal), then the options (plan_options.py).
_PLAN_HEAD = struct.Struct("<16s4i")
PLAN_BODY = struct.Struct(_PLAN_HEAD.format + OPTIONS_HEAD.format[1:])
REPLY_BODY = struct.Struct("<B2iQdd")
HASH_SIZE = 16
# Largest side the planner accepts, as the ROS node's map validation.
MAX_MAP_SIDE = 100000
MAX_METADATA_BYTES = 1024
# The largest first message of a connection; a client pings ahead of a larger one (see above).
FIRST_MESSAGE_MAX_BYTES = 1 << 20
# A stats reply is small (per-client counts are bounded by the server); a client refuses a larger one.
MAX_STATS_BYTES = 1 << 20
# Fleet learner: ROWS carries at most MAX_ROWS decision/outcome pairs in ROS 1 wire format, MAX_ROWS_BYTES in all,
# with the two FLEET_TYPES' definitions (at most MAX_DEFINITIONS_BYTES); a version is a SHA-256, 64 hex.
FLEET_TYPES = ("offload_msgs/OffloadDecision", "offload_msgs/OffloadOutcome")
MAX_ROWS, MAX_ROWS_BYTES, MAX_DEFINITIONS_BYTES, MAX_ROLLED_BACK, MAX_FLEET_JSON_BYTES = 512, 4 << 20, 64 << 10, 64, 8192
MAX_MODEL_BYTES = 16 << 20   # a MODEL_FETCH answer; offload_learner_py.core.model_file.MAX_MODEL_BYTES (a test checks)


class Kind(enum.IntEnum):
    PING = 1
    PLAN = 2
    UPLOAD = 3
    REPLY = 4
    STATS = 5     # server counters, answered by the broker (as PING) without waiting behind plans
    ROWS = 6          # fleet learner: JSON {"definitions", "md5", "rows": N} + 2N rows; reply {"accepted", "refused"}
    MODEL_QUERY = 7   # fleet learner: JSON {"current", "rolled_back"}; reply JSON {"version", "bytes"}
    MODEL_FETCH = 8   # fleet learner: JSON {"version"}; reply OK with the model file as its last frame


class LinkStatus(enum.IntEnum):
    """Reply codes of the link itself, apart from the planner's."""
    MAP_UNKNOWN = 20           # the hash is not (or no longer) cached: upload the map and retry
    BAD_REQUEST = 21           # malformed message; the reply says what is wrong
    UNSUPPORTED_VERSION = 22
    TOO_LARGE = 23
    BUSY = 24                  # every worker busy and the queue full: try later or plan locally
    SERVER_ERROR = 25


# Reply status: the planner's outcomes are the core's PlanStatus codes, taken from the binding (the
# offload_msgs/PlanPath codes: a reply's planner status reaches the robot untranslated), then the link's.
Status = enum.IntEnum("Status", [(name, int(code)) for name, code in PlanStatus.__members__.items()] +
                      [(code.name, code.value) for code in LinkStatus], module=__name__)


_FIRST_LINK_STATUS = int(min(LinkStatus))   # once: min() walks the enum (a dozen calls each time)
# Codes to members by a dict lookup: calling an IntEnum on the link's hot path costs several Python calls a time.
_KIND_OF = {int(kind): kind for kind in Kind}
_STATUS_OF = {int(status): status for status in Status}


def is_planner_status(status: int) -> bool:
    """True for the planner's own outcomes (the server planned on the map), False for the link's codes."""
    return status < _FIRST_LINK_STATUS


class ProtocolError(ValueError):
    """A message that does not follow this protocol; `status` is the reply code to send back."""

    def __init__(self, status: Status, message: str):
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class PlanRequest:
    request_id: int
    map_hash: bytes
    start: Tuple[int, int]
    goal: Tuple[int, int]
    options: PlanOptions
    grid: Optional[np.ndarray] = None   # set when the map travels with the request


@dataclass(frozen=True)
class Reply:
    request_id: int
    status: Status
    message: str = ""
    path: np.ndarray = field(default_factory=lambda: np.empty((0, 2), np.int32))
    goal: Tuple[int, int] = (0, 0)
    expansions: int = 0
    planning_time_s: float = 0.0
    cost_cells: float = 0.0


def map_metadata(grid: np.ndarray) -> bytes:
    """The metadata frame of `grid`, canonical (sorted keys, no spaces) so its hash is stable."""
    return json.dumps({"dtype": "int8", "height": int(grid.shape[0]), "width": int(grid.shape[1])},
                      sort_keys=True, separators=(",", ":")).encode()


def map_hash(metadata: bytes, data) -> bytes:
    """Content hash of a map: metadata and cells both count, so a reshaped grid is a different map."""
    digest = hashlib.blake2b(digest_size=HASH_SIZE)
    digest.update(metadata)
    digest.update(data)
    return digest.digest()


def grid_hash(grid: np.ndarray) -> bytes:
    buffer = _buffer_of(grid)   # first: it explains what is wrong with a grid that is not 2-D int8
    return map_hash(map_metadata(grid), buffer)


def _buffer_of(grid: np.ndarray) -> memoryview:
    if grid.dtype != np.int8 or grid.ndim != 2 or not grid.flags.c_contiguous:
        raise ValueError("grid must be a C-contiguous 2-D int8 array indexed [y, x]")
    return memoryview(grid).cast("B") if grid.size else b""


def envelope(kind: Kind, request_id: int) -> bytes:
    return ENVELOPE.pack(MAGIC, VERSION, kind, request_id)


def encode_ping(request_id: int) -> List[bytes]:
    return [envelope(Kind.PING, request_id)]


def encode_stats(request_id: int) -> List[bytes]:
    return [envelope(Kind.STATS, request_id)]


def encode_stats_reply(request_id: int, stats: dict) -> list:
    """The reply to a STATS request: status OK, the counters as canonical JSON in the message frame."""
    text = json.dumps(stats, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return encode_reply(Reply(request_id, Status.OK, text))


def decode_stats(reply: Reply) -> dict:
    """The counters of a STATS reply; ProtocolError when it is an error reply or not a JSON object."""
    return decode_json_reply(reply, "stats", MAX_STATS_BYTES)


def decode_json_reply(reply: Reply, what: str, max_bytes: int = MAX_FLEET_JSON_BYTES) -> dict:
    """The JSON object in an OK reply's message frame; ProtocolError naming `what` otherwise."""
    if reply.status != Status.OK:
        raise ProtocolError(reply.status, f"{what} refused: {reply.status.name}: {reply.message}")
    if len(reply.message) > max_bytes:
        raise ProtocolError(Status.BAD_REQUEST, f"{what} reply of {len(reply.message)} characters is too long")
    return json_object(reply.message, f"{what} reply")


def json_object(text, what: str) -> dict:
    try:   # RecursionError: deeply nested arrays within the size cap
        value = json.loads(text)
    except (ValueError, RecursionError):
        raise ProtocolError(Status.BAD_REQUEST, f"{what} is not JSON") from None
    if not isinstance(value, dict):
        raise ProtocolError(Status.BAD_REQUEST, f"{what} is not a JSON object")
    return value


def canonical_json(value) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def encode_json_reply(request_id: int, value: dict, status: Status = Status.OK) -> list:
    return encode_reply(Reply(request_id, status, canonical_json(value).decode()))


def encode_blob_reply(request_id: int, data: bytes) -> list:
    """An OK reply whose last frame is `data` (a model file) in place of a path."""
    return encode_reply(Reply(request_id, Status.OK))[:3] + [data]


def encode_upload(request_id: int, grid: np.ndarray) -> list:
    return [envelope(Kind.UPLOAD, request_id), map_metadata(grid), *map_frames.split(_buffer_of(grid))]


_last_options = (None, b"")   # (PlanOptions, its encoding): one tuple, replaced whole, so safe across threads


def encode_plan(request_id: int, map_hash_: bytes, start: Sequence[int], goal: Sequence[int],
                options: PlanOptions = PlanOptions(), grid: Optional[np.ndarray] = None) -> list:
    """Frames of a plan request; with `grid` the map travels too (its buffer, in frames of at most 1 MiB, is sent
    without a copy)."""
    global _last_options
    last = _last_options
    if last[0] is not options:   # a robot asks with the same (frozen) options object over and over
        last = _last_options = (options, encode_options(options))
    body = _PLAN_HEAD.pack(map_hash_, int(start[0]), int(start[1]), int(goal[0]), int(goal[1]))
    frames = [envelope(Kind.PLAN, request_id), body + last[1]]
    if grid is not None:
        frames += [map_metadata(grid), *map_frames.split(_buffer_of(grid))]
    return frames


def encode_reply(reply: Reply) -> list:
    path = np.ascontiguousarray(reply.path, dtype=np.int32)
    body = REPLY_BODY.pack(int(reply.status), int(reply.goal[0]), int(reply.goal[1]), int(reply.expansions),
                           float(reply.planning_time_s), float(reply.cost_cells))
    return [envelope(Kind.REPLY, reply.request_id), body, reply.message.encode("utf-8", "replace"),
            memoryview(path).cast("B") if path.size else b""]


def decode_envelope(frame) -> Tuple[Kind, int]:
    """Kind and request id of a message's first frame; ProtocolError when it is not ours or too new."""
    frame = bytes(frame)
    if len(frame) < 5 or frame[:4] != MAGIC:
        raise ProtocolError(Status.BAD_REQUEST, "not an offload planner message (bad magic)")
    if frame[4] != VERSION:
        raise ProtocolError(Status.UNSUPPORTED_VERSION,
                            f"protocol version {frame[4]} is not supported: this server speaks version {VERSION}")
    if len(frame) != ENVELOPE.size:
        raise ProtocolError(Status.BAD_REQUEST, f"envelope is {len(frame)} bytes, expected {ENVELOPE.size}")
    _, _, code, request_id = ENVELOPE.unpack(frame)
    kind = _KIND_OF.get(code)
    if kind is None:
        raise ProtocolError(Status.BAD_REQUEST, f"unknown message kind {code}")
    return kind, request_id


def request_id_of(frame) -> int:
    """Best-effort id of a message whose envelope may be bad, so even an error reply can be matched."""
    frame = bytes(frame)
    return ENVELOPE.unpack(frame)[3] if len(frame) == ENVELOPE.size else 0


def decode_map(metadata_frame, data_frames, max_cells: int) -> Tuple[bytes, np.ndarray]:
    """Hash and grid of an uploaded map whose cells came in `data_frames` (one frame or a sequence of them): a
    view of a single frame (no copy), else the frames joined."""
    metadata = bytes(metadata_frame)
    if len(metadata) > MAX_METADATA_BYTES:
        raise ProtocolError(Status.BAD_REQUEST, "map metadata frame too long")
    try:
        # RecursionError: deeply nested arrays or objects (b"[" * 1000 fits in the size cap).
        meta = json.loads(metadata)
        if not isinstance(meta, dict):
            raise TypeError("not a JSON object")
        width, height, dtype = meta["width"], meta["height"], meta["dtype"]
    except (ValueError, TypeError, KeyError, UnicodeDecodeError, RecursionError):
        raise ProtocolError(Status.BAD_REQUEST,
                            "map metadata must be a JSON object with width, height and dtype") from None
    if dtype != "int8" or type(width) is not int or type(height) is not int:
        raise ProtocolError(Status.BAD_REQUEST, "map metadata needs integer width and height and dtype int8")
    if not (0 < width <= MAX_MAP_SIDE and 0 < height <= MAX_MAP_SIDE):
        raise ProtocolError(Status.BAD_REQUEST, f"map of {width} x {height} cells is not accepted")
    if width * height > max_cells:
        raise ProtocolError(Status.TOO_LARGE, f"map of {width} x {height} cells exceeds {max_cells} cells")
    data_frames = [data_frames] if isinstance(data_frames, (bytes, bytearray, memoryview)) else data_frames
    nbytes = map_frames.total_bytes(data_frames)
    if nbytes != width * height:
        raise ProtocolError(Status.BAD_REQUEST,
                            f"map data has {nbytes} bytes but {width} x {height} = {width * height} were declared")
    data = map_frames.join(data_frames)   # after the size checks: at most max_cells bytes
    grid = np.frombuffer(data, dtype=np.int8).reshape(height, width)
    return map_hash(metadata, data), grid


def decode_plan(request_id: int, frames, max_cells: int) -> PlanRequest:
    """A plan request from the frames after the envelope; ProtocolError when malformed or inconsistent."""
    if len(frames) == 2 or not frames:
        raise ProtocolError(Status.BAD_REQUEST, f"plan request needs 1 body frame (+ a metadata frame and the map's "
                                                f"cell frames), got {len(frames)} frames")
    body = bytes(frames[0])
    if len(body) not in (PLAN_BODY.size, PLAN_BODY.size + PLANNER_TAIL.size):
        raise ProtocolError(Status.BAD_REQUEST, f"plan body is {len(body)} bytes, expected {PLAN_BODY.size} "
                                                f"(or {PLAN_BODY.size + PLANNER_TAIL.size} with planner options)")
    digest, sx, sy, gx, gy = _PLAN_HEAD.unpack_from(body)
    try:
        options = decode_options(body[_PLAN_HEAD.size:])
    except ValueError as error:
        raise ProtocolError(Status.BAD_REQUEST, str(error)) from None
    grid = None
    if len(frames) >= 3:
        uploaded, grid = decode_map(frames[1], frames[2:], max_cells)
        if uploaded != digest:
            raise ProtocolError(Status.BAD_REQUEST, "map hash does not match the uploaded map")
    return PlanRequest(request_id, digest, (sx, sy), (gx, gy), options, grid)


def decode_reply(frames, blob: bool = False):
    """A reply from all its frames (envelope first); ProtocolError when malformed. With blob, (the reply without
    a path, its last frame's bytes): a MODEL_FETCH's answer."""
    if len(frames) != 4:
        raise ProtocolError(Status.BAD_REQUEST, f"reply needs 4 frames, got {len(frames)}")
    kind, request_id = decode_envelope(frames[0])
    body = bytes(frames[1])
    if kind != Kind.REPLY or len(body) != REPLY_BODY.size:
        raise ProtocolError(Status.BAD_REQUEST, "malformed reply")
    status, gx, gy, expansions, planning_time_s, cost = REPLY_BODY.unpack(body)
    path_bytes = memoryview(frames[2 + 1])
    if path_bytes.nbytes % 8 and not blob:
        raise ProtocolError(Status.BAD_REQUEST, "reply path is not whole (x, y) int32 pairs")
    code, status = status, _STATUS_OF.get(status)
    if status is None:
        raise ProtocolError(Status.BAD_REQUEST, f"unknown reply status {code}")
    message = bytes(frames[2]).decode("utf-8", "replace")
    if blob:
        return Reply(request_id, status, message), bytes(path_bytes)
    path = np.frombuffer(path_bytes, dtype=np.int32).reshape(-1, 2)
    return Reply(request_id, status, message, path, (gx, gy), expansions, planning_time_s, cost)
