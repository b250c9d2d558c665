"""Versioned `.npz` files: named arrays plus a format tag and JSON metadata, never pickles. Shared by the
transition tables and the planning traces."""
import json
import zipfile
import zlib
from typing import Callable, Dict, Iterable, Mapping, Tuple

import numpy as np

# Bounds checked before anything is decompressed or allocated (crafted files: zip bombs, headers that
# claim more rows than the file holds, metadata nested deep enough to exhaust the stack). One member of
# 256 MiB is 32 million float64 rows, far beyond any table or trace this package writes.
MAX_MEMBER_BYTES = 256 * 2 ** 20
MAX_METADATA_DEPTH = 64
MAX_METADATA_BYTES = 4 * 2 ** 20  # the metadata and format members (numpy stores 4 bytes per character)

# What reading a missing, truncated, corrupt or foreign file can raise. The members of an .npz are
# read lazily, so a damaged compressed member only fails inside archive[name] (zlib.error), and a
# damaged array header fails in numpy's parser (ValueError).
_READ_ERRORS = (OSError, EOFError, zipfile.BadZipFile, zlib.error, json.JSONDecodeError, KeyError, ValueError,
                UnicodeDecodeError)


def save_versioned_npz(path: str, file_format: str, metadata: Mapping, arrays: Mapping[str, np.ndarray]) -> None:
    # Through a file object: given a path without ".npz", numpy would append the suffix and write
    # another file than the one the caller named.
    with open(path, "wb") as out:
        np.savez_compressed(out, format=np.array(file_format), metadata=np.array(json.dumps(dict(metadata))),
                            **arrays)


def load_versioned_npz(path: str, file_format: str, names: Iterable[str], what: str,
                       max_member_bytes: int = MAX_MEMBER_BYTES, optional: Iterable[str] = ()) -> Tuple[Dict, Dict]:
    """(arrays by name, metadata) of a file written by save_versioned_npz with `file_format`; of `names`, the
    `optional` ones may be absent (an older file) and are then left out of the arrays. A missing,
    corrupt, foreign or oversized file raises ValueError naming the file and saying why. Each member's
    uncompressed size (from the zip directory) must be at most max_member_bytes and agree with its .npy
    header before it is read."""
    names = tuple(names)
    try:
        with open(path, "rb") as source:
            magic = source.read(4)
    except OSError as error:
        raise ValueError(f"{path}: cannot read {what}: {error}") from error
    if magic != b"PK\x03\x04":  # every .npz is a zip archive
        raise ValueError(f"{path} is not a {what} ({file_format}): not an .npz (zip) archive")
    try:
        archive = np.load(path, allow_pickle=False)
    except _READ_ERRORS as error:
        raise ValueError(f"{path}: cannot read {what}: {error}") from error
    if not isinstance(archive, np.lib.npyio.NpzFile):  # a bare .npy array
        raise ValueError(f"{path} is not a {what} ({file_format}): it holds one bare array, not an .npz archive")
    with archive:
        if "format" in archive.files:
            _check_member(archive, "format", path, what, min(max_member_bytes, MAX_METADATA_BYTES))
        try:
            found = str(archive["format"]) if "format" in archive.files else None
        except _READ_ERRORS as error:
            raise ValueError(f"{path}: cannot read {what}: its format tag is unreadable: {error}") from error
        if found != file_format:
            raise ValueError(f"{path} is not a {what} ({file_format}), format is {found!r}")
        optional = set(optional)
        missing = [name for name in names + ("metadata",) if name not in archive.files and name not in optional]
        if missing:
            raise ValueError(f"{path} lacks {what} arrays {missing}")
        arrays = {}
        for name in tuple(n for n in names if n in archive.files) + ("metadata",):
            _check_member(archive, name, path, what,
                          min(max_member_bytes, MAX_METADATA_BYTES) if name == "metadata" else max_member_bytes)
            try:
                arrays[name] = archive[name]
            except _READ_ERRORS as error:
                raise ValueError(f"{path}: cannot read {what}: array {name!r} is corrupt: {error}") from error
    metadata_text = str(arrays.pop("metadata"))
    depth = _json_depth(metadata_text)
    if depth > MAX_METADATA_DEPTH:
        raise ValueError(f"{path}: cannot read {what}: its metadata nests deeper than {MAX_METADATA_DEPTH} levels "
                         f"({depth})")
    try:
        metadata = json.loads(metadata_text)
    except (json.JSONDecodeError, ValueError) as error:
        raise ValueError(f"{path}: cannot read {what}: its metadata is not JSON: {error}") from error
    if not isinstance(metadata, dict):
        raise ValueError(f"{path}: cannot read {what}: its metadata is a {type(metadata).__name__}, not an object")
    return arrays, metadata


def load_versioned(build: Callable, path: str, file_format: str, names: Iterable[str], what: str,
                   max_member_bytes: int = MAX_MEMBER_BYTES, optional: Iterable[str] = ()):
    """`build(**arrays, metadata=metadata)` from the file; its ValueError on invalid content is raised
    again naming the file."""
    arrays, metadata = load_versioned_npz(path, file_format, names, what, max_member_bytes, optional)
    try:
        return build(**arrays, metadata=metadata)
    except ValueError as error:
        raise ValueError(f"{path}: invalid {what}: {error}") from error


def _check_member(archive, name: str, path: str, what: str, max_member_bytes: int) -> None:
    """Refuse member `name` of an open NpzFile unless its declared uncompressed size is within the cap
    and its .npy header describes exactly the data that follows it. Reads only the header."""
    try:
        info = archive.zip.getinfo(name + ".npy")
    except KeyError:
        return  # an archive written without the suffix: numpy's own reader reports it
    if info.file_size > max_member_bytes:
        raise ValueError(f"{path}: cannot read {what}: array {name!r} would decompress to {info.file_size} bytes, "
                         f"more than the {max_member_bytes / 2 ** 20:g} MiB cap")
    try:
        with archive.zip.open(info) as member:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                shape, fortran_order, dtype = np.lib.format.read_array_header_1_0(member)
            elif version == (2, 0):
                shape, fortran_order, dtype = np.lib.format.read_array_header_2_0(member)
            else:
                raise ValueError(f".npy format version {version} is not supported")
            header_bytes = member.tell()
    except _READ_ERRORS as error:
        raise ValueError(f"{path}: cannot read {what}: array {name!r} is corrupt: {error}") from error
    if dtype.hasobject:
        raise ValueError(f"{path}: cannot read {what}: array {name!r} holds Python objects")
    data_bytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if header_bytes + data_bytes != info.file_size:
        raise ValueError(f"{path}: cannot read {what}: array {name!r} has shape {tuple(shape)} of {dtype}, "
                         f"{data_bytes} bytes of data, but its member holds {info.file_size - header_bytes}")


def _json_depth(text: str) -> int:
    """Deepest nesting of [ and { in JSON text, brackets inside strings excluded. Iterative, so a
    crafted document cannot exhaust the stack the way json.loads does."""
    depth = deepest = 0
    in_string = escaped = False
    for char in text:
        if in_string:
            if escaped:
                escaped = False
            elif char == "\\":
                escaped = True
            elif char == '"':
                in_string = False
        elif char == '"':
            in_string = True
        elif char in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in "]}":
            depth -= 1
    return deepest


class VersionedNpz:
    """save_npz / load_npz for a dataclass of named arrays with `metadata`: the class names its file format,
    its arrays and what it is called in errors."""
    NPZ_FORMAT = ""
    NPZ_ARRAYS: tuple = ()
    NPZ_OPTIONAL: tuple = ()
    """arrays an older file may lack (the class fills them in)."""
    NPZ_WHAT = ""

    def save_npz(self, path: str) -> None:
        save_versioned_npz(path, self.NPZ_FORMAT, self.metadata, {name: getattr(self, name) for name in self.NPZ_ARRAYS})

    @classmethod
    def load_npz(cls, path: str, max_member_bytes: int = MAX_MEMBER_BYTES):
        """The object in an .npz written by save_npz. Any unreadable, foreign, invalid or oversized file (an
        array over max_member_bytes uncompressed) raises ValueError naming the file."""
        return load_versioned(cls, path, cls.NPZ_FORMAT, cls.NPZ_ARRAYS, cls.NPZ_WHAT, max_member_bytes,
                              cls.NPZ_OPTIONAL)
