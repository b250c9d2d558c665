"""A ROWS batch judged by the learner's own bag reader before it joins the pool, and the pool's bag files.

The robot's decision and outcome bytes are written into a scratch bag with the robot's definitions and read back
through offload_learner_py.data.bags, which is hardened against hostile bags: definitions that do not decode (or
are over its caps), rows that do not pair, values outside the physical bounds (NaN or out-of-range states,
propensities outside (0, 1], latencies) are refused exactly as a bag read would refuse them. Only the rows it keeps
are written to the pool, as the robot's bytes."""
import os
import tempfile
import time
from collections import Counter
from typing import Dict, List, Sequence, Tuple

from offload_learner_py.data.bag_decoding import Decoder
from offload_learner_py.data.bag_format import Connection
from offload_learner_py.data.bags import BagReadError, read_bag
from offload_learner_py.data.records import DECISION_DEFAULTS

# The topics the learner node publishes, as `rosbag record` stores them.
DECISION_TOPIC = "/offload_learner/decision"
OUTCOME_TOPIC = "/offload_learner/outcome"
DECISION_TYPE = "offload_msgs/msg/OffloadDecision"   # rosbags' names of the wire's FLEET_TYPES
OUTCOME_TYPE = "offload_msgs/msg/OffloadOutcome"
WIRE_TYPES = {"offload_msgs/OffloadDecision": DECISION_TYPE, "offload_msgs/OffloadOutcome": OUTCOME_TYPE}
# The pairing counts of a read that are refusals, by the name they are counted under per key.
REFUSALS = ("invalid", "undecodable", "dropped_no_outcome", "orphan_outcomes", "duplicate_decisions",
            "duplicate_outcomes", "damaged_chunks")


def typed(definitions: Dict[str, str], md5: Dict[str, str]) -> Dict[str, Tuple[str, str]]:
    """rosbags type name -> (definition, md5) of a ROWS message's metadata."""
    return {WIRE_TYPES[name]: (definitions[name], md5[name]) for name in WIRE_TYPES}


class PoolBag:
    """One bag of the pool being written: the robot's bytes as they came, each batch a chunk flushed and fsynced,
    so a learner killed between batches loses nothing it acknowledged (the file reads as an unindexed bag, a
    recorder's `.bag.active`, until it is closed with its index)."""

    def __init__(self, path: str, types: Dict[str, Tuple[str, str]]):
        from rosbags.rosbag1 import Writer

        self.path = path
        self.types = types
        self.writer = Writer(path)
        self.writer.chunk_threshold = 1 << 62   # a chunk per batch, written by flush()
        self.writer.open()
        self.connections = {msgtype: self.writer.add_connection(topic, msgtype, msgdef=types[msgtype][0],
                                                                md5sum=types[msgtype][1])
                            for topic, msgtype in ((DECISION_TOPIC, DECISION_TYPE), (OUTCOME_TOPIC, OUTCOME_TYPE))}
        self.last_ns = 0
        self.rows = 0

    def write(self, rows: Sequence[Tuple[bytes, bytes]]) -> None:
        stamp = max(time.time_ns(), self.last_ns + 1)
        for decision, outcome in rows:
            self.writer.write(self.connections[DECISION_TYPE], stamp, decision)
            self.writer.write(self.connections[OUTCOME_TYPE], stamp + 1, outcome)
            stamp += 2
        self.last_ns = stamp
        self.rows += len(rows)
        self.writer.write_chunk(self.writer.chunks[-1])
        self.writer.bio.flush()
        os.fsync(self.writer.bio.fileno())

    def size(self) -> int:
        return self.writer.bio.tell()

    def close(self) -> None:
        self.writer.close()


def check_rows(types: Dict[str, Tuple[str, str]], rows: Sequence[Tuple[bytes, bytes]], scratch_dir: str
               ) -> Tuple[List[int], Counter]:
    """(indices of the rows the bag reader keeps, refusals counted by reason). A definition the reader refuses
    refuses the whole batch ("definitions")."""
    refused: Counter = Counter()
    handle, path = tempfile.mkstemp(suffix=".bag", dir=scratch_dir)
    os.close(handle)
    os.unlink(path)   # rosbags' Writer creates the file itself and refuses to overwrite one
    try:
        bag = PoolBag(path, types)
        bag.write(rows)
        bag.close()
        try:
            columns, report = read_bag(path)
        except BagReadError:
            refused["definitions"] += len(rows)
            return [], refused
    finally:
        if os.path.exists(path):
            os.unlink(path)
    kept_ids = set(int(i) for i in columns["request_id"])
    decision = Decoder(Connection(0, DECISION_TOPIC, DECISION_TYPE, *types[DECISION_TYPE]), DECISION_DEFAULTS)
    accepted, seen = [], set()
    for index, (raw, _) in enumerate(rows):
        try:
            request_id = int(decision(raw)[0]["request_id"])
        except Exception:   # the reader counted it as undecodable
            continue
        if request_id in kept_ids and request_id not in seen:
            seen.add(request_id)
            accepted.append(index)
    for name in REFUSALS:
        if getattr(report, name, 0):
            refused[name] += getattr(report, name)
    unexplained = len(rows) - len(accepted) - sum(refused.values())
    if unexplained > 0:
        refused["other"] += unexplained
    return accepted, refused
