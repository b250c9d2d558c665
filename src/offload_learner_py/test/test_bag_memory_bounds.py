"""Hostile bags read end to end by the command a user runs (`off_policy`), in a process of its own whose peak
memory is measured: an indexed bag whose one chunk inflates to 1 GiB, a learner message definition of
200,000 fields, and decisions whose strings inflate to 40 MB each. Each is refused (or its hostile messages
dropped, the real requests kept), within the documented 256 MiB per bag plus the interpreter (512 MiB in all)."""
import bz2
import struct
import subprocess
import sys

import pytest

from bagtools import make_requests, write
from hostile_bags import bag_records
from offload_demos.bag_writer import DECISION_TOPIC, BagWriter, installed_definitions, probe_request, \
    typestore_for, write_requests
from offload_learner_py.data.bags import DECISION_TYPE

PEAK_RSS_BOUND_MIB = 512
GIB = 1 << 30


def _inflating(codec: str) -> bytes:
    """1 GiB of zeros, compressed as rosbag compresses a chunk."""
    import lz4.frame
    compressor = lz4.frame.LZ4FrameCompressor() if codec == "lz4" else bz2.BZ2Compressor()
    pieces = [compressor.begin()] if codec == "lz4" else []
    zeros = bytes(64 << 20)
    pieces += [compressor.compress(zeros) for _ in range(GIB // len(zeros))]
    pieces.append(compressor.flush())
    return b"".join(pieces)


def bomb_bag(path, codec: str) -> str:
    """A real indexed bag whose first chunk's data is replaced by a 1 GiB bomb, the chunk header declaring
    that size honestly, and the index moved to match: an index reader sees a well-formed bag."""
    write(path, make_requests(20), compression=codec, chunk_bytes=1 << 20)
    blob = bytearray(open(path, "rb").read())
    records = list(bag_records(bytes(blob), 13))
    op = lambda fields: fields["op"][0][0]   # noqa: E731  (value, offset): the value's one byte
    bag_header = next(fields for _, fields, _, _ in records if op(fields) == 0x03)
    chunk_at, chunk, data_at, data_len = next(r for r in records if op(r[1]) == 0x05)
    bomb = _inflating(codec)
    struct.pack_into("<I", blob, chunk["size"][1], GIB)
    delta = len(bomb) - data_len
    (index_pos,) = struct.unpack_from("<Q", blob, bag_header["index_pos"][1])
    struct.pack_into("<Q", blob, bag_header["index_pos"][1], index_pos + delta)
    for at, fields, _, _ in records:      # later chunks' positions in the chunk infos move by delta
        if op(fields) == 0x06:
            (chunk_pos,) = struct.unpack_from("<Q", blob, fields["chunk_pos"][1])
            if chunk_pos > chunk_at:
                struct.pack_into("<Q", blob, fields["chunk_pos"][1], chunk_pos + delta)
    blob[data_at - 4:data_at + data_len] = struct.pack("<I", len(bomb)) + bomb
    open(path, "wb").write(blob)
    return str(path)


def hostile_definition_bag(path, fields: int = 200_000) -> str:
    """Real decisions under a definition text of `fields` fields (as a hostile author would store it)."""
    decision_msg, outcome_msg = installed_definitions()
    store = typestore_for(decision_msg, outcome_msg)
    md5 = store.generate_msgdef(DECISION_TYPE)[1]
    huge = decision_msg + "".join(f"float64 pad{k}\n" for k in range(fields))
    with BagWriter(str(path), store) as bag:
        bag.connections[(DECISION_TOPIC, DECISION_TYPE)] = bag.writer.add_connection(
            DECISION_TOPIC, DECISION_TYPE, msgdef=huge, md5sum=md5)
        for decision, _ in make_requests(5):
            bag.write(DECISION_TOPIC, DECISION_TYPE, decision, 1_700_000_000 * 10 ** 9)
    return str(path)


def run_off_policy(bag: str):
    """off_policy on one bag in a child of a fresh interpreter; (exit code, output, the child's peak RSS MiB)."""
    wrapper = ("import resource, subprocess, sys\n"
               "child = subprocess.run([sys.executable, '-m', 'offload_learner_py.offline.off_policy', sys.argv[1]],"
               " capture_output=True, text=True)\n"
               "sys.stdout.write(child.stdout + child.stderr)\n"
               "print('PEAK_KIB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
               "sys.exit(child.returncode)\n")
    done = subprocess.run([sys.executable, "-c", wrapper, bag], capture_output=True, text=True, timeout=600)
    peak_kib = int(done.stdout.rsplit("PEAK_KIB", 1)[1])
    return done.returncode, done.stdout, peak_kib / 1024


@pytest.mark.parametrize("codec", ["lz4", "bz2"])
def test_an_indexed_bag_whose_chunk_inflates_to_a_gibibyte_is_refused_in_bounded_memory(tmp_path, codec):
    bag = bomb_bag(tmp_path / f"bomb-{codec}.bag", codec)
    code, output, peak_mib = run_off_policy(bag)
    assert code != 0
    assert f"bomb-{codec}.bag" in output and "more than" in output, output
    assert peak_mib <= PEAK_RSS_BOUND_MIB, f"peak RSS {peak_mib:.0f} MiB"


def test_a_two_hundred_thousand_field_definition_is_refused_in_bounded_memory(tmp_path):
    bag = hostile_definition_bag(tmp_path / "hostile.bag")
    code, output, peak_mib = run_off_policy(bag)
    assert code != 0 and "hostile.bag" in output and "cap" in output, output
    assert peak_mib <= PEAK_RSS_BOUND_MIB, f"peak RSS {peak_mib:.0f} MiB"


def test_decisions_with_forty_megabyte_strings_are_dropped_in_bounded_memory(tmp_path):
    """Found by the fuzzer (an 8 kB input past libFuzzer's 1 GiB): a decision's strings are kept with its
    request, so twelve lz4 chunks each inflating to a decision with a 40 MB policy name held about 700 MiB.
    Now a message over the cap is dropped unread and counted, and the real requests around it are kept."""
    huge = "a" * (40 << 20)
    requests = make_requests(6)
    for k in range(12):
        decision, outcome = probe_request(9000 + k, 0.5, 0.5, 0.03, 0.02, 0.05, 0, 0.5, 0.1)
        decision["policy"] = huge
        requests.append((decision, outcome))
    bag = str(tmp_path / "strings.bag")
    write_requests(bag, requests, compression="lz4", chunk_bytes=1 << 10)
    code, output, peak_mib = run_off_policy(bag)
    assert peak_mib <= PEAK_RSS_BOUND_MIB, f"peak RSS {peak_mib:.0f} MiB"
    assert code == 0, output
    from offload_learner_py.data.bags import read_bag
    columns, report = read_bag(bag)
    assert report.undecodable == 12 and any("cap" in note for note in report.invalid_examples)
    assert len(columns["request_id"]) == 6
