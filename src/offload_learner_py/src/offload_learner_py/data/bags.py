"""ROS 1 bags to the learner's records and the one transition table, without ROS.

Reads OffloadDecision and OffloadOutcome messages with the `rosbags` library, decoding each bag with
the message definitions stored in that bag (so a bag written with an older version of the messages
still reads), and pairs them by request id into a `records.RequestLog`; `records.transition_table`
turns that into TransitionTable rows. What real bags hold is tolerated and counted: other topics
(ignored, never decoded), decisions without an outcome (dropped), outcomes without a decision,
duplicate request ids, invalid values, and steps with one latency only (kept in the log for
off-policy evaluation, not in the table, since eq. 10 needs both). An unindexed bag (a `.bag.active`
left by a crashed `rosbag record`, or a bag whose index was cut off) is read record by record, as
`rosbag reindex` would, up to its last complete record. A file that cannot be read at all gets an
error naming it; the other bags are still read. Many bags are read in parallel processes.
"""
import glob
import math
import os
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from offload_learner_py.core.reward import CostWeights
from offload_learner_py.data.bag_decoding import Decoder
from offload_learner_py.data.bag_format import indexed_messages, scan_unindexed
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.data.records import DECISION_DEFAULTS, OUTCOME_DEFAULTS, Pairing, PairingCounts, \
    RequestLog, transition_table

DECISION_TYPE = "offload_msgs/msg/OffloadDecision"
OUTCOME_TYPE = "offload_msgs/msg/OffloadOutcome"
CONFIG_TYPE = "offload_msgs/msg/LearnerConfig"
BAG_SUFFIXES = (".bag", ".bag.active")
# Our message definitions are a few kB with a few dozen fields; one far larger under our type names is
# hostile (parsing a 200k-field definition took minutes and gigabytes), and so are many distinct ones.
MAX_DEFINITION_BYTES = 64 * 1024
MAX_DEFINITION_FIELDS = 256
MAX_DEFINITIONS = 16
# The learner's latched settings (offload_msgs/LearnerConfig); every field optional.
CONFIG_DEFAULTS = {"policy": "", "mode": "", "learn": False, "explore": False, "alpha": math.nan, "beta": math.nan,
                   "gamma": math.nan, "epsilon": math.nan, "learning_starts": 0, "probe_rate": math.nan,
                   "cloud_timeout_s": math.nan, "hedge": False, "hedge_deadline_s": math.nan,
                   "hedge_quantile": math.nan, "hedge_min_s": math.nan, "hedge_max_s": math.nan,
                   "breaker_failures": 0, "breaker_max_round_trip_s": math.nan, "breaker_retry_s": math.nan,
                   "seed": 0, "dqn_config_json": ""}


class BagReadError(ValueError):
    """A bag that cannot be read; the message names the file."""


@dataclass
class BagReport(PairingCounts):
    """What one bag held and what became of it (the pairing counts, and the reading's own)."""
    path: str = ""
    ok: bool = True
    error: str = ""
    indexed: bool = True
    recovered_note: str = ""          # how an unindexed or cut-off bag was read
    topics: Dict[str, int] = field(default_factory=dict)   # messages per topic that was read
    ignored_topics: Dict[str, int] = field(default_factory=dict)
    undecodable: int = 0              # messages that do not decode with their own definition
    damaged_chunks: int = 0           # chunks that do not decompress (their messages are lost)
    definitions: Dict[str, str] = field(default_factory=dict)   # message type -> md5 of the bag's definition
    configs: List[dict] = field(default_factory=list)   # the learner's latched settings, one per session


@dataclass
class ReadReport:
    bags: List[BagReport]
    duplicates_across_bags: int = 0   # identical requests found in two bags (kept once)
    id_collisions: int = 0            # same request id, different content, in two bags (both kept)

    @property
    def failed(self) -> List[BagReport]:
        return [bag for bag in self.bags if not bag.ok]

    def total(self, name: str) -> int:
        return sum(getattr(bag, name) for bag in self.bags)

    def recorded(self, name: str) -> list:
        """The distinct values of one LearnerConfig field over every session in the bags."""
        values = []
        for bag in self.bags:
            for config in bag.configs:
                if config.get(name) not in values:
                    values.append(config.get(name))
        return values

    def to_dict(self) -> dict:
        return {"bags": [asdict(bag) for bag in self.bags], "duplicates_across_bags": self.duplicates_across_bags,
                "id_collisions": self.id_collisions}

    def format(self) -> str:
        lines = []
        for bag in self.bags:
            if not bag.ok:
                lines.append(f"FAILED {bag.error}")
                continue
            lines.append(f"{bag.path}: {bag.decisions} decisions, {bag.outcomes} outcomes -> {bag.requests} "
                         f"requests ({bag.rewarded_steps} with both latencies, {bag.one_latency_steps} with one)")
            if not bag.indexed:
                lines.append(f"  {bag.recovered_note}")
            skipped = [f"{count} {what}" for count, what in (
                (bag.dropped_no_outcome, "decisions without outcome dropped"),
                (bag.orphan_outcomes, "outcomes without decision dropped"),
                (bag.duplicate_decisions, "duplicate decisions dropped"),
                (bag.duplicate_outcomes, "duplicate outcomes dropped"),
                (bag.invalid, "invalid requests dropped"),
                (bag.undecodable, "undecodable messages dropped"),
                (bag.damaged_chunks, "damaged chunks skipped")) if count]
            if skipped:
                lines.append("  skipped: " + ", ".join(skipped))
            for example in bag.invalid_examples:
                lines.append(f"    e.g. {example}")
            if bag.ignored_topics:
                lines.append("  ignored topics: " + ", ".join(f"{topic} ({count})" for topic, count in
                                                           sorted(bag.ignored_topics.items())))
        read = [bag for bag in self.bags if bag.ok]
        lines.append(f"read {len(read)}/{len(self.bags)} bags: {self.total('requests')} requests, "
                     f"{self.total('rewarded_steps')} transitions with both latencies, "
                     f"{self.total('one_latency_steps')} with one latency")
        if self.duplicates_across_bags or self.id_collisions:
            lines.append(f"across bags: {self.duplicates_across_bags} duplicate requests kept once, "
                         f"{self.id_collisions} request ids reused with different content (both kept)")
        return "\n".join(lines)


@dataclass
class BagData:
    """Every request read, in time order, and what the reading skipped."""
    log: RequestLog
    report: ReadReport

    def transition_table(self, metadata: Optional[dict] = None) -> TransitionTable:
        """Rows with both latencies (the eq. 10 reward), in time order."""
        return transition_table(self.log, {"sources": [bag.path for bag in self.report.bags if bag.ok],
                                           **(metadata or {})})


# --- finding bags ------------------------------------------------------------------------------
def expand_bag_paths(arguments: Sequence[str]) -> List[str]:
    """Files, globs and directories (searched recursively for .bag and .bag.active) to a sorted,
    duplicate-free list. An argument that names nothing is kept so the reader reports it."""
    found = []
    for argument in arguments:
        if os.path.isdir(argument):
            for root, _, names in os.walk(argument):
                found += [os.path.join(root, name) for name in names if name.endswith(BAG_SUFFIXES)]
        elif glob.has_magic(argument):
            matches = [path for path in glob.glob(argument, recursive=True) if os.path.isfile(path)]
            found += matches or [argument]   # a pattern that matches nothing is reported, not ignored
        else:
            found.append(argument)
    seen, result = set(), []
    for path in sorted(found):
        key = os.path.realpath(path)
        if key not in seen:
            seen.add(key)
            result.append(path)
    return result


def read_bag(path: str, weights: CostWeights = CostWeights()) -> Tuple[Dict[str, np.ndarray], BagReport]:
    """One bag's requests as RequestLog columns (plus stamp_ns), and its report. Raises BagReadError
    naming the file when it cannot be read at all."""
    report = BagReport(path=path)
    try:
        return _read_bag(path, report, weights), report
    except BagReadError:
        raise
    except MemoryError as error:
        raise BagReadError(f"{path}: cannot read bag: out of memory ({error})") from None
    except Exception as error:   # rosbags, struct, zlib, lz4 and the type system raise many types on bad input
        raise BagReadError(f"{path}: cannot read bag: {type(error).__name__}: {error}") from None


def _read_bag(path: str, report: BagReport, weights: CostWeights) -> Dict[str, np.ndarray]:
    from rosbags.rosbag1 import Reader, ReaderError

    if not os.path.isfile(path):
        raise BagReadError(f"{path}: no such bag file")
    with open(path, "rb") as source:
        if source.read(13) != b"#ROSBAG V2.0\n":
            raise BagReadError(f"{path}: not a ROS 1 bag (version 2.0 magic line missing)")
    reader = Reader(path)
    try:
        reader.open()
    except Exception as error:  # rosbags raises ReaderError, AssertionError, struct.error on a bad index
        # No index (index_pos 0), or one cut off or damaged: read the bag record by record instead.
        if getattr(reader, "bio", None) is not None:   # rosbags closes only on its own ReaderError
            reader.bio.close()
        why = "" if isinstance(error, ReaderError) and "not indexed" in str(error) else \
            f" ({type(error).__name__}: {error})"
        return _pair(_filtered(scan_unindexed(path, report, why), report), report, weights, path)
    try:
        wanted = _select(reader.connections, report)
        return _pair(indexed_messages(reader, wanted, report) if wanted else iter(()), report, weights, path)
    finally:
        reader.close()


def _is_ours(msgtype: str) -> bool:
    return msgtype in (DECISION_TYPE, OUTCOME_TYPE, CONFIG_TYPE)


def _select(connections, report: BagReport) -> List:
    wanted = []
    for connection in connections:
        if _is_ours(connection.msgtype):
            wanted.append(connection)
        else:
            report.ignored_topics[connection.topic] = report.ignored_topics.get(connection.topic, 0) + \
                connection.msgcount
    return wanted


def _filtered(messages, report: BagReport):
    for connection, time_ns, raw in messages:
        if _is_ours(connection.msgtype):
            yield connection, time_ns, raw
        else:
            report.ignored_topics[connection.topic] = report.ignored_topics.get(connection.topic, 0) + 1


def _pair(messages, report: BagReport, weights: CostWeights, path: str) -> Dict[str, np.ndarray]:
    decoders: Dict[Tuple[str, str, str], Decoder] = {}
    pairing = Pairing(report, weights)
    for connection, time_ns, raw in messages:
        key = (connection.msgtype, connection.md5sum, connection.msgdef)
        decoder = decoders.get(key)
        if decoder is None:
            if len(decoders) >= MAX_DEFINITIONS:
                raise BagReadError(f"{path}: more than {MAX_DEFINITIONS} distinct definitions of the learner's "
                                   "messages: not a recording of this learner")
            if len(connection.msgdef) > MAX_DEFINITION_BYTES or \
                    connection.msgdef.count("\n") > MAX_DEFINITION_FIELDS:
                raise BagReadError(f"{path}: the definition of {connection.msgtype} on {connection.topic} is "
                                   f"{len(connection.msgdef)} bytes in {connection.msgdef.count(chr(10))} lines, over "
                                   f"the {MAX_DEFINITION_BYTES}-byte / {MAX_DEFINITION_FIELDS}-line cap")
            defaults = {DECISION_TYPE: DECISION_DEFAULTS, CONFIG_TYPE: CONFIG_DEFAULTS}.get(connection.msgtype,
                                                                                          OUTCOME_DEFAULTS)
            try:
                decoder = Decoder(connection, defaults)
            except ValueError as error:
                raise BagReadError(f"{path}: {error}") from None
            decoders[key] = decoder
            report.definitions[connection.msgtype] = connection.md5sum
        try:
            values, stamp = decoder(raw)
        except Exception as error:   # one damaged message costs that message only
            report.undecodable += 1
            report.note(f"undecodable {connection.msgtype}: {type(error).__name__}: {error}")
            continue
        report.topics[connection.topic] = report.topics.get(connection.topic, 0) + 1
        if connection.msgtype == CONFIG_TYPE:
            report.configs.append(values)
            continue
        if connection.msgtype == DECISION_TYPE:
            pairing.decision(values, stamp or time_ns)
        else:
            pairing.outcome(values)
    return pairing.log().columns


# --- many bags ---------------------------------------------------------------------------------
def _read_one(path: str):
    try:
        columns, report = read_bag(path)
    except BagReadError as error:
        return None, BagReport(path=path, ok=False, error=str(error))
    return columns, report


def read_bags(arguments: Sequence[str], workers: Optional[int] = None) -> BagData:
    """Every request in the bags (files, globs, directories), merged in time order. A bag that cannot
    be read is reported (ok false, error naming it) and the others are still read. Bags are read in
    up to `workers` processes (default: the CPU count, one process for one bag)."""
    paths = expand_bag_paths(arguments)
    if workers is None:
        workers = os.cpu_count() or 1
    workers = max(1, min(workers, len(paths)))
    results: List[Tuple[Optional[Dict], BagReport]] = []
    if workers == 1:
        results = [_read_one(path) for path in paths]
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            futures = [pool.submit(_read_one, path) for path in paths]
            for path, future in zip(paths, futures):
                try:
                    results.append(future.result())
                except BrokenProcessPool:
                    # One reader process died (killed, out of memory) and broke the pool for every bag still
                    # in it: each of those is read again alone, so only the bag that kills a reader is lost.
                    results.append(_read_alone(path))
    return merge(results)


def _read_alone(path: str) -> Tuple[Optional[Dict], BagReport]:
    with ProcessPoolExecutor(max_workers=1) as pool:
        try:
            return pool.submit(_read_one, path).result()
        except BrokenProcessPool:
            return None, BagReport(path=path, ok=False, error=f"{path}: the reader process died reading it "
                                                              "(killed, or out of memory)")


def merge(results: Sequence[Tuple[Optional[Dict], BagReport]]) -> BagData:
    """One log from per-bag columns: a request found in two bags with the same content (the same bag
    given twice, overlapping splits) is kept once; the same id with other content (two robots) is
    kept twice and counted."""
    report = ReadReport([bag for _, bag in results])
    parts = []
    for index, (columns, _) in enumerate(results):
        if columns is not None and len(columns["request_id"]):
            parts.append({**columns, "bag": np.full(len(columns["request_id"]), index, dtype=np.int64)})
    if not parts:
        empty = Pairing().log().columns
        empty["bag"] = np.zeros(0, dtype=np.int64)
        return BagData(RequestLog(empty), report)
    merged = {name: np.concatenate([part[name] for part in parts]) for name in parts[0]}
    order = np.lexsort((merged["bag"], merged["request_id"], merged["stamp_ns"]))
    merged = {name: values[order] for name, values in merged.items()}
    keep = np.ones(len(order), dtype=bool)
    ids = merged["request_id"]
    by_id = np.argsort(ids, kind="stable")
    same = np.flatnonzero(ids[by_id][1:] == ids[by_id][:-1])
    compared = [name for name in merged if name not in ("bag", "policy")]
    for position in same:
        first, second = by_id[position], by_id[position + 1]
        if merged["bag"][first] == merged["bag"][second]:
            continue
        if all(_same(merged[name][first], merged[name][second]) for name in compared):
            keep[second] = False
            report.duplicates_across_bags += 1
        else:
            report.id_collisions += 1
    merged = {name: values[keep] for name, values in merged.items()}
    return BagData(RequestLog(merged), report)


def _same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b)) or \
        (np.isnan(a) and np.isnan(b) if np.issubdtype(type(a), np.floating) else False)
