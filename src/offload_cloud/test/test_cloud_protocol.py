"""Protocol round trips and rejections, the map cache, and the Python port of the map geometry."""
import hashlib
import json
import math

import numpy as np
import pytest

from offload_cloud import protocol
from offload_cloud.map_cache import ENTRY_OVERHEAD_BYTES, MapCache
from offload_cloud.protocol import Kind, PlanOptions, ProtocolError, Reply, Status

MAX_CELLS = 1 << 24


def test_plan_request_round_trip_with_and_without_map():
    grid = np.arange(12, dtype=np.int8).reshape(3, 4)
    digest = protocol.grid_hash(grid)
    options = PlanOptions(goal_tolerance_cells=2.5, lethal_threshold=70, unknown_is_obstacle=False,
                          stop_at_goal=True)
    for attached in (None, grid):
        frames = protocol.encode_plan(77, digest, (1, 2), (3, 0), options, attached)
        kind, request_id = protocol.decode_envelope(frames[0])
        assert (kind, request_id) == (Kind.PLAN, 77)
        request = protocol.decode_plan(request_id, [bytes(f) for f in frames[1:]], MAX_CELLS)
        assert request.map_hash == digest and request.start == (1, 2) and request.goal == (3, 0)
        assert request.options == options
        if attached is None:
            assert request.grid is None
        else:
            np.testing.assert_array_equal(request.grid, grid)


def test_request_on_a_cached_map_is_small():
    frames = protocol.encode_plan(1, b"\0" * 16, (1, 2), (3, 4))
    assert sum(len(f) for f in frames) <= 512
    assert len(frames) == 2


def test_reply_round_trip():
    path = np.array([[0, 0], [1, 1], [2, 1]], np.int32)
    reply = Reply(9, Status.OK, "", path, (2, 1), 42, 0.0125, 2.414)
    decoded = protocol.decode_reply([bytes(f) for f in protocol.encode_reply(reply)])
    assert decoded.request_id == 9 and decoded.status == Status.OK and decoded.goal == (2, 1)
    assert decoded.expansions == 42 and decoded.planning_time_s == 0.0125 and decoded.cost_cells == 2.414
    np.testing.assert_array_equal(decoded.path, path)
    empty = protocol.decode_reply([bytes(f) for f in protocol.encode_reply(Reply(3, Status.NO_PATH, "none"))])
    assert empty.path.shape == (0, 2) and empty.message == "none"


def test_upload_and_ping_round_trip():
    grid = np.zeros((5, 7), np.int8)
    frames = protocol.encode_upload(5, grid)
    assert protocol.decode_envelope(frames[0]) == (Kind.UPLOAD, 5)
    digest, decoded = protocol.decode_map(bytes(frames[1]), bytes(frames[2]), MAX_CELLS)
    assert digest == protocol.grid_hash(grid) and decoded.shape == (5, 7)
    assert protocol.decode_envelope(protocol.encode_ping(6)[0]) == (Kind.PING, 6)


def test_hash_depends_on_shape_and_content():
    grid = np.zeros((4, 6), np.int8)
    assert protocol.grid_hash(grid) != protocol.grid_hash(grid.reshape(6, 4))
    changed = grid.copy()
    changed[3, 5] = 1
    assert protocol.grid_hash(grid) != protocol.grid_hash(changed)


def test_other_version_is_told_which_version_the_server_speaks():
    frame = protocol.ENVELOPE.pack(protocol.MAGIC, protocol.VERSION + 1, Kind.PLAN, 3)
    with pytest.raises(ProtocolError) as error:
        protocol.decode_envelope(frame)
    assert error.value.status == Status.UNSUPPORTED_VERSION
    assert f"speaks version {protocol.VERSION}" in str(error.value)


@pytest.mark.parametrize("frame", [b"", b"OFP", b"XXXX" + bytes(10), protocol.envelope(Kind.PLAN, 1)[:-1],
                                   protocol.ENVELOPE.pack(protocol.MAGIC, protocol.VERSION, 99, 1)])
def test_bad_envelopes_are_rejected(frame):
    with pytest.raises(ProtocolError) as error:
        protocol.decode_envelope(frame)
    assert error.value.status == Status.BAD_REQUEST


def test_malformed_plans_are_rejected():
    grid = np.zeros((3, 3), np.int8)
    good = [bytes(f) for f in protocol.encode_plan(1, protocol.grid_hash(grid), (0, 0), (2, 2), grid=grid)][1:]
    bad_cases = [
        [],                                        # no body
        [good[0][:-1]],                            # truncated body
        good[:2],                                  # metadata without data
        [good[0], good[1], good[2][:-1]],          # data shorter than declared
        [good[0], b"{not json", good[2]],
        [good[0], b'{"dtype":"int8","height":3,"width":-3}', good[2]],
        [good[0], b'{"dtype":"float32","height":3,"width":3}', good[2]],
        [good[0], b'{"dtype":"int8","height":3.0,"width":3}', good[2]],
        [good[0], b"[" * 1000, good[2]],           # nesting that blows the JSON parser's recursion limit
        [good[0], b'{"a":' * 340 + b"1" + b"}" * 340, good[2]],
        [good[0], b'[{"dtype":"int8","height":3,"width":3}]', good[2]],   # not an object
        [good[0], b'"int8"', good[2]],
        [good[0], b"null", good[2]],
        [good[0], b'{"dtype":"int8","height":true,"width":3}', good[2]],
        [good[0], b'{"dtype":"int8","height":3,"width":1' + b"0" * 900 + b"}", good[2]],
        [protocol.encode_plan(1, b"\1" * 16, (0, 0), (2, 2))[1], good[1], good[2]],   # hash mismatch
        [protocol.PLAN_BODY.pack(b"\0" * 16, 0, 0, 1, 1, float("nan"), 50, 3)],
        [protocol.PLAN_BODY.pack(b"\0" * 16, 0, 0, 1, 1, -1.0, 50, 3)],
    ]
    for frames in bad_cases:
        with pytest.raises(ProtocolError) as error:
            protocol.decode_plan(1, frames, MAX_CELLS)
        assert error.value.status == Status.BAD_REQUEST, frames
    for metadata in (b"[" * 1000, b"{" * 1000, b'{"a":[' * 200):
        with pytest.raises(ProtocolError) as error:
            protocol.decode_map(metadata, good[2], MAX_CELLS)
        assert error.value.status == Status.BAD_REQUEST
    with pytest.raises(ProtocolError) as error:
        protocol.decode_plan(1, good, max_cells=8)
    assert error.value.status == Status.TOO_LARGE


def test_map_cache_is_lru_and_bounded():
    charge = 100 + ENTRY_OVERHEAD_BYTES
    cache = MapCache(capacity_bytes=2 * charge + 50)
    maps = {key: np.zeros(100, np.int8) for key in (b"a", b"b", b"c")}
    assert cache.put(b"a", maps[b"a"]) and cache.put(b"b", maps[b"b"])
    np.testing.assert_array_equal(cache.get(b"a"), maps[b"a"])   # a is now the most recent
    assert cache.put(b"c", maps[b"c"])            # evicts b
    assert b"b" not in cache and b"a" in cache and b"c" in cache
    assert cache.size_bytes == 2 * charge and cache.evictions == 1
    assert not cache.put(b"big", np.zeros(2 * charge + 51 - ENTRY_OVERHEAD_BYTES, np.int8))
    assert cache.get(b"b") is None and cache.misses == 1


def test_map_cache_counts_per_map_overhead_so_tiny_maps_cannot_grow_it_without_bound():
    """200,000 maps of 8 cells each fitted a cap that counted cells only: each map counts its overhead too."""
    cap = 1 << 20
    cache = MapCache(cap)
    source = bytearray(64)   # every map a view of one big received buffer, as the server gets them
    for k in range(5000):
        grid = np.frombuffer(bytes(source[:8]) + k.to_bytes(8, "little"), np.int8).reshape(2, 8)
        assert cache.put(k.to_bytes(16, "little"), grid)
    assert len(cache) <= cap // (16 + ENTRY_OVERHEAD_BYTES)
    assert cache.size_bytes <= cap and cache.evictions == 5000 - len(cache)
    kept = cache.get((4999).to_bytes(16, "little"))
    assert kept.base is None or kept.base.nbytes == kept.nbytes   # a compact copy, not a view of the message


# Golden bytes of protocol version 2, little endian, as the offload_cloud README documents the layout. A change
# to any wire constant (kinds, statuses, flags, version, field order or width) must fail here: a round
# trip through this same module cannot see it, and robots and servers of different builds would.
GOLDEN_GRID = np.array([[0, 100], [-1, 5]], np.int8)


def test_golden_bytes_of_every_message():
    assert bytes(protocol.encode_ping(7)[0]) == b"OFPL" + bytes([2, 1]) + (7).to_bytes(8, "little")
    plan = [bytes(f) for f in protocol.encode_plan(
        258, bytes(range(16)), (1, 2), (3, 4),
        PlanOptions(goal_tolerance_cells=1.5, lethal_threshold=60, unknown_is_obstacle=False, stop_at_goal=True))]
    assert plan == [b"OFPL\x02\x02" + (258).to_bytes(8, "little"),
                    bytes(range(16)) + bytes.fromhex("01000000" "02000000" "03000000" "04000000")
                    + bytes.fromhex("000000000000f83f")   # 1.5 as float64
                    + (60).to_bytes(2, "little") + bytes([2])]   # flags: stop_at_goal only
    upload = [bytes(f) for f in protocol.encode_upload(1, GOLDEN_GRID)]
    assert upload == [b"OFPL\x02\x03" + (1).to_bytes(8, "little"), b'{"dtype":"int8","height":2,"width":2}',
                      bytes([0, 100, 255, 5])]
    assert protocol.grid_hash(GOLDEN_GRID) == hashlib.blake2b(upload[1] + upload[2], digest_size=16).digest()
    reply = [bytes(f) for f in protocol.encode_reply(Reply(9, Status.GOAL_BLOCKED, "no", np.array(
        [[1, 2], [3, 4]], np.int32), (3, 4), 77, 0.25, 2.5))]
    assert reply == [b"OFPL\x02\x04" + (9).to_bytes(8, "little"),
                     bytes([6]) + bytes.fromhex("03000000" "04000000") + (77).to_bytes(8, "little")
                     + bytes.fromhex("000000000000d03f" "0000000000000440"),   # 0.25, 2.5
                     b"no", bytes.fromhex("01000000" "02000000" "03000000" "04000000")]
    assert bytes(protocol.encode_stats(5)[0]) == b"OFPL\x02\x05" + (5).to_bytes(8, "little")
    # And the other way: golden bytes decode to the values they stand for.
    decoded = protocol.decode_plan(258, plan[1:], MAX_CELLS)
    assert (decoded.map_hash, decoded.start, decoded.goal) == (bytes(range(16)), (1, 2), (3, 4))
    assert decoded.options == PlanOptions(goal_tolerance_cells=1.5, lethal_threshold=60, unknown_is_obstacle=False,
                                          stop_at_goal=True)
    back = protocol.decode_reply(reply)
    assert (back.request_id, back.status, back.goal, back.expansions, back.planning_time_s, back.cost_cells) == \
        (9, Status.GOAL_BLOCKED, (3, 4), 77, 0.25, 2.5)


def test_wire_codes_are_fixed():
    assert {k.name: int(k) for k in Kind} == {"PING": 1, "PLAN": 2, "UPLOAD": 3, "REPLY": 4, "STATS": 5, "ROWS": 6,
                                              "MODEL_QUERY": 7, "MODEL_FETCH": 8}
    assert (protocol.MAX_ROWS, protocol.MAX_ROWS_BYTES, protocol.MAX_DEFINITIONS_BYTES, protocol.MAX_MODEL_BYTES) == \
        (512, 4 << 20, 64 << 10, 16 << 20)
    assert {s.name: int(s) for s in protocol.LinkStatus} == {
        "MAP_UNKNOWN": 20, "BAD_REQUEST": 21, "UNSUPPORTED_VERSION": 22, "TOO_LARGE": 23, "BUSY": 24,
        "SERVER_ERROR": 25}
    assert (protocol.VERSION, protocol.FLAG_UNKNOWN_IS_OBSTACLE, protocol.FLAG_STOP_AT_GOAL) == (2, 1, 2)
    assert (protocol.MAX_MAP_SIDE, protocol.MAX_METADATA_BYTES, protocol.HASH_SIZE) == (100000, 1024, 16)


def _raises(status, call):
    with pytest.raises(ProtocolError) as error:
        call()
    assert error.value.status == status, error.value
    return error.value


def test_every_decoder_check_at_its_boundary():
    """Each validation branch of the decoders, on both sides of its limit."""
    assert protocol.is_planner_status(11) and protocol.is_planner_status(0) and not protocol.is_planner_status(20)
    for bad in (np.zeros((2, 2), np.uint8), np.zeros(4, np.int8), np.zeros((4, 4), np.int8)[:, ::2]):
        with pytest.raises(ValueError):
            protocol.grid_hash(bad)
    # Envelopes.
    good = protocol.envelope(Kind.PING, 77)
    assert protocol.decode_envelope(good) == (Kind.PING, 77) and protocol.request_id_of(good) == 77
    assert protocol.request_id_of(good[:-1]) == 0 and protocol.request_id_of(good + b"x") == 0
    _raises(Status.BAD_REQUEST, lambda: protocol.decode_envelope(b"OFPL"))
    _raises(Status.BAD_REQUEST, lambda: protocol.decode_envelope(b"OFPX" + good[4:]))
    _raises(Status.BAD_REQUEST, lambda: protocol.decode_envelope(good + b"\0"))
    _raises(Status.BAD_REQUEST, lambda: protocol.decode_envelope(good[:5] + bytes([9]) + good[6:]))
    # Maps: dtype, integer sides (a bool is not one), sides within 1..MAX_MAP_SIDE, cells within the cap.
    def meta(**fields):
        return json.dumps({"dtype": "int8", "width": 2, "height": 2, **fields}).encode()
    assert protocol.decode_map(meta(), bytes(4), 4)[1].shape == (2, 2)
    for fields in ({"dtype": "uint8"}, {"width": 2.0}, {"height": True}, {"width": 0}, {"height": -1},
                   {"width": protocol.MAX_MAP_SIDE + 1}):
        _raises(Status.BAD_REQUEST, lambda: protocol.decode_map(meta(**fields), bytes(4), 1 << 30))
    assert protocol.decode_map(meta(width=protocol.MAX_MAP_SIDE, height=1), bytes(protocol.MAX_MAP_SIDE),
                               1 << 30)[1].shape == (1, protocol.MAX_MAP_SIDE)
    _raises(Status.TOO_LARGE, lambda: protocol.decode_map(meta(), bytes(4), 3))
    _raises(Status.BAD_REQUEST, lambda: protocol.decode_map(meta(), bytes(3), 4))
    _raises(Status.BAD_REQUEST, lambda: protocol.decode_map(meta(), bytes(5), 4))
    # A plan whose uploaded map is not the one its hash names.
    grid = np.zeros((2, 2), np.int8)
    frames = protocol.encode_plan(1, protocol.grid_hash(grid), (0, 0), (1, 1), grid=grid)
    assert protocol.decode_plan(1, frames[1:], 16).grid is not None
    other = np.ones((2, 2), np.int8)
    frames = protocol.encode_plan(1, protocol.grid_hash(grid), (0, 0), (1, 1), grid=other)
    _raises(Status.BAD_REQUEST, lambda: protocol.decode_plan(1, frames[1:], 16))
    # Replies: exactly four frames, kind REPLY, body size, whole path pairs, a known status.
    reply = [bytes(f) for f in protocol.encode_reply(Reply(3, Status.OK, "", np.array([[1, 2]], np.int32), (1, 2)))]
    assert protocol.decode_reply(reply).path.tolist() == [[1, 2]]
    for frames in (reply[:3], reply + [b""], [protocol.envelope(Kind.PING, 3)] + reply[1:],
                   [protocol.envelope(Kind.STATS, 3)] + reply[1:], reply[:1] + [reply[1][:-1]] + reply[2:],
                   reply[:1] + [reply[1] + b"\0"] + reply[2:], reply[:3] + [reply[3][:-1]],
                   reply[:1] + [bytes([99]) + reply[1][1:]] + reply[2:]):
        _raises(Status.BAD_REQUEST, lambda: protocol.decode_reply(frames))


def test_stats_replies_are_checked():
    ok = protocol.decode_reply([bytes(f) for f in protocol.encode_stats_reply(4, {"requests": 3})])
    assert protocol.decode_stats(ok) == {"requests": 3}
    error = _raises(Status.BUSY, lambda: protocol.decode_stats(Reply(4, Status.BUSY, "later")))
    assert "later" in str(error)
    for message in ("[1, 2]", "not json", "[" * 5000, "{}" + " " * protocol.MAX_STATS_BYTES):
        with pytest.raises(ProtocolError):
            protocol.decode_stats(Reply(4, Status.OK, message))
    assert protocol.decode_stats(Reply(4, Status.OK, "{}" + " " * (protocol.MAX_STATS_BYTES - 2))) == {}
