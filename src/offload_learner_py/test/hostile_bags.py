"""Hostile bags of the attack round (#31), built at test time from a real bag of requests: an index
amplified by repeated chunk-info or connection records, thousands of junk connections, and a learner
definition nesting levels of fields ("billion laughs"). Each keeps the real requests, so a reader that
refuses the index but scans the bag still finds them. Also runnable as a script to write them to a
scratch directory: python hostile_bags.py DIR [REQUESTS]."""
import struct
import sys

from bagtools import make_requests, write
from offload_demos.bag_writer import DECISION_TOPIC, DECISION_TYPE, OUTCOME_TOPIC, OUTCOME_TYPE, BagWriter, \
    installed_definitions, typestore_for


def _field(name: bytes, value: bytes) -> bytes:
    return struct.pack("<I", len(name) + 1 + len(value)) + name + b"=" + value


def _record(fields, data: bytes = b"") -> bytes:
    header = b"".join(_field(name, value) for name, value in fields)
    return struct.pack("<I", len(header)) + header + struct.pack("<I", len(data)) + data


def bag_records(blob: bytes, at: int):
    """(offset, header fields, data offset, data length) of each ROS 1 bag record from `at` on; a field is
    (value, the value's file offset), so a test can patch it in place."""
    while at + 4 <= len(blob):
        (header_len,) = struct.unpack_from("<I", blob, at)
        header = blob[at + 4:at + 4 + header_len]
        (data_len,) = struct.unpack_from("<I", blob, at + 4 + header_len)
        fields, k = {}, 0
        while k < len(header):
            (n,) = struct.unpack_from("<I", header, k)
            name, _, value = header[k + 4:k + 4 + n].partition(b"=")
            fields[name.decode()] = (value, at + 4 + k + 4 + len(name) + 1)
            k += 4 + n
        yield at, fields, at + 8 + header_len, data_len
        at += 8 + header_len + data_len


def _rewrite_index(path: str, extra_connections=b"", extra_connection_count=0, extra_chunk_infos=b"",
                   extra_chunk_info_count=0, chunk_info_copies=0) -> str:
    """Append records to the bag's index section and raise the counts in its bag header to match;
    chunk_info_copies more copies of the first chunk-info record (all naming the first chunk)."""
    blob = bytearray(open(path, "rb").read())
    header = next(bag_records(bytes(blob), 13))[1]
    assert header["op"][0] == b"\x03"
    (index_pos,) = struct.unpack_from("<Q", blob, header["index_pos"][1])
    records = [(fields["op"][0], bytes(blob[at:data_at + n])) for at, fields, data_at, n in
               bag_records(bytes(blob), index_pos)]
    connections = b"".join(record for op, record in records if op == b"\x07")
    infos = [record for op, record in records if op == b"\x06"]
    index = connections + extra_connections + b"".join(infos) + infos[0] * chunk_info_copies + extra_chunk_infos
    (conn_count,) = struct.unpack_from("<I", blob, header["conn_count"][1])
    (chunk_count,) = struct.unpack_from("<I", blob, header["chunk_count"][1])
    struct.pack_into("<I", blob, header["conn_count"][1], conn_count + extra_connection_count)
    struct.pack_into("<I", blob, header["chunk_count"][1], chunk_count + chunk_info_copies + extra_chunk_info_count)
    open(path, "wb").write(bytes(blob[:index_pos]) + index)
    return str(path)


def real_bag(path, requests: int = 200) -> str:
    return write(path, make_requests(requests), chunk_bytes=1 << 20)


def chunk_info_amplified(path, copies: int = 100_000, requests: int = 200) -> str:
    """Many chunk-info records naming the first chunk (the 9.8 MB finding: 100k copies)."""
    return _rewrite_index(real_bag(path, requests), chunk_info_copies=copies)


def _connection(conn_id: int, topic: str, msgtype: str = "std_msgs/String", definition: str = "string data\n",
                md5: str = "992ce8a1687cec8c8bd883ec73ca41d1") -> bytes:
    data = b"".join(_field(name, value) for name, value in (
        (b"topic", topic.encode()), (b"type", msgtype.encode()), (b"md5sum", md5.encode()),
        (b"message_definition", definition.encode())))
    return _record(((b"op", b"\x07"), (b"conn", struct.pack("<I", conn_id)), (b"topic", topic.encode())), data)


def connection_amplified(path, copies: int = 20_000, requests: int = 200, messages: int = 200_000) -> str:
    """The real requests, `messages` empty messages on one other topic, and `copies` more connection records
    with that topic's id in the index (the 14 MB finding: 20k)."""
    def noise(bag, index, time_ns):
        for k in range(messages // requests):
            bag.write_raw("/noise", "std_msgs/msg/Empty", b"", time_ns + k)
    write(path, make_requests(requests), chunk_bytes=1 << 22, extra=noise)
    blob = open(path, "rb").read()
    header = next(bag_records(blob, 13))[1]
    (index_pos,) = struct.unpack_from("<Q", blob, header["index_pos"][1])
    noise_record = next(fields for _, fields, _, _ in bag_records(blob, index_pos)
                        if fields["op"][0] == b"\x07" and fields["topic"][0] == b"/noise")
    (conn_id,) = struct.unpack("<I", noise_record["conn"][0])
    one = _connection(conn_id, "/noise", "std_msgs/Empty", "", "d41d8cd98f00b204e9800998ecf8427e")
    return _rewrite_index(path, one * copies, copies)


def junk_connections(path, count: int = 250_000, requests: int = 200) -> str:
    """`count` connections on distinct topics, none with a message (the 250k-connection finding)."""
    real_bag(path, requests)
    extra = b"".join(_connection(1000 + k, f"/junk/topic_{k:07d}") for k in range(count))
    return _rewrite_index(path, extra, count)


def nested_definition_text(levels: int = 6, fan: int = 20) -> str:
    """OffloadDecision with one more field whose type nests `levels` levels of `fan` fields each:
    fan ** levels primitive fields once flattened, in about levels * fan lines."""
    decision_msg, outcome_msg = installed_definitions()
    text = typestore_for(decision_msg, outcome_msg).generate_msgdef(DECISION_TYPE)[0]   # with its Header
    own, separator, dependencies = text.partition("=" * 80 + "\n")
    parts = [own.rstrip("\n") + "\noffload_msgs/Laugh0 laughs\n" + separator + dependencies.rstrip("\n")]
    for level in range(levels):
        inner = f"offload_msgs/Laugh{level + 1}" if level + 1 < levels else "float64"
        parts.append("=" * 80 + f"\nMSG: offload_msgs/Laugh{level}\n" + "".join(f"{inner} f{k}\n" for k in range(fan)))
    return "\n".join(parts)


def nested_definition(path, levels: int = 6, fan: int = 20, requests: int = 200) -> str:
    """Real outcomes (and decisions under the real definition) plus one decision under the nested one."""
    decision_msg, outcome_msg = installed_definitions()
    store = typestore_for(decision_msg, outcome_msg)
    md5 = store.generate_msgdef(DECISION_TYPE)[1]
    with BagWriter(str(path), store) as bag:
        hostile = bag.writer.add_connection("/hostile/decision", DECISION_TYPE, msgdef=nested_definition_text(
            levels, fan), md5sum=md5)
        time_ns = 1_700_000_000 * 10 ** 9
        for decision, outcome in make_requests(requests):
            bag.write(DECISION_TOPIC, DECISION_TYPE, decision, time_ns)
            bag.write(OUTCOME_TOPIC, OUTCOME_TYPE, outcome, time_ns + 1)
            time_ns += 100_000_000
        bag.writer.write(hostile, time_ns, b"\0" * 64)
    return str(path)


if __name__ == "__main__":
    import os
    out, n = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 200
    os.makedirs(out, exist_ok=True)
    for name, build in (("chunk_infos", chunk_info_amplified), ("connections", connection_amplified),
                        ("junk", junk_connections), ("nested", nested_definition)):
        if os.path.exists(os.path.join(out, name + ".bag")):
            os.remove(os.path.join(out, name + ".bag"))
        print(build(os.path.join(out, name + ".bag"), requests=n))
