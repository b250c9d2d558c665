"""The bag reader on damaged and hostile bags: unindexed and cut-off bags read up to their last whole record,
damaged files named while the other bags still read, hostile headers, chunks and definitions refused without
exhausting memory, a reader killed on one bag losing that bag only."""
import os
import shutil

import pytest

from bagtools import make_requests, write
from offload_learner_py.data import bag_format, bags
from offload_demos.bag_writer import OUTCOME_TOPIC, installed_definitions, typestore_for, unindex


@pytest.mark.parametrize("compression", ["none", "lz4", "bz2"])
def test_an_unindexed_bag_cut_mid_chunk_reads_up_to_its_last_complete_record(tmp_path, compression):
    requests = make_requests(400, probe_every=2)
    full = write(tmp_path / "full.bag", requests, compression=compression, chunk_bytes=4096)
    complete = bags.read_bags([full]).log
    active = str(tmp_path / "run.bag.active")
    shutil.copy(full, active)
    size = os.path.getsize(full)
    unindex(active, keep_bytes=int(size * 0.6))   # a crash: no index, the last chunk cut in the middle
    data = bags.read_bags([str(tmp_path)])   # a directory: the .bag.active is found too
    reports = {os.path.basename(bag.path): bag for bag in data.report.bags}
    recovered = reports["run.bag.active"]
    assert recovered.ok, recovered.error
    assert not recovered.indexed and "rosbag reindex" in recovered.recovered_note
    assert 100 < recovered.requests < 400
    assert "rosbag reindex" in data.report.format()
    # every recovered request is exactly the written one (the full bag's copies are kept once)
    got = bags.read_bag(active)[0]
    index = {int(i): k for k, i in enumerate(complete["request_id"])}
    for k, request_id in enumerate(got["request_id"]):
        for name in ("input_size", "action", "outcome_reward_valid"):
            assert got[name][k] == complete[name][index[int(request_id)]]
    assert data.report.duplicates_across_bags == recovered.requests
    if compression == "none":   # records of the cut chunk that were written whole are kept
        assert "cut-off last chunk" in recovered.recovered_note


def test_the_records_a_crash_left_whole_in_an_uncompressed_chunk_are_kept(tmp_path):
    from rosbags.rosbag1 import Reader

    full = write(tmp_path / "full.bag", make_requests(200), chunk_bytes=4096)
    with Reader(full) as reader:
        outcome = next(c for c in reader.connections if c.topic == OUTCOME_TOPIC)
        middle = sorted(reader.chunks)[len(reader.chunks) // 2]
        cut = reader.chunks[middle].datapos + 3000
        # outcome records (each under 400 bytes, after their decision) that end before the cut
        expected = sum(1 for entry in reader.indexes[outcome.id]
                       if reader.chunks[entry.chunk_pos].datapos + entry.offset + 400 <= cut)
        in_complete_chunks = sum(1 for entry in reader.indexes[outcome.id] if entry.chunk_pos < middle)
    assert expected > in_complete_chunks
    unindex(full, keep_bytes=cut)
    columns, report = bags.read_bag(full)
    assert report.requests >= expected


def test_an_unindexed_complete_bag_reads_everything(tmp_path):
    path = write(tmp_path / "x.bag", make_requests(50), chunk_bytes=2048)
    unindex(path)
    data = bags.read_bags([path])
    assert len(data.log) == 50 and not data.report.bags[0].indexed


def test_damaged_files_get_an_error_naming_them_and_the_other_bags_still_read(tmp_path):
    good = write(tmp_path / "good.bag", make_requests(40), compression="lz4", chunk_bytes=2048)
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(os.urandom(5000))
    flipped = tmp_path / "flipped.bag"
    raw = bytearray(open(good, "rb").read())
    for offset in range(5000, 5400):   # inside the first chunks' compressed data
        raw[offset] ^= 0xFF
    flipped.write_bytes(bytes(raw))
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    missing = str(tmp_path / "missing.bag")
    data = bags.read_bags([str(tmp_path / "*.bag"), missing, str(tmp_path / "nothing*.bag")], workers=2)
    reports = {os.path.basename(bag.path): bag for bag in data.report.bags}
    assert reports["good.bag"].ok and reports["good.bag"].requests == 40
    for name in ("garbage.bag", "empty.bag", "missing.bag", "nothing*.bag"):
        assert not reports[name].ok and name in reports[name].error
    damaged = reports["flipped.bag"]
    # either refused with its name, or read with the damaged messages counted and dropped
    assert (not damaged.ok and "flipped.bag" in damaged.error) or damaged.requests < 40
    assert len(data.log) >= 40
    assert "FAILED" in data.report.format()


def test_hostile_headers_do_not_exhaust_memory(tmp_path):
    path = write(tmp_path / "h.bag", make_requests(10), chunk_bytes=1024)
    unindex(path)
    raw = bytearray(open(path, "rb").read())
    at = raw.find(b"compression=")
    # the first chunk record claims 4 GB of data: read what is there, never allocate the claim
    header_end = raw.find(b"size=", at)
    raw[header_end + 5:header_end + 9] = (0xFFFFFFF0).to_bytes(4, "little")
    (tmp_path / "h.bag").write_bytes(bytes(raw))
    data = bags.read_bags([path])
    bag = data.report.bags[0]
    assert (not bag.ok and "h.bag" in bag.error) or bag.requests <= 10


@pytest.mark.parametrize("codec", ["lz4", "bz2"])
def test_a_chunk_that_inflates_past_its_declared_size_is_refused_without_inflating(codec):
    """A decompression bomb: a small chunk whose data inflates to far more than its header declares (and
    than the cap). Decompression stops one byte past the bound, so memory stays bounded."""
    import bz2
    import struct

    import lz4.frame
    zeros = bytes(16 << 20)
    compressor = lz4.frame.LZ4FrameCompressor() if codec == "lz4" else bz2.BZ2Compressor()
    pieces = [compressor.begin()] if codec == "lz4" else []
    pieces += [compressor.compress(zeros) for _ in range(8)]   # 128 MiB, over the 64 MiB cap
    pieces.append(compressor.flush())
    bomb = b"".join(pieces)
    assert len(bomb) < (2 << 20)
    with pytest.raises(ValueError, match="inflates past its declared 4096 bytes"):
        bag_format.decompress_chunk(codec, bomb, {"size": struct.pack("<I", 4096)})
    with pytest.raises(ValueError, match="inflates past"):
        bag_format.decompress_chunk(codec, bomb, {})          # no declared size: the cap bounds it
    with pytest.raises(ValueError, match="more than"):
        bag_format.decompress_chunk(codec, bomb, {"size": struct.pack("<I", 1 << 30)})


_REAL_READ_ONE = bags._read_one


def _read_one_killed_on_killer(path):
    """A reader the kernel kills (as the OOM killer would) on one bag; module level so workers can run it."""
    if path.endswith("killer.bag"):
        os.kill(os.getpid(), 9)
    return _REAL_READ_ONE(path)


def test_a_reader_killed_on_one_bag_loses_that_bag_only(tmp_path, monkeypatch):
    """A reader process that dies (the OOM killer) broke the pool, and five good bags were reported as
    dead with it: now each is read again alone, and only the killing bag is reported, as what it is."""
    good = [write(tmp_path / f"good{k}.bag", make_requests(5, first_id=100 * k)) for k in range(4)]
    killer = str(tmp_path / "killer.bag")
    shutil.copy(good[0], killer)
    monkeypatch.setattr(bags, "_read_one", _read_one_killed_on_killer)
    data = bags.read_bags(good + [killer], workers=2)
    failed = data.report.failed
    assert [bag.path for bag in failed] == [killer] and "reader process died" in failed[0].error
    assert sum(bag.ok for bag in data.report.bags) == 4 and len(data.log) == 20


def test_a_hostile_definition_under_our_type_name_is_refused_at_once(tmp_path):
    """A definition of thousands of fields under the learner's type name (parsing 200k of them took minutes
    and gigabytes) is refused before it is parsed, naming the bag."""
    decision_msg, outcome_msg = installed_definitions()
    padded = decision_msg + "".join(f"float64 pad{k}\n" for k in range(2000))
    store = typestore_for(padded, outcome_msg)
    path = write(tmp_path / "hostile.bag", make_requests(3), store=store)
    data = bags.read_bags([path])
    (failed,) = data.report.failed
    assert "hostile.bag" in failed.error and "cap" in failed.error
