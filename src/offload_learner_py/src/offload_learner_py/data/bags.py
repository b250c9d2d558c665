"""ROS 1 bags to the learner's records and the one transition table, without ROS.

Reads OffloadDecision and OffloadOutcome messages (the index read and checked by `bag_index`, the chunks
by `bag_format`), decoding each bag with the message definitions stored in that bag (`bag_decoding`, so a
bag written with an older version of the messages still reads), and pairs them by request id into a `records.RequestLog`; `records.transition_table`
turns that into TransitionTable rows. What real bags hold is tolerated and counted: other topics
(ignored, never decoded), decisions without an outcome (dropped), outcomes without a decision,
duplicate request ids, invalid values, and steps with one latency only (kept in the log for
off-policy evaluation, not in the table, since eq. 10 needs both). An unindexed bag (a `.bag.active`
left by a crashed `rosbag record`, or a bag whose index is cut off or absurd) is read record by record, as
`rosbag reindex` would, up to its last complete record. A file that cannot be read at all gets an
error naming it; the other bags are still read. Many bags are read in parallel processes.
"""
import glob
import math
import os
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from offload_learner_py.core.reward import CostWeights
from offload_learner_py.data.bag_decoding import Decoder
from offload_learner_py.data.bag_format import indexed_messages, scan_unindexed
from offload_learner_py.data.bag_index import IndexRefused, read_index
from offload_learner_py.data.bag_report import BagReport, ReadReport
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.data.records import DECISION_DEFAULTS, OUTCOME_DEFAULTS, Pairing, RequestLog, \
    transition_table

DECISION_TYPE = "offload_msgs/msg/OffloadDecision"
OUTCOME_TYPE = "offload_msgs/msg/OffloadOutcome"
CONFIG_TYPE = "offload_msgs/msg/LearnerConfig"
BAG_SUFFIXES = (".bag", ".bag.active")
# Our message definitions are a few kB with a few dozen fields; one far larger under our type names is
# hostile (parsing a 200k-field definition took minutes and gigabytes), and so are many distinct ones.
MAX_DEFINITION_BYTES = 64 * 1024
MAX_DEFINITION_FIELDS = 256
MAX_DEFINITIONS = 16
# A decision or an outcome is a few hundred bytes and the settings a few kB (their strings are names, a hash and a
# small JSON). A message far larger is damage or hostility: its strings would be kept with the request (a 15 kB bz2
# bag of six decisions with 40 MB policy names held 364 MiB; the fuzzer's went past 1 GiB), so it is dropped unread.
MAX_MESSAGE_BYTES = 64 * 1024
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
    if not os.path.isfile(path):
        raise BagReadError(f"{path}: no such bag file")
    with open(path, "rb") as source:
        if source.read(13) != b"#ROSBAG V2.0\n":
            raise BagReadError(f"{path}: not a ROS 1 bag (version 2.0 magic line missing)")
    try:
        index = read_index(path, _is_ours)
    except IndexRefused as error:
        # No index (index_pos 0), or one cut off, damaged or absurd: read the bag record by record instead.
        why = "" if str(error) == "not indexed" else f" ({error})"
        return _pair(_filtered(scan_unindexed(path, report, why), report), report, weights, path)
    wanted = {}
    ignored: Dict[str, int] = {}
    for connection in index.connections.values():
        if _is_ours(connection.msgtype):
            wanted[connection.id] = connection
        else:
            ignored[connection.topic] = ignored.get(connection.topic, 0) + index.msgcounts[connection.id]
    report.list_topics("ignored_topics", ignored)
    return _pair(indexed_messages(path, index.chunks, wanted, report), report, weights, path)


def _is_ours(msgtype: str) -> bool:
    return msgtype in (DECISION_TYPE, OUTCOME_TYPE, CONFIG_TYPE)


def _filtered(messages, report: BagReport):
    ignored: Dict[str, int] = {}
    for connection, time_ns, raw in messages:
        if _is_ours(connection.msgtype):
            yield connection, time_ns, raw
        else:
            ignored[connection.topic] = ignored.get(connection.topic, 0) + 1
    report.list_topics("ignored_topics", ignored)


def _pair(messages, report: BagReport, weights: CostWeights, path: str) -> Dict[str, np.ndarray]:
    decoders: Dict[Tuple[str, str, str], Decoder] = {}
    topics: Dict[str, int] = {}
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
        if len(raw) > MAX_MESSAGE_BYTES:
            report.undecodable += 1
            report.note(f"a {connection.msgtype} of {len(raw)} bytes, over the {MAX_MESSAGE_BYTES}-byte cap: dropped")
            continue
        try:
            values, stamp = decoder(raw)
        except Exception as error:   # one damaged message costs that message only
            report.undecodable += 1
            report.note(f"undecodable {connection.msgtype}: {type(error).__name__}: {error}")
            continue
        topics[connection.topic] = topics.get(connection.topic, 0) + 1
        if connection.msgtype == CONFIG_TYPE:
            report.add_config(values, stamp or time_ns)
            continue
        if connection.msgtype == DECISION_TYPE:
            pairing.decision(values, stamp or time_ns)
        else:
            pairing.outcome(values)
    report.list_topics("topics", topics)
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
