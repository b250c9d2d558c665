"""The rosbag v2.0 file format, without ROS and with nothing of the learner's in it (the learner's messages
are `bag_decoding` and `records`): an index-less front-to-back scan of a bag's records (what `rosbag
reindex` does, for a `.bag.active` a crash left behind) and the messages of an indexed bag's chunks (the
index read and checked by `bag_index`), each chunk decompressed with a bound taken from its own header and
a hard cap, so a decompression bomb costs at most MAX_CHUNK_BYTES. `report` is the bag's BagReport (notes,
damaged chunks, how it was read)."""
import bz2
import os
import struct
from typing import Dict, Iterator, List, NamedTuple, Optional, Tuple

# A chunk rosbag writes is 768 KiB by default; anything this large, compressed or not, is damage or
# hostility, not data. Decompression stops at the chunk's declared size and at this cap, so a bomb (a small
# chunk that inflates to gigabytes) costs at most this much memory, and the chunk is a counted skip.
MAX_CHUNK_BYTES = 64 * 1024 * 1024


class Connection(NamedTuple):
    id: int
    topic: str
    msgtype: str          # normalised: pkg/msg/Name
    msgdef: str
    md5sum: str


def _normalise_type(name: str) -> str:
    package, _, message = name.partition("/")
    return name if "/msg/" in name else f"{package}/msg/{message}"


def _header_fields(data: bytes) -> Dict[str, bytes]:
    """The name=value fields of a bag record header."""
    fields, position = {}, 0
    while position < len(data):
        if position + 4 > len(data):
            raise ValueError("header field length cut off")
        (size,) = struct.unpack_from("<I", data, position)
        position += 4
        if position + size > len(data):
            raise ValueError("header field longer than its header")
        name, separator, value = data[position:position + size].partition(b"=")
        if not separator:
            raise ValueError("header field without '='")
        fields[name.decode("ascii", "replace")] = value
        position += size
    return fields


def _op(fields: Dict[str, bytes]) -> int:
    value = fields.get("op", b"")
    if len(value) != 1:
        raise ValueError("record without an op code")
    return value[0]


def _decompressor(compression: str):
    """The one codec dispatch of chunk data: bz2 and lz4 streams with a bounded output."""
    if compression == "bz2":
        return bz2.BZ2Decompressor()
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.LZ4FrameDecompressor()
    raise ValueError(f"chunk compression {compression!r} is not supported")


def _decompress_partial(compression: str, data: bytes) -> bytes:
    """As much of a (possibly cut-off) chunk as can be decompressed, at most MAX_CHUNK_BYTES."""
    if compression == "none":
        return data
    try:
        return _decompressor(compression).decompress(data, max_length=MAX_CHUNK_BYTES)
    except (OSError, RuntimeError, EOFError, ValueError):
        return b""


def _connection_from(fields: Dict[str, bytes], data) -> Connection:
    details = _header_fields(bytes(data))
    return Connection(struct.unpack("<I", fields["conn"])[0], fields["topic"].decode("utf-8", "replace"),
                      _normalise_type(details["type"].decode("utf-8", "replace")),
                      details.get("message_definition", b"").decode("utf-8", "replace"),
                      details.get("md5sum", b"").decode("ascii", "replace"))


def scan_unindexed(path: str, report, why: str = "") -> Iterator[Tuple[Connection, int, memoryview]]:
    """Every complete message of a bag read front to back, ignoring its index: what `rosbag reindex`
    does, without ROS. A chunk cut off by a crash yields the records it completed."""
    with open(path, "rb") as source:
        if source.readline() != b"#ROSBAG V2.0\n":
            raise ValueError("not a ROS 1 bag (version 2.0)")
        offset = source.tell()
        connections: Dict[int, Connection] = {}
        complete_chunks, partial = 0, False
        while True:
            source.seek(offset)
            prefix = source.read(4)
            if len(prefix) < 4:
                break
            (header_size,) = struct.unpack("<I", prefix)
            if header_size > 1 << 20:
                partial = True   # garbage or a cut: nothing after can be trusted
                break
            header = source.read(header_size)
            size_bytes = source.read(4)
            if len(header) < header_size or len(size_bytes) < 4:
                partial = True
                break
            try:
                fields = _header_fields(header)
                op = _op(fields)
            except ValueError as error:
                report.note(f"unreadable record at offset {offset} ({error}): the rest of the file is skipped")
                partial = True
                break
            (data_size,) = struct.unpack("<I", size_bytes)
            data_start = offset + 8 + header_size
            remaining = os.fstat(source.fileno()).st_size - data_start
            if op == 5:   # chunk
                # The chunk rosbag was writing when it died still has 0 (or more than the file) as size.
                cut = data_size == 0 or data_size > remaining
                to_read = min(remaining, MAX_CHUNK_BYTES) if cut else data_size
                if to_read > MAX_CHUNK_BYTES:
                    raise ValueError(f"a chunk of {data_size} bytes at offset {offset} is larger than "
                                     f"{MAX_CHUNK_BYTES}")
                compression = fields.get("compression", b"none").decode("ascii", "replace")
                raw = source.read(to_read)
                if cut:
                    inner = _decompress_partial(compression, raw)
                    partial = True
                else:
                    try:
                        inner = decompress_chunk(compression, raw, fields)
                        complete_chunks += 1
                    except Exception as error:   # lz4, bz2 raise their own types on damaged data
                        report.damaged_chunks += 1
                        report.note(f"chunk at offset {offset} does not decompress: {type(error).__name__}: {error}")
                        inner = b""
                yield from _chunk_messages(inner, connections, connections)
                if cut:
                    break
                offset = data_start + data_size
                continue
            if data_size > remaining:
                partial = True
                break
            if op == 7:
                try:
                    connection = _connection_from(fields, source.read(data_size))
                    connections.setdefault(connection.id, connection)
                except (KeyError, ValueError, struct.error):
                    report.note(f"damaged connection record at offset {offset}")
            offset = data_start + data_size
    report.indexed = False
    report.recovered_note = (f"not indexed (a .bag.active left by a stopped recorder, or a cut-off, damaged or absurd "
                             f"index{why}): read record by record, {complete_chunks} complete chunks"
                             + (", and the records completed in a cut-off last chunk" if partial else "")
                             + f"; `rosbag reindex {path}` makes it an ordinary bag"
                             + (" but drops the records of the cut-off last chunk, which this reader keeps"
                                if partial else ""))


def decompress_chunk(compression: str, data: bytes, fields: Dict[str, bytes]) -> bytes:
    """A whole chunk, decompressed to at most its declared size (and MAX_CHUNK_BYTES): one that would
    inflate further is damage or a bomb, and raises."""
    size = struct.unpack("<I", fields["size"])[0] if len(fields.get("size", b"")) == 4 else None
    if size is not None and size > MAX_CHUNK_BYTES:
        raise ValueError(f"chunk declares {size} bytes uncompressed, more than {MAX_CHUNK_BYTES}")
    if compression == "none":
        return data
    bound = MAX_CHUNK_BYTES if size is None else size
    decompressor = _decompressor(compression)
    inner = decompressor.decompress(data, max_length=bound + 1)
    if len(inner) > bound:
        raise ValueError(f"chunk inflates past {'its declared ' if size is not None else ''}{bound} bytes")
    return inner


def indexed_messages(path: str, chunks: List, wanted: Dict[int, Connection],
                     report) -> Iterator[Tuple[Connection, int, memoryview]]:
    """Messages of the wanted connections in the chunks `bag_index.read_index` found holding them (a checked
    index: each chunk named once, inside the file), in file order. One decompressed chunk in memory at a time."""
    with open(path, "rb") as source:
        for chunk in chunks:
            if chunk.data_size > MAX_CHUNK_BYTES:
                report.damaged_chunks += 1
                report.note(f"chunk at offset {chunk.pos}: {chunk.data_size} bytes, over the "
                            f"{MAX_CHUNK_BYTES}-byte cap")
                continue
            try:
                # The chunk record's own header names its compression and uncompressed size.
                source.seek(chunk.data_pos)
                data = source.read(chunk.data_size)
                if len(data) != chunk.data_size:
                    raise ValueError(f"the chunk at offset {chunk.pos} is cut off")
                inner = decompress_chunk(chunk.compression, data, chunk.fields)
            except Exception as error:   # lz4, bz2 raise their own types on damaged data
                report.damaged_chunks += 1
                report.note(f"chunk at offset {chunk.pos} does not decompress: {type(error).__name__}: {error}")
                continue
            yield from _chunk_messages(inner, wanted, None)


def _chunk_messages(buffer: bytes, connections: Dict[int, Connection], found: Optional[Dict[int, Connection]]):
    """(connection, time ns, data) of each message record in a decompressed chunk. With `found`,
    connection records in the chunk are added to it (and looked up there)."""
    unpack, view, position, end = struct.unpack_from, memoryview(buffer), 0, len(buffer)
    table = found if found is not None else connections
    while position + 4 <= end:
        (header_size,) = unpack("<I", buffer, position)
        start = position + 4
        data_start = start + header_size + 4
        if data_start > end:
            return
        (data_size,) = unpack("<I", buffer, data_start - 4)
        if data_start + data_size > end:
            return
        position = data_start + data_size
        op = conn = time_ns = None
        field_at = start
        while field_at + 4 <= start + header_size:
            (size,) = unpack("<I", buffer, field_at)
            name_at = field_at + 4
            field_at = name_at + size
            if buffer[name_at:name_at + 3] == b"op=":
                op = buffer[name_at + 3]
            elif buffer[name_at:name_at + 5] == b"conn=" and name_at + 9 <= end:
                (conn,) = unpack("<I", buffer, name_at + 5)
            elif buffer[name_at:name_at + 5] == b"time=":
                if name_at + 13 > end:
                    return
                sec, nsec = unpack("<II", buffer, name_at + 5)
                time_ns = sec * 1_000_000_000 + nsec
        if op == 2:
            connection = table.get(conn)
            if connection is not None:
                yield connection, time_ns, view[data_start:position]
        elif op == 7 and found is not None:
            try:
                connection = _connection_from(_header_fields(buffer[start:start + header_size]),
                                              view[data_start:position])
            except (KeyError, ValueError, struct.error):
                continue   # a damaged connection record: its messages cannot be decoded, the rest can
            found[connection.id] = connection
