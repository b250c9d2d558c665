"""Decoding the learner's messages with the definition each bag stores, without ROS: flat messages (ours)
with precompiled structs, anything else with rosbags' deserializer; a field an older definition lacks
gets its default."""
import struct
from typing import Dict, Tuple

from offload_learner_py.data.bag_format import Connection


_PRIMITIVES = {"bool": "?", "int8": "b", "uint8": "B", "byte": "B", "char": "B", "int16": "h", "uint16": "H",
               "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q", "float32": "f", "float64": "d"}


def _layout(store, msgtype: str, prefix: str = ""):
    """The message flattened to primitive fields in wire order, [(name, struct code or "string")], or
    None when it holds arrays or anything else the fast path does not decode."""
    layout = []
    for name, (kind, spec) in store.fielddefs[msgtype][1]:
        if kind.name == "BASE" and spec[0] == "string":
            layout.append((prefix + name, "string"))
        elif kind.name == "BASE" and spec[0] in _PRIMITIVES:
            layout.append((prefix + name, _PRIMITIVES[spec[0]]))
        elif kind.name == "NAME":
            inner = _layout(store, spec, prefix + name + ".")
            if inner is None:
                return None
            layout += inner
        else:
            return None
    return layout


def _compile(layout):
    """Decoding steps for a flat layout: runs of fixed-size fields become one struct each."""
    steps, run, names = [], "", []
    for name, code in layout + [(None, "string")]:
        if code == "string":
            if run:
                steps.append((struct.Struct("<" + run), tuple(names)))
                run, names = "", []
            if name is not None:
                steps.append((None, name))
        else:
            run += code
            names.append(name)
    return steps


_LENGTH = struct.Struct("<I")
# Our messages flatten to a few dozen primitive fields. A definition nesting L levels of F fields flattens to
# F ** L ("billion laughs": 237 lines flattened to 1e8 fields and 10 GiB), so a definition's flattened size is
# counted, each type once, before any decoder or type store is built from it.
MAX_FLATTENED_FIELDS = 4096
_BUILTIN_SIZES = {"builtin_interfaces/msg/Time": 2, "builtin_interfaces/msg/Duration": 2}


def flattened_fields(types: Dict[str, tuple], root: str) -> int:
    """Primitive fields of `root` once its nested types (and fixed-size arrays) are flattened, from the parsed
    definition `types` (rosbags' name -> (constants, fields)). Raises ValueError above MAX_FLATTENED_FIELDS,
    on a type that contains itself, and on a variable-length array of a type without fields (decoding one
    element costs no bytes of the message, so a 4-byte length would make billions)."""
    sizes: Dict[str, int] = dict(_BUILTIN_SIZES)
    open_types = set()

    def size_of(name: str) -> int:
        if name in sizes:
            return sizes[name]
        if name in open_types:
            raise ValueError(f"the definition of {root}: {name} contains itself")
        if name not in types:
            return 1   # undefined: building the type store refuses it
        open_types.add(name)
        total = 0
        for _, (kind, spec) in types[name][1]:
            total += field_size(kind, spec)
            if total > MAX_FLATTENED_FIELDS:
                raise ValueError(f"the definition of {root} flattens to more than {MAX_FLATTENED_FIELDS} fields "
                                 f"(cap; {name} alone)")
        open_types.discard(name)
        sizes[name] = total
        return total

    def field_size(kind, spec) -> int:
        if kind.name == "BASE":
            return 1
        if kind.name == "NAME":
            return size_of(spec)
        (element_kind, element_spec), length = spec
        element = field_size(element_kind, element_spec)
        if kind.name == "SEQUENCE":
            if element == 0:
                raise ValueError(f"the definition of {root} has a variable-length array of a type without fields")
            return element
        return max(element, 1) * length   # an element without fields still costs a step to decode

    return size_of(root)


class Decoder:
    """Decodes one connection's messages with that bag's own definition and pulls out the fields the
    table needs, filling a default for a field an older definition lacks. Flat messages (ours) are
    decoded with precompiled structs; anything else goes through rosbags' deserializer."""

    def __init__(self, connection: Connection, defaults: Dict[str, object]):
        from rosbags.typesys import Stores, get_typestore, get_types_from_msg

        self.msgtype = connection.msgtype
        self.store = get_typestore(Stores.EMPTY)
        types = get_types_from_msg(connection.msgdef, connection.msgtype)
        flattened_fields(types, connection.msgtype)
        self.store.register(types)
        present = {name for name, _ in self.store.fielddefs[connection.msgtype][1]}
        missing = [name for name, default in defaults.items() if default is None and name not in present]
        if missing:
            raise ValueError(f"{connection.msgtype} on {connection.topic} lacks the fields {', '.join(missing)} "
                             f"(its definition in the bag: md5 {connection.md5sum})")
        self.names = [name for name in defaults if name in present]
        self.fills = {name: default for name, default in defaults.items() if name not in present}
        self.has_stamp = "header" in present
        layout = _layout(self.store, connection.msgtype)
        self.steps = _compile(layout) if layout is not None else None
        self.deserialize = self.store.deserialize_ros1

    def __call__(self, raw) -> Tuple[Dict[str, object], int]:
        if self.steps is None:
            return self._slow(raw)
        values, position = {}, 0
        for packer, names in self.steps:
            if packer is None:
                (size,) = _LENGTH.unpack_from(raw, position)
                position += 4
                if position + size > len(raw):
                    raise ValueError(f"string {names} runs past the end of the message")
                values[names] = bytes(raw[position:position + size]).decode("utf-8", "replace")
                position += size
            else:
                values.update(zip(names, packer.unpack_from(raw, position)))
                position += packer.size
        if position != len(raw):
            raise ValueError(f"{len(raw) - position} bytes left after the message")
        result = {name: values[name] for name in self.names}
        result.update(self.fills)
        stamp = values["header.stamp.sec"] * 1_000_000_000 + values["header.stamp.nanosec"] \
            if self.has_stamp and "header.stamp.sec" in values else 0
        return result, stamp

    def _slow(self, raw):
        message = self.deserialize(raw, self.msgtype)
        values = {name: getattr(message, name) for name in self.names}
        values.update(self.fills)
        stamp = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec if self.has_stamp else 0
        return values, stamp
