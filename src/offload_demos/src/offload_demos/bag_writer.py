"""Writes small ROS 1 bags of OffloadDecision / OffloadOutcome messages with the `rosbags` writer, for
tests and the offline benchmark, from any message definitions (the installed .msg files or an older
version of them). Like `rosbag record`, it puts each connection record inside the chunks that use
it, so a bag cut off before its index still names its message types."""
import math
import os
import struct
from typing import Dict, Iterable, Optional, Tuple

from offload_learner_py import CLOUD, LOCAL

DECISION_TYPE = "offload_msgs/msg/OffloadDecision"
OUTCOME_TYPE = "offload_msgs/msg/OffloadOutcome"
DECISION_TOPIC = "/offload_learner/decision"
OUTCOME_TOPIC = "/offload_learner/outcome"
CONFIG_TYPE = "offload_msgs/msg/LearnerConfig"
CONFIG_TOPIC = "/offload_learner/config"


def installed_definitions(msg_dir: Optional[str] = None) -> Tuple[str, str]:
    """(OffloadDecision.msg, OffloadOutcome.msg) text from the source tree's offload_msgs."""
    if msg_dir is None:
        here = os.path.dirname(os.path.abspath(__file__))
        msg_dir = os.path.join(here, "..", "..", "..", "offload_msgs", "msg")
    with open(os.path.join(msg_dir, "OffloadDecision.msg")) as decision, \
            open(os.path.join(msg_dir, "OffloadOutcome.msg")) as outcome:
        return decision.read(), outcome.read()


def config_definition(msg_dir: Optional[str] = None) -> str:
    """LearnerConfig.msg text from the source tree's offload_msgs."""
    if msg_dir is None:
        msg_dir = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "..", "offload_msgs", "msg")
    with open(os.path.join(msg_dir, "LearnerConfig.msg")) as config:
        return config.read()


def typestore_for(decision_msg: str, outcome_msg: str, extra: Dict[str, str] = None):
    """A ROS 1 type store holding std_msgs and the given definitions (type name -> .msg text)."""
    from rosbags.typesys import Stores, get_typestore, get_types_from_msg

    store = get_typestore(Stores.ROS1_NOETIC)
    types = {}
    for name, text in ((DECISION_TYPE, decision_msg), (OUTCOME_TYPE, outcome_msg), *(extra or {}).items()):
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store


def probe_request(request_id: int, input_size: float, cpu_availability: float, round_trip_s: float,
                  local_s: float, cloud_s: float, action: int, propensity: float, reward_value: float,
                  probe: bool = True, loss: float = math.nan, local_plan_rate: float = 0.0) -> Tuple[dict, dict]:
    """(decision fields, outcome fields) of one request; with probe false only the taken side is measured. The
    local planning rate p_t defaults to 0, "not measured" (the state schema's value for older records)."""
    decision = dict(request_id=request_id, input_size=input_size, cpu_availability=cpu_availability,
                    round_trip_s=round_trip_s, local_plan_rate=local_plan_rate, action=action, action_propensity=propensity, q_local=math.nan,
                    q_cloud=math.nan, policy="dqn", model_steps=request_id, probe=probe, routed=action)
    local_measured, cloud_measured = probe or action == LOCAL, probe or action == CLOUD
    outcome = dict(request_id=request_id, action=action, delivered=action, local_measured=local_measured,
                   local_s=local_s if local_measured else 0.0, local_status=0, cloud_measured=cloud_measured,
                   cloud_s=cloud_s if cloud_measured else 0.0, cloud_status=0, cloud_timeout=False,
                   reward_valid=probe, reward=reward_value if probe else math.nan, loss_valid=not math.isnan(loss),
                   loss=loss, delivered_s=min(local_s, cloud_s) if probe else (cloud_s if action == CLOUD else local_s))
    return decision, outcome


class BagWriter:
    """`with BagWriter(path, store) as bag: bag.write(topic, msgtype, fields, time_ns)`. Fields missing
    from the definition are dropped, fields the definition has and `fields` lacks get zero values."""

    def __init__(self, path: str, store, compression: str = "none", chunk_bytes: int = 1 << 20):
        from rosbags.rosbag1 import Writer

        self.store = store
        self.writer = Writer(path)
        if compression != "none":
            self.writer.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
        self.writer.chunk_threshold = chunk_bytes
        self.connections = {}
        self._chunk_seen = (None, set())

    def __enter__(self):
        self.writer.open()
        return self

    def __exit__(self, *exc):
        self.writer.close()

    def _connection(self, topic: str, msgtype: str):
        key = (topic, msgtype)
        if key not in self.connections:
            self.connections[key] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        return self.connections[key]

    def build(self, msgtype: str, fields: dict, stamp_ns: int):
        return self._build(msgtype, fields, stamp_ns)

    def _build(self, msgtype: str, fields: dict, stamp_ns: int):
        cls = self.store.types[msgtype]
        values = {}
        for name, (kind, spec) in self.store.fielddefs[msgtype][1]:
            if name == "header":
                values[name] = self._header(stamp_ns)
            elif name in fields:
                values[name] = fields[name]
            elif kind.name == "BASE" and spec[0] == "string":
                values[name] = ""
            elif kind.name == "BASE":
                values[name] = False if spec[0] == "bool" else 0
            else:
                raise ValueError(f"test writer cannot default the field {name} of {msgtype}")
        return cls(**values)

    def _header(self, stamp_ns: int):
        header = self.store.types["std_msgs/msg/Header"]
        time = self.store.types["builtin_interfaces/msg/Time"]
        return header(seq=0, stamp=time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000),
                      frame_id="")

    def write(self, topic: str, msgtype: str, fields: dict, time_ns: int) -> None:
        self.write_raw(topic, msgtype, self.store.serialize_ros1(self._build(msgtype, fields, time_ns), msgtype),
                       time_ns)

    def write_raw(self, topic: str, msgtype: str, data: bytes, time_ns: int) -> None:
        connection = self._connection(topic, msgtype)
        chunk = self.writer.chunks[-1]
        chunk_id, seen = self._chunk_seen
        if chunk_id is not chunk:
            self._chunk_seen = (chunk, set())
            chunk_id, seen = self._chunk_seen
        if connection.id not in seen:   # as rosbag record does: the chunk names its connections
            seen.add(connection.id)
            self.writer.write_connection(connection, chunk.data)
        self.writer.write(connection, time_ns, data)


def write_requests(path: str, requests: Iterable[Tuple[dict, dict]], store=None, compression: str = "none",
                   chunk_bytes: int = 1 << 20, start_ns: int = 1_700_000_000 * 1_000_000_000,
                   step_ns: int = 100_000_000, extra=None) -> str:
    """A bag of decision/outcome pairs, one pair every step_ns; `extra(bag, index, time_ns)` may add
    other topics."""
    store = store or typestore_for(*installed_definitions())
    with BagWriter(path, store, compression, chunk_bytes) as bag:
        for index, (decision, outcome) in enumerate(requests):
            time_ns = start_ns + index * step_ns
            if decision is not None:
                bag.write(DECISION_TOPIC, DECISION_TYPE, decision, time_ns)
            if extra is not None:
                extra(bag, index, time_ns + 1000)
            if outcome is not None:
                bag.write(OUTCOME_TOPIC, OUTCOME_TYPE, outcome, time_ns + step_ns // 2)
    return path


def unindex(path: str, keep_bytes: Optional[int] = None) -> None:
    """Make a bag look like the `.bag.active` of a crashed recorder: index position 0 in the bag
    header and, with keep_bytes, the file cut after that many bytes."""
    with open(path, "r+b") as bag:
        bag.seek(13)
        (header_size,) = struct.unpack("<I", bag.read(4))
        header = bag.read(header_size)
        at = header.find(b"index_pos=")
        if at < 0:
            raise ValueError(f"{path} has no index_pos in its bag header")
        bag.seek(13 + 4 + at + len(b"index_pos="))
        bag.write(b"\0" * 8)
        if keep_bytes is not None:
            bag.truncate(keep_bytes)
