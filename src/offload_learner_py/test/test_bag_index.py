"""The attack round's bag findings (#31): an amplified index (chunk-info records naming one chunk, connection
records sharing one id) is not trusted and the bag is scanned front to back, its real requests kept; a
learner definition nesting levels of fields ("billion laughs") is refused from its flattened size before a
decoder is built; a bag of thousands of junk connections gets a report of bounded size. Unit tests measure
memory with tracemalloc; the end-to-end ones run `off_policy` in a child (2 GiB address-space limit, a
timeout) and check its peak RSS against the documented 512 MiB."""
import struct
import subprocess
import sys
import tracemalloc

import pytest

from hostile_bags import chunk_info_amplified, connection_amplified, junk_connections, nested_definition, \
    nested_definition_text, real_bag, _rewrite_index
from offload_learner_py.data import bags
from offload_learner_py.data.bags import BagReadError, DECISION_TYPE, read_bag

PEAK_RSS_BOUND_MIB = 512
MAX_LISTED_TOPICS, MAX_CONFIGS, MAX_FLATTENED_FIELDS = 20, 32, 4096   # bag_report's and bag_decoding's caps


def _peak_mib(function, *args):
    tracemalloc.start()
    try:
        result = function(*args)
        return result, tracemalloc.get_traced_memory()[1] / 2 ** 20
    finally:
        tracemalloc.stop()


def test_chunk_info_records_naming_one_chunk_are_not_trusted_and_the_requests_are_kept(tmp_path):
    """rosbags re-read the chunk's index records once per chunk-info record: 2,000 copies held 800,000
    index entries (~100 MiB); the 9.8 MB finding (100k copies) grew to 10 GiB."""
    bag = chunk_info_amplified(tmp_path / "infos.bag", copies=2000)
    (columns, report), peak = _peak_mib(read_bag, bag)
    assert len(columns["request_id"]) == 200 and report.requests == 200
    assert not report.indexed and "two chunk-info records name the chunk" in report.recovered_note
    assert peak < 32, f"{peak:.0f} MiB traced"


def test_connection_records_sharing_an_id_are_not_trusted_and_the_requests_are_kept(tmp_path):
    """rosbags sorted the connection's index once per record with its id: 20,000 records with one id over
    200,000 messages took 11 minutes of a core. Such an index is scanned instead, once."""
    bag = connection_amplified(tmp_path / "connections.bag", copies=50, messages=2000)
    columns, report = read_bag(bag)
    assert report.requests == 200
    assert not report.indexed and "two connection records with id" in report.recovered_note
    assert report.ignored_topics == {"/noise": 2000}


@pytest.mark.parametrize("where", ["past the index", "inside the first chunk", "unknown connection"])
def test_an_index_naming_what_the_bag_lacks_is_scanned_instead(tmp_path, where):
    bag = real_bag(tmp_path / "real.bag")
    blob = open(bag, "rb").read()
    (index_pos,) = struct.unpack_from("<Q", blob, blob.index(b"index_pos=") + len(b"index_pos="))
    chunk_pos, conn = {"past the index": (index_pos + 10, 0), "inside the first chunk": (4200, 0),
                       "unknown connection": (index_pos - 100, 99)}[where]
    fields = [(b"op", b"\x06"), (b"ver", struct.pack("<I", 1)), (b"chunk_pos", struct.pack("<Q", chunk_pos)),
              (b"start_time", bytes(8)), (b"end_time", bytes(8)), (b"count", struct.pack("<I", 1))]
    header = b"".join(struct.pack("<I", len(n) + 1 + len(v)) + n + b"=" + v for n, v in fields)
    record = struct.pack("<I", len(header)) + header + struct.pack("<I", 8) + struct.pack("<II", conn, 1)
    _rewrite_index(bag, extra_chunk_infos=record, extra_chunk_info_count=1)
    from offload_learner_py.data.bag_index import IndexRefused, read_index
    with pytest.raises(IndexRefused):
        read_index(bag, lambda msgtype: True)
    _, report = read_bag(bag)
    assert report.requests == 200 and not report.indexed


def test_the_index_of_a_real_bag_is_read_as_rosbags_reads_it(tmp_path):
    from rosbags.rosbag1 import Reader
    from offload_learner_py.data.bag_index import read_index

    bag = connection_amplified(tmp_path / "noise.bag", copies=0, messages=2000)
    index = read_index(bag, lambda msgtype: msgtype != "std_msgs/msg/Empty")
    with Reader(bag) as reader:
        assert {c.id: (c.topic, c.msgtype, c.msgcount) for c in reader.connections} == \
            {c.id: (c.topic, c.msgtype, index.msgcounts[c.id]) for c in index.connections.values()}
        ours = {c.id for c in reader.connections if c.msgtype != "std_msgs/msg/Empty"}
        holding = {info.pos for info in reader.chunk_infos if ours & set(info.connection_counts)}
        assert [chunk.pos for chunk in index.chunks] == sorted(holding)
    assert index.connections[next(k for k, c in index.connections.items() if c.topic == "/noise")].msgdef == ""


def test_a_nested_definition_is_refused_from_its_flattened_size_before_a_decoder_is_built(tmp_path):
    """4 levels of 20 fields: 160,000 fields once flattened, in 120 lines (6 levels: 6.4e7 and 10 GiB)."""
    bag = nested_definition(tmp_path / "nested.bag", levels=4, fan=20)
    with pytest.raises(BagReadError, match=f"flattens to more than {MAX_FLATTENED_FIELDS} fields") as error:
        read_bag(bag)
    assert "nested.bag" in str(error.value)
    from offload_learner_py.data import bag_decoding
    assert bag_decoding.MAX_FLATTENED_FIELDS == MAX_FLATTENED_FIELDS


def _types(text, name="offload_msgs/msg/OffloadDecision"):
    from rosbags.typesys import get_types_from_msg
    return get_types_from_msg(text, name)


def test_flattened_size_counts_each_type_once_and_refuses_the_shapes_that_explode():
    from offload_demos.bag_writer import installed_definitions, typestore_for
    from offload_learner_py.data.bag_decoding import flattened_fields

    decision, outcome = installed_definitions()
    text = typestore_for(decision, outcome).generate_msgdef(DECISION_TYPE)[0]
    assert 10 < flattened_fields(_types(text), DECISION_TYPE) < 100
    # 40 levels of 2 fields: 2 ** 40 once flattened, counted in 80 steps
    with pytest.raises(ValueError, match="flattens to more than"):
        flattened_fields(_types(nested_definition_text(levels=40, fan=2)), DECISION_TYPE)
    separator = "=" * 80 + "\n"
    for body, why in (("a/Empty[5000] e\n" + separator + "MSG: a/Empty\n", "flattens to more than"),
                      ("a/Empty[] e\n" + separator + "MSG: a/Empty\n", "variable-length array of a type without"),
                      ("float64[100000] x\n", "flattens to more than")):
        with pytest.raises(ValueError, match=why):
            flattened_fields(_types(body, "a/msg/Top"), "a/msg/Top")
    looped = {"a/msg/A": ([], [("b", (_kind("NAME"), "a/msg/B"))]),
              "a/msg/B": ([], [("a", (_kind("NAME"), "a/msg/A"))])}
    with pytest.raises(ValueError, match="contains itself"):
        flattened_fields(looped, "a/msg/A")
    assert flattened_fields(_types("a/Empty[] e\nuint8 x\n" + separator + "MSG: a/Empty\nuint8 y\n", "a/msg/T"),
                            "a/msg/T") == 2


def _kind(name):
    from rosbags.interfaces import Nodetype
    return Nodetype[name]


def test_a_bag_of_thousands_of_junk_connections_gets_a_report_of_bounded_size(tmp_path):
    """250,000 junk connections once made a 4.75 MB terminal line and 17 MB of report files."""
    bag = junk_connections(tmp_path / "junk.bag", count=5000)
    data = bags.read_bags([bag], workers=1)
    report = data.report.bags[0]
    assert report.requests == 200
    assert len(report.ignored_topics) == MAX_LISTED_TOPICS and report.other_topics == 5000 - MAX_LISTED_TOPICS
    assert len(data.report.format()) < 4000 and len(str(data.report.to_dict())) < 8000
    from offload_learner_py.data import bag_report
    assert (bag_report.MAX_LISTED_TOPICS, bag_report.MAX_CONFIGS) == (MAX_LISTED_TOPICS, MAX_CONFIGS)


def test_the_learner_settings_kept_per_bag_are_bounded(tmp_path):
    from offload_demos.bag_writer import CONFIG_TOPIC, CONFIG_TYPE, config_definition, installed_definitions, \
        typestore_for
    from bagtools import make_requests, write

    store = typestore_for(*installed_definitions(), extra={CONFIG_TYPE: config_definition()})

    def extra(bag, index, time_ns):   # 100 sessions' settings: 40 distinct seeds, each 2-3 times
        bag.write(CONFIG_TOPIC, CONFIG_TYPE, {"mode": "learning", "alpha": 0.5, "seed": index % 40}, time_ns)
    data = bags.read_bags([write(tmp_path / "configs.bag", make_requests(100), store=store, extra=extra)])
    report = data.report.bags[0]
    # seeds 0-31 kept (their repeats too: once each), seeds 32-39 counted each time they come (twice)
    assert len(report.configs) == MAX_CONFIGS and report.other_configs == 2 * (40 - MAX_CONFIGS)
    assert data.report.recorded("alpha") == [0.5]


def run_off_policy(bag: str, timeout: int = 120):
    """off_policy on one bag in a child limited to 2 GiB of address space; (exit code, output, peak RSS MiB)."""
    wrapper = ("import resource, subprocess, sys\n"
               "limit = lambda: resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))\n"
               "child = subprocess.run([sys.executable, '-m', 'offload_learner_py.offline.off_policy', sys.argv[1]],"
               " capture_output=True, text=True, preexec_fn=limit)\n"
               "sys.stdout.write(child.stdout + child.stderr)\n"
               "print('PEAK_KIB', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
               "sys.exit(child.returncode)\n")
    done = subprocess.run([sys.executable, "-c", wrapper, bag], capture_output=True, text=True, timeout=timeout)
    peak_kib = int(done.stdout.rsplit("PEAK_KIB", 1)[1])
    return done.returncode, done.stdout, peak_kib / 1024


@pytest.mark.parametrize("build", [chunk_info_amplified, connection_amplified], ids=["chunk_infos", "connections"])
def test_off_policy_reads_the_finding_sized_amplified_bags_in_bounded_memory_and_time(tmp_path, build):
    """The findings' sizes: 100,000 chunk-info copies (12 MB), 20,000 connection records over 200,000
    messages (15 MB). Before: killed at 10 GiB, and 11 minutes of a core."""
    code, output, peak_mib = run_off_policy(build(tmp_path / "amplified.bag"), timeout=60)
    assert code == 0 and "200 requests" in output and "not indexed" in output, output
    assert peak_mib <= PEAK_RSS_BOUND_MIB, f"peak RSS {peak_mib:.0f} MiB"


def test_off_policy_refuses_the_finding_sized_nested_definition_in_bounded_memory(tmp_path):
    code, output, peak_mib = run_off_policy(nested_definition(tmp_path / "nested.bag", levels=6, fan=20), timeout=60)
    assert code != 0 and "nested.bag" in output and "flattens to more than" in output, output
    assert peak_mib <= PEAK_RSS_BOUND_MIB, f"peak RSS {peak_mib:.0f} MiB"
