"""The index of a rosbag v2.0 file, read and checked by the project itself (nothing of the learner's in it).

A bag's index is its bag header's counts, then connection records and chunk-info records at index_pos.
`rosbags`' Reader.open() grows with a hostile index before any check can apply (it re-reads a chunk's index
records once per chunk-info record naming that chunk, and sorts a connection's index once per connection
record sharing its id: a 10 MB bag reached 10 GiB). This reader never reads the per-chunk index records
(the learner reads whole chunks), reads each index record once with its size bounded by the file, and
refuses an index no `rosbag record` writes: two connection records with one id, two chunk-info records
naming one chunk, a chunk outside the bag or overlapping the next, a chunk-info record naming a connection
the index lacks. Refused (`IndexRefused`), the bag is scanned front to back as if it had no index, so its
real records are still read. Time and memory are linear in the index's size."""
import os
import struct
from typing import Callable, Dict, List, NamedTuple

from offload_learner_py.data.bag_format import Connection, _connection_from, _header_fields, _op

MAX_HEADER_BYTES = 1 << 16          # a record header (a chunk's, a connection's) holds a few short fields
MAX_CONNECTION_DATA_BYTES = 1 << 22  # a connection's type, md5 and full message definition
MIN_RECORD_BYTES = 8                # header length + data length


class IndexRefused(ValueError):
    """No usable index (none, cut off, damaged or absurd): read the bag front to back instead."""


class ChunkRef(NamedTuple):
    pos: int                 # the chunk record's offset in the file
    data_pos: int
    data_size: int
    compression: str
    fields: Dict[str, bytes]  # the chunk record's header (its declared uncompressed size)


class BagIndex(NamedTuple):
    connections: Dict[int, Connection]   # by id; the definition kept only for connections `keep` wants
    msgcounts: Dict[int, int]            # messages per connection id, from the chunk-info records
    chunks: List[ChunkRef]               # chunks holding a wanted connection, in file order


def _read_record(source, at: int, end: int, what: str):
    """(header fields, data offset, data size) of the record at `at`, which must end by `end`."""
    source.seek(at)
    prefix = source.read(4)
    if len(prefix) < 4:
        raise IndexRefused(f"{what} at offset {at} is cut off")
    (header_size,) = struct.unpack("<I", prefix)
    if header_size > MAX_HEADER_BYTES or at + 8 + header_size > end:
        raise IndexRefused(f"{what} at offset {at} has a {header_size}-byte header")
    header = source.read(header_size)
    size_bytes = source.read(4)
    if len(header) < header_size or len(size_bytes) < 4:
        raise IndexRefused(f"{what} at offset {at} is cut off")
    (data_size,) = struct.unpack("<I", size_bytes)
    data_pos = at + 8 + header_size
    if data_pos + data_size > end:
        raise IndexRefused(f"{what} at offset {at} runs past offset {end}")
    try:
        return _header_fields(header), data_pos, data_size
    except ValueError as error:
        raise IndexRefused(f"{what} at offset {at}: {error}") from None


def _uint(fields: Dict[str, bytes], name: str, size: int, what: str) -> int:
    value = fields.get(name, b"")
    if len(value) != size:
        raise IndexRefused(f"{what} without a {size * 8}-bit {name}")
    return int.from_bytes(value, "little")


def _expect(fields: Dict[str, bytes], op: int, what: str, at: int) -> None:
    try:
        found = _op(fields)
    except ValueError:
        found = None
    if found != op:
        raise IndexRefused(f"{what} expected at offset {at}, found a record of op {found}")


def read_index(path: str, keep: Callable[[str], bool]) -> BagIndex:
    """The bag's checked index; `keep(msgtype)` names the connections whose definitions and chunks are
    wanted. Raises IndexRefused when the bag has no index or one that cannot be trusted."""
    with open(path, "rb") as source:
        if source.readline() != b"#ROSBAG V2.0\n":
            raise ValueError("not a ROS 1 bag (version 2.0)")
        file_size = os.fstat(source.fileno()).st_size
        first = source.tell()
        fields, data_pos, data_size = _read_record(source, first, file_size, "the bag header")
        _expect(fields, 3, "the bag header", first)
        if fields.get("encryptor"):
            raise IndexRefused("an encrypted bag")
        index_pos = _uint(fields, "index_pos", 8, "a bag header")
        conn_count = _uint(fields, "conn_count", 4, "a bag header")
        chunk_count = _uint(fields, "chunk_count", 4, "a bag header")
        body = data_pos + data_size
        if index_pos == 0:
            raise IndexRefused("not indexed")
        if not body <= index_pos < file_size or \
                (conn_count + chunk_count) * MIN_RECORD_BYTES > file_size - index_pos:
            raise IndexRefused(f"index at offset {index_pos} with {conn_count} connections and {chunk_count} "
                               f"chunks does not fit a {file_size}-byte file")
        at = index_pos
        connections: Dict[int, Connection] = {}
        kept = set()
        for _ in range(conn_count):
            fields, data_pos, data_size = _read_record(source, at, file_size, "a connection record")
            _expect(fields, 7, "a connection record", at)
            if data_size > MAX_CONNECTION_DATA_BYTES:
                raise IndexRefused(f"a connection record of {data_size} bytes at offset {at}")
            try:
                connection = _connection_from(fields, source.read(data_size))
            except (KeyError, ValueError, struct.error):
                raise IndexRefused(f"a damaged connection record at offset {at}") from None
            if connection.id in connections:
                raise IndexRefused(f"two connection records with id {connection.id} (offset {at})")
            if keep(connection.msgtype):
                kept.add(connection.id)
            connections[connection.id] = connection if connection.id in kept else connection._replace(msgdef="")
            at = data_pos + data_size
        msgcounts = dict.fromkeys(connections, 0)
        wanted_at: Dict[int, bool] = {}
        for _ in range(chunk_count):
            fields, data_pos, data_size = _read_record(source, at, file_size, "a chunk-info record")
            _expect(fields, 6, "a chunk-info record", at)
            if _uint(fields, "ver", 4, "a chunk-info record") != 1:
                raise IndexRefused(f"a chunk-info record of an unknown version at offset {at}")
            chunk_pos = _uint(fields, "chunk_pos", 8, "a chunk-info record")
            count = _uint(fields, "count", 4, "a chunk-info record")
            if data_size != 8 * count:
                raise IndexRefused(f"a chunk-info record at offset {at} names {count} connections in {data_size} bytes")
            if chunk_pos in wanted_at:
                raise IndexRefused(f"two chunk-info records name the chunk at offset {chunk_pos}")
            if not body <= chunk_pos < index_pos:
                raise IndexRefused(f"a chunk-info record names offset {chunk_pos}, outside the bag's chunks")
            wanted = False
            for connection_id, messages in struct.iter_unpack("<II", source.read(data_size)):
                if connection_id not in msgcounts:
                    raise IndexRefused(f"the chunk at offset {chunk_pos} names connection {connection_id}, "
                                       "which the index lacks")
                msgcounts[connection_id] += messages
                wanted = wanted or connection_id in kept
            wanted_at[chunk_pos] = wanted
            at = data_pos + data_size
        return BagIndex(connections, msgcounts, _chunks(source, wanted_at, index_pos))


def _chunks(source, wanted_at: Dict[int, bool], index_pos: int) -> List[ChunkRef]:
    """The wanted chunks; every chunk named must be a chunk record ending before the next one starts."""
    chunks = []
    positions = sorted(wanted_at)
    for position, end in zip(positions, positions[1:] + [index_pos]):
        fields, data_pos, data_size = _read_record(source, position, end, "a chunk record")
        _expect(fields, 5, "a chunk record", position)
        if wanted_at[position]:
            compression = fields.get("compression", b"none").decode("ascii", "replace")
            chunks.append(ChunkRef(position, data_pos, data_size, compression, fields))
    return chunks
