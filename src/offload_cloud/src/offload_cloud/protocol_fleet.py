"""The fleet learner's messages (kinds ROWS, MODEL_QUERY, MODEL_FETCH), coded on protocol.py's envelope, kinds,
statuses and bounds: one wire, split out of protocol.py by size only. Both ends use these functions; nothing
else builds or parses a fleet frame.

    ROWS         frame 1: JSON {"definitions": {type: .msg text as rosbag stores it}, "md5": {type: 32 hex},
                 "rows": N} for the two FLEET_TYPES; then 2N frames, each row's OffloadDecision and OffloadOutcome
                 in ROS 1 wire format (genpy's serialize(): the bytes a bag records). At most MAX_ROWS rows and
                 MAX_ROWS_BYTES in all, at most MAX_DEFINITIONS_BYTES of definitions (TOO_LARGE past them).
                 Reply: OK with JSON {"accepted": k, "refused": m}, or BUSY (keep the rows, retry later).
    MODEL_QUERY  frame 1: JSON {"current": version or "", "rolled_back": [version, ...]} (at most MAX_ROLLED_BACK).
                 Reply: OK with JSON {"version": version or "", "bytes": n}: the model this robot should run.
    MODEL_FETCH  frame 1: JSON {"version": version}. Reply: OK whose last frame (a path's, in a plan reply) is the
                 model file's bytes; or an error status (MAP_UNKNOWN: no such version).

A version is the model file's SHA-256, 64 lowercase hex characters. A MODEL_QUERY or MODEL_FETCH frame is at most
MAX_FLEET_JSON_BYTES.
"""
from typing import List, Sequence, Tuple

from offload_cloud.protocol import FLEET_TYPES, MAX_DEFINITIONS_BYTES, MAX_FLEET_JSON_BYTES, MAX_ROLLED_BACK, \
    MAX_ROWS, MAX_ROWS_BYTES, Kind, ProtocolError, Status, canonical_json, envelope, json_object


def is_version(text, empty_ok: bool = False, digits: int = 64) -> bool:
    """A model version, 64 lowercase hex characters ("" too with empty_ok); with digits=32, an md5."""
    return isinstance(text, str) and ((empty_ok and not text) or (len(text) == digits and set(text) <= _HEX))


_HEX = set("0123456789abcdef")


def encode_rows(request_id: int, definitions: dict, md5: dict, rows: Sequence[Tuple[bytes, bytes]]) -> list:
    meta = canonical_json({"definitions": definitions, "md5": md5, "rows": len(rows)})
    return [envelope(Kind.ROWS, request_id), meta] + [bytes(part) for row in rows for part in row]


def decode_rows(frames) -> Tuple[dict, dict, List[Tuple[bytes, bytes]]]:
    """(definitions, md5, [(decision, outcome)]) from the frames after a ROWS envelope; ProtocolError otherwise."""
    if len(frames) > 1 + 2 * MAX_ROWS or sum(memoryview(f).nbytes for f in frames) > MAX_ROWS_BYTES:
        raise ProtocolError(Status.TOO_LARGE, f"at most {MAX_ROWS} rows and {MAX_ROWS_BYTES} bytes a message")
    if frames and memoryview(frames[0]).nbytes > 2 * MAX_DEFINITIONS_BYTES + 1024:   # before parsing it
        raise ProtocolError(Status.TOO_LARGE, f"rows metadata over {2 * MAX_DEFINITIONS_BYTES + 1024} bytes")
    meta = json_object(bytes(frames[0]), "rows metadata") if frames else {}
    definitions, md5, count = meta.get("definitions"), meta.get("md5"), meta.get("rows")
    if not (isinstance(definitions, dict) and isinstance(md5, dict) and sorted(definitions) == sorted(md5) ==
            sorted(FLEET_TYPES) and all(isinstance(v, str) for v in definitions.values())
            and all(is_version(v, digits=32) for v in md5.values())):
        raise ProtocolError(Status.BAD_REQUEST, f"rows metadata needs definitions and md5 of {FLEET_TYPES}")
    if sum(len(v.encode()) for v in definitions.values()) > MAX_DEFINITIONS_BYTES:
        raise ProtocolError(Status.TOO_LARGE, f"definitions over {MAX_DEFINITIONS_BYTES} bytes")
    if type(count) is not int or len(frames) != 1 + 2 * count:
        raise ProtocolError(Status.BAD_REQUEST, "rows metadata's count is not the number of row frame pairs")
    return definitions, md5, [(bytes(frames[i]), bytes(frames[i + 1])) for i in range(1, len(frames), 2)]


def encode_model_query(request_id: int, current: str, rolled_back: Sequence[str] = ()) -> list:
    return [envelope(Kind.MODEL_QUERY, request_id), canonical_json({"current": current, "rolled_back": list(rolled_back)})]


def encode_model_fetch(request_id: int, version: str) -> list:
    return [envelope(Kind.MODEL_FETCH, request_id), canonical_json({"version": version})]


def decode_model_request(kind: Kind, frames) -> Tuple[str, List[str]]:
    """(version, rolled-back versions) of a MODEL_QUERY (version: the robot's current, may be "") or a
    MODEL_FETCH (the version asked for; no rolled-back list); ProtocolError when malformed."""
    if len(frames) != 1 or memoryview(frames[0]).nbytes > MAX_FLEET_JSON_BYTES:
        raise ProtocolError(Status.BAD_REQUEST, f"a model request is one JSON frame of at most {MAX_FLEET_JSON_BYTES} B")
    meta = json_object(bytes(frames[0]), "model request")
    version = meta.get("current" if kind == Kind.MODEL_QUERY else "version")
    rolled_back = meta.get("rolled_back", []) if kind == Kind.MODEL_QUERY else []
    if not (is_version(version, empty_ok=kind == Kind.MODEL_QUERY) and isinstance(rolled_back, list)
            and len(rolled_back) <= MAX_ROLLED_BACK and all(is_version(v) for v in rolled_back)):
        raise ProtocolError(Status.BAD_REQUEST, f"{kind.name} needs versions of 64 hex characters (at most "
                                                f"{MAX_ROLLED_BACK} rolled back)")
    return version, rolled_back
