"""The fleet learner's wire: golden bytes, round trips and every bound on both sides of its limit."""
import hashlib

import pytest

from offload_cloud import protocol, protocol_fleet
from offload_cloud.protocol import Kind, ProtocolError, Status

DEFS = {"offload_msgs/OffloadDecision": "uint64 request_id\n", "offload_msgs/OffloadOutcome": "uint64 request_id\n"}
MD5 = {"offload_msgs/OffloadDecision": "0" * 32, "offload_msgs/OffloadOutcome": "f" * 32}
V = "ab" * 32


def test_golden_bytes():
    frames = protocol_fleet.encode_rows(1, DEFS, MD5, [(b"\x01\x02", b"\x03")])
    assert frames[0] == b"OFPL\x02\x06\x01\x00\x00\x00\x00\x00\x00\x00"
    assert frames[1] == (b'{"definitions":{"offload_msgs/OffloadDecision":"uint64 request_id\\n","offload_msgs/OffloadOutcome"'
                         b':"uint64 request_id\\n"},"md5":{"offload_msgs/OffloadDecision":"00000000000000000000000000000000",'
                         b'"offload_msgs/OffloadOutcome":"ffffffffffffffffffffffffffffffff"},"rows":1}')
    assert frames[2:] == [b"\x01\x02", b"\x03"]
    assert protocol_fleet.encode_model_query(2, "", [V]) == [
        b"OFPL\x02\x07\x02\x00\x00\x00\x00\x00\x00\x00", b'{"current":"","rolled_back":["' + V.encode() + b'"]}']
    assert protocol_fleet.encode_model_fetch(3, V) == [b"OFPL\x02\x08\x03\x00\x00\x00\x00\x00\x00\x00",
                                                       b'{"version":"' + V.encode() + b'"}']
    reply = [bytes(f) for f in protocol.encode_blob_reply(4, b"model")]
    assert reply == [b"OFPL\x02\x04\x04\x00\x00\x00\x00\x00\x00\x00", protocol.REPLY_BODY.pack(0, 0, 0, 0, 0.0, 0.0),
                     b"", b"model"]
    assert [bytes(f) for f in protocol.encode_json_reply(5, {"accepted": 2, "refused": 1})][2] == \
        b'{"accepted":2,"refused":1}'
    assert (Kind.ROWS, Kind.MODEL_QUERY, Kind.MODEL_FETCH) == (6, 7, 8)


def test_round_trips():
    frames = protocol_fleet.encode_rows(9, DEFS, MD5, [(b"a", b"b"), (b"c", b"")])
    assert protocol.decode_envelope(frames[0]) == (Kind.ROWS, 9)
    assert protocol_fleet.decode_rows(frames[1:]) == (DEFS, MD5, [(b"a", b"b"), (b"c", b"")])
    query = protocol_fleet.encode_model_query(1, V, [V[::-1]])
    assert protocol_fleet.decode_model_request(Kind.MODEL_QUERY, query[1:]) == (V, [V[::-1]])
    assert protocol_fleet.decode_model_request(Kind.MODEL_FETCH, protocol_fleet.encode_model_fetch(1, V)[1:]) == (V, [])
    reply, data = protocol.decode_reply(protocol.encode_blob_reply(7, b"xyz"), blob=True)
    assert (reply.request_id, reply.status, data) == (7, Status.OK, b"xyz")
    with pytest.raises(ProtocolError):   # a plan reply's path must be whole int32 pairs; only blob replies are not
        protocol.decode_reply(protocol.encode_blob_reply(7, b"xyz"))
    assert protocol.decode_json_reply(protocol.decode_reply(protocol.encode_json_reply(1, {"version": V})), "q") == \
        {"version": V}


def test_model_bound_is_the_model_files():
    from offload_learner_py.core.model_file import MAX_MODEL_BYTES
    assert protocol.MAX_MODEL_BYTES == MAX_MODEL_BYTES


def _status(frames):
    with pytest.raises(ProtocolError) as error:
        protocol_fleet.decode_rows(frames)
    return error.value.status


def test_rows_bounds():
    row = (b"d", b"o")
    assert len(protocol_fleet.decode_rows(protocol_fleet.encode_rows(1, DEFS, MD5, [row] * 512)[1:])[2]) == 512
    assert _status(protocol_fleet.encode_rows(1, DEFS, MD5, [row] * 513)[1:]) == Status.TOO_LARGE
    half = protocol.MAX_ROWS_BYTES // 2
    assert _status(protocol_fleet.encode_rows(1, DEFS, MD5, [(b"x" * half, b"y" * half)])[1:]) == Status.TOO_LARGE
    fits = protocol.MAX_ROWS_BYTES // 2 - 1024
    assert protocol_fleet.decode_rows(protocol_fleet.encode_rows(1, DEFS, MD5, [(b"x" * fits, b"y" * fits)])[1:])
    big = {name: "#" * (protocol.MAX_DEFINITIONS_BYTES // 2 + 1) for name in DEFS}
    assert _status(protocol_fleet.encode_rows(1, big, MD5, [row])[1:]) == Status.TOO_LARGE
    ok = {name: "#" * (protocol.MAX_DEFINITIONS_BYTES // 2) for name in DEFS}
    assert protocol_fleet.decode_rows(protocol_fleet.encode_rows(1, ok, MD5, [row])[1:])
    escaped = {name: "\x01" * (protocol.MAX_DEFINITIONS_BYTES // 2) for name in DEFS}   # 6 bytes each in JSON
    assert _status(protocol_fleet.encode_rows(1, escaped, MD5, [row])[1:]) == Status.TOO_LARGE


@pytest.mark.parametrize("change", [
    lambda f: f[:-1],                                              # a row without its outcome
    lambda f: [f[0].replace(b'"rows":1', b'"rows":2')] + f[1:],    # count disagrees
    lambda f: [f[0].replace(b'"rows":1', b'"rows":true')] + f[1:],
    lambda f: [f[0].replace(b"0" * 32, b"0" * 31 + b"g")] + f[1:],  # md5 not hex
    lambda f: [f[0].replace(b"OffloadOutcome", b"LearnerConfig")] + f[1:],
    lambda f: [b"[" * 5000] + f[1:],
    lambda f: [b"\xff\xfe"] + f[1:],
    lambda f: [],
])
def test_malformed_rows_are_bad_requests(change):
    frames = protocol_fleet.encode_rows(1, DEFS, MD5, [(b"d", b"o")])[1:]
    assert _status(change(frames)) == Status.BAD_REQUEST


@pytest.mark.parametrize("kind, frames", [
    (Kind.MODEL_QUERY, [b'{"current":"abc","rolled_back":[]}']),
    (Kind.MODEL_QUERY, [b'{"current":"' + V.upper().encode() + b'"}']),
    (Kind.MODEL_QUERY, [b'{"current":"","rolled_back":["' + V.encode() + b'"' + b',"' + V.encode() + b'"' * 0 + b"]}"]),
    (Kind.MODEL_QUERY, [b'{"current":"","rolled_back":' + str([V] * 65).replace("'", '"').encode() + b"}"]),
    (Kind.MODEL_QUERY, [b'{"current":""}', b"extra"]),
    (Kind.MODEL_FETCH, [b'{"version":""}']),
    (Kind.MODEL_FETCH, [b'{"version":"' + V.encode() + b'",' + b'"x":"' + b"y" * 9000 + b'"}']),
])
def test_malformed_model_requests(kind, frames):
    with pytest.raises(ProtocolError) as error:
        protocol_fleet.decode_model_request(kind, frames)
    assert error.value.status == Status.BAD_REQUEST


def test_sixty_four_rolled_back_versions_are_accepted():
    versions = [hashlib.sha256(bytes([i])).hexdigest() for i in range(64)]
    frames = protocol_fleet.encode_model_query(1, "", versions)
    assert protocol_fleet.decode_model_request(Kind.MODEL_QUERY, frames[1:])[1] == versions
