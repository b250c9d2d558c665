"""The planner options a plan request carries (protocol.py's PLAN body after the start and goal): the dataclass,
built from the core's options table, and its wire form. Decoding is cached: a robot sends the same few options
over and over, and building the frozen dataclass of 13 fields was a fifth of a worker's Python per request."""
import functools
import math
import struct
from dataclasses import field, make_dataclass

from offload_planner_cpp import options_table
from offload_planner_cpp._core import ALGORITHM_NAMES, validate_options

OPTIONS_HEAD = struct.Struct("<dhB")   # goal tolerance (cells), lethal threshold, flags
PLANNER_TAIL = struct.Struct("<B5d")   # only when a planner option differs from its default (protocol.py)
FLAG_UNKNOWN_IS_OBSTACLE = 1
FLAG_STOP_AT_GOAL = 2
FLAG_ANY_ANGLE = 4
# The core's algorithm names (planner_options.h): PLANNER_TAIL's algorithm code is the index, as in the core's enum.
ALGORITHMS = ALGORITHM_NAMES
_TAIL_NUMBERS = ("cost_factor", "neutral_cost", "robot_radius_cells", "inflation_radius_cells", "inflation_decay")

# The core's options that a request carries in cells: PlanOptions' fields, their order and defaults.
_CELL_OPTIONS = [row for row in options_table() if row["scope"] == "cells"]
_OPTION_TYPES = {"int": int, "bool": bool, "float": float, "algorithm": str}


class _PlanOptionsMethods:
    __slots__ = ()

    def planner_kwargs(self) -> dict:
        """The options as plan_raw's keyword arguments (a new dict each call)."""
        return dict(self._planner_kwargs)

    @functools.cached_property
    def _planner_kwargs(self) -> dict:
        # Once per options object (decode_options hands the same one out for the same bytes): the dict of 13
        # names cost a worker a few microseconds per request. The dataclass is frozen: it never goes stale.
        kwargs = {row["name"]: getattr(self, row["name"]) for row in _CELL_OPTIONS}
        kwargs["goal_tolerance"] = kwargs.pop("goal_tolerance_cells")
        return kwargs

    def _tail(self) -> tuple:
        return tuple(float(getattr(self, name)) for name in _TAIL_NUMBERS)


# Built from the core's table (planner_options.h): a new cell option of the core is a field here with no
# change to this file. A request without PLANNER_TAIL means the core's defaults, so changing one of the core's
# is a change of the protocol. Values are checked by the core when the server plans (INVALID_REQUEST).
PlanOptions = make_dataclass(
    "PlanOptions", [(row["name"], _OPTION_TYPES[row["type"]], field(default=row["default"])) for row in _CELL_OPTIONS],
    bases=(_PlanOptionsMethods,), frozen=True, namespace={"__module__": "offload_cloud.protocol", "__doc__":
        "The core's planner options in cells (the pybind11 module's keyword arguments), with the core's defaults."})
_DEFAULT_TAIL = PlanOptions()._tail()


def algorithm_code(name: str) -> int:
    """PLANNER_TAIL's code of an algorithm: its index in the core's names. ValueError, the core's, for a name
    that is no algorithm."""
    validate_options(algorithm=name)
    return ALGORITHMS.index(name)


def encode_options(options: PlanOptions) -> bytes:
    """OPTIONS_HEAD, then PLANNER_TAIL only when the algorithm or a number differs from the core's default (a
    request with default options is byte for byte what it was before the tail)."""
    flags = (FLAG_UNKNOWN_IS_OBSTACLE if options.unknown_is_obstacle else 0) | \
            (FLAG_STOP_AT_GOAL if options.stop_at_goal else 0) | (FLAG_ANY_ANGLE if options.any_angle else 0)
    encoded = OPTIONS_HEAD.pack(float(options.goal_tolerance_cells), int(options.lethal_threshold), flags)
    if options.algorithm != PlanOptions.algorithm or options._tail() != _DEFAULT_TAIL:
        encoded += PLANNER_TAIL.pack(algorithm_code(options.algorithm), *options._tail())
    return encoded


@functools.lru_cache(maxsize=64)
def decode_options(encoded: bytes) -> PlanOptions:
    """The options of OPTIONS_HEAD (+ PLANNER_TAIL); ValueError, not cached, for a negative or non-finite goal
    tolerance or an unknown algorithm code. The caller checks the length. Range checks are the core's, when the
    server plans (INVALID_REQUEST with its reason)."""
    tolerance, lethal, flags = OPTIONS_HEAD.unpack_from(encoded)
    if not math.isfinite(tolerance) or tolerance < 0:
        raise ValueError("goal tolerance must be a finite number >= 0 cells")
    tail = {}
    if len(encoded) > OPTIONS_HEAD.size:
        algorithm, *numbers = PLANNER_TAIL.unpack_from(encoded, OPTIONS_HEAD.size)
        if algorithm >= len(ALGORITHMS):
            raise ValueError(f"unknown algorithm code {algorithm}")
        tail = dict(zip(_TAIL_NUMBERS, numbers), algorithm=ALGORITHMS[algorithm])
    return PlanOptions(goal_tolerance_cells=tolerance, lethal_threshold=lethal,
                       unknown_is_obstacle=bool(flags & FLAG_UNKNOWN_IS_OBSTACLE),
                       stop_at_goal=bool(flags & FLAG_STOP_AT_GOAL), any_angle=bool(flags & FLAG_ANY_ANGLE), **tail)
