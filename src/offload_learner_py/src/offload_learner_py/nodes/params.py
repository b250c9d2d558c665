"""Node parameters whose defaults are the fields of the config dataclasses: each default is stated once, in the
dataclass, and a node reads `~name` with that field's default as the fallback. No rospy here: a node passes
its getter (`lambda name, default: rospy.get_param("~" + name, default)`), and tests and the README check
read the same tables."""
from dataclasses import MISSING, fields
from typing import Any, Callable, Dict, Mapping, Tuple

Getter = Callable[[str, Any], Any]
# ROS parameter name -> (dataclass, field): the field's default is the parameter's.
Table = Mapping[str, Tuple[type, str]]


def field_default(cls: type, name: str) -> Any:
    """The default of dataclass `cls`'s field `name` (a fresh one for a default_factory)."""
    spec = next((spec for spec in fields(cls) if spec.name == name), None)
    if spec is None:
        raise KeyError(f"{cls.__name__} has no field {name!r}")
    if spec.default is not MISSING:
        return spec.default
    if spec.default_factory is not MISSING:
        return spec.default_factory()
    raise KeyError(f"{cls.__name__}.{name} has no default")


def coerce(value: Any, default: Any) -> Any:
    """A parameter's value as its default's type: a YAML or command-line `1` for a float field is 1.0, a
    number for a string field its text. Bools stay as given (`bool`), containers as given."""
    if isinstance(default, bool):
        return bool(value)
    if isinstance(default, int):
        return int(value)
    if isinstance(default, float):
        return float(value)
    if isinstance(default, str):
        return str(value)
    return value


def read(get: Getter, table: Table) -> Dict[str, Any]:
    """{parameter: value} for every parameter of the table, unset ones at their field's default."""
    values = {}
    for name, (cls, attr) in table.items():
        default = field_default(cls, attr)
        values[name] = coerce(get(name, default), default)
    return values


def for_class(values: Mapping[str, Any], table: Table, cls: type) -> Dict[str, Any]:
    """The read values of the parameters that fill `cls`'s fields, as its keyword arguments."""
    return {attr: values[name] for name, (owner, attr) in table.items() if owner is cls}


def defaults(table: Table) -> Dict[str, Any]:
    """{parameter: default} of the table (the README's parameter tables are checked against this)."""
    return {name: field_default(cls, attr) for name, (cls, attr) in table.items()}

