"""Robot-side client of the fleet learner (`offload-cloud-learner`): stream rows, ask which model version to run,
fetch a version's file. ROS-free and learner-free (it never imports offload_learner_py or torch): the robot's
learner node wraps it in a background thread and loads the fetched bytes with
offload_learner_py.core.model_file.load_model(data, expected_version=version).

The transport is CloudClient's (offload_cloud.client): the same Lazy Pirate request/reply over a DEALER socket with
the robot's CURVE keys (keys_dir: client.key_secret and server.key, the learner's public key), a deadline per call
(`timeout_s`, split over `retries + 1` attempts), and replies matched by request id. A resent ROWS batch is answered
by the learner as the first one was and not pooled twice.

Stable API (the robot side depends on it):
    FleetClient(endpoint, *, keys_dir=None, insecure=False, timeout_s=5.0, retries=1, context=None)
    send_rows(definitions, md5, rows) -> (accepted, refused)
        definitions, md5: {"offload_msgs/OffloadDecision": text, "offload_msgs/OffloadOutcome": text} (genpy's
        `_full_text` and `_md5sum` of the message classes, what rosbag stores); rows: [(decision bytes, outcome
        bytes)], each serialized with genpy's msg.serialize(); at most protocol.MAX_ROWS rows and
        protocol.MAX_ROWS_BYTES in all (ValueError otherwise: batch them). Raises FleetBusy (keep the rows, retry
        later), CloudTimeout (learner unreachable: keep them), FleetError (refused as malformed).
    current_version(current="", rolled_back=()) -> (version, size): the version this robot should run ("" when the
        learner has none) and its file's size; never one in rolled_back.
    fetch(version) -> bytes: the model file, checked here against its SHA-256 (FleetError when it differs).
    close(), or use it as a context manager. Not thread safe: one client per thread.
"""
import hashlib
import time
from typing import Optional, Sequence, Tuple

import zmq

from offload_cloud import protocol, protocol_fleet
from offload_cloud.client import CloudClient, CloudTimeout   # noqa: F401  (CloudTimeout: part of this API)
from offload_cloud.protocol import ProtocolError, Status


class FleetError(RuntimeError):
    """The learner refused a request (its status and message), or answered with something that is not a reply."""

    def __init__(self, status: Status, message: str):
        super().__init__(f"{status.name}: {message}")
        self.status = status


class FleetBusy(FleetError):
    """BUSY: the learner is over this robot's rate or its disk budget. Keep the rows and send them later."""


class FleetClient:
    def __init__(self, endpoint: str, *, keys_dir: Optional[str] = None, insecure: bool = False,
                 timeout_s: float = 5.0, retries: int = 1, context: Optional[zmq.Context] = None):
        self._link = CloudClient(endpoint, keys_dir=keys_dir, insecure=insecure, timeout_s=timeout_s,
                                 retries=retries, context=context,
                                 max_reply_bytes=protocol.MAX_MODEL_BYTES + 4096)
        self.endpoint = endpoint

    def close(self) -> None:
        self._link.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @property
    def bytes_sent(self) -> int:
        return self._link.bytes_sent

    @property
    def bytes_received(self) -> int:
        return self._link.bytes_received

    def _json(self, build, what: str, timeout_s: Optional[float]) -> dict:
        deadline = time.monotonic() + (self._link.timeout_s if timeout_s is None else timeout_s)
        reply = self._link.request(build, deadline)
        if reply.status == Status.BUSY:
            raise FleetBusy(reply.status, reply.message)
        try:
            return protocol.decode_json_reply(reply, what)
        except ProtocolError as error:
            raise FleetError(error.status, str(error)) from None

    def send_rows(self, definitions: dict, md5: dict, rows: Sequence[Tuple[bytes, bytes]],
                  timeout_s: Optional[float] = None) -> Tuple[int, int]:
        rows = [(bytes(d), bytes(o)) for d, o in rows]
        size = sum(len(d) + len(o) for d, o in rows)
        if not rows or len(rows) > protocol.MAX_ROWS or size > protocol.MAX_ROWS_BYTES - 2 * protocol.MAX_DEFINITIONS_BYTES:
            raise ValueError(f"send 1 to {protocol.MAX_ROWS} rows of at most "
                             f"{protocol.MAX_ROWS_BYTES - 2 * protocol.MAX_DEFINITIONS_BYTES} bytes a batch")
        answer = self._json(lambda request_id: protocol_fleet.encode_rows(request_id, definitions, md5, rows),
                            "rows", timeout_s)
        return int(answer.get("accepted", 0)), int(answer.get("refused", 0))

    def current_version(self, current: str = "", rolled_back: Sequence[str] = (),
                        timeout_s: Optional[float] = None) -> Tuple[str, int]:
        answer = self._json(lambda request_id: protocol_fleet.encode_model_query(request_id, current, rolled_back),
                            "model query", timeout_s)
        version = answer.get("version", "")
        if not protocol_fleet.is_version(version, empty_ok=True) or version in rolled_back:
            raise FleetError(Status.SERVER_ERROR, f"the learner offered {version!r}")
        return version, int(answer.get("bytes", 0))

    def fetch(self, version: str, timeout_s: Optional[float] = None) -> bytes:
        deadline = time.monotonic() + (self._link.timeout_s if timeout_s is None else timeout_s)
        reply, data = self._link.request(lambda request_id: protocol_fleet.encode_model_fetch(request_id, version),
                                         deadline, decode=lambda frames: protocol.decode_reply(frames, blob=True))
        if reply.status != Status.OK:
            raise (FleetBusy if reply.status == Status.BUSY else FleetError)(reply.status, reply.message)
        if hashlib.sha256(data).hexdigest() != version:
            raise FleetError(Status.SERVER_ERROR, f"the file's SHA-256 is not the version {version[:12]} asked for")
        return data
