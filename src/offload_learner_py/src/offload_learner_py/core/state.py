"""The state s_t = {d_t, u_t, b_t} of the paper (eq. 4): its one schema, the State built from it, and the
input size d_t of a path-planning request (eq. 11 and 12).

`STATE_SCHEMA` is the only list of the state's fields. Everything else derives from it: State (its
attributes, their order and its validation), STATE_SIZE (the Q-network's input width, the replay memory's
rows), the transition table's state columns and their checks (.npz and CSV), the OffloadDecision fields the
learner publishes and the bag reader decodes, the bounds a recorded decision must meet, normalisation (which
fields the network sees on a log scale) and the offline latency features built the same way, the LSTM's
feature choices and the summary's terciles. Adding a field takes one `StateField` here, the code that
measures it where the learner node builds its State, and the field in offload_msgs/OffloadDecision.msg."""
import math
from dataclasses import dataclass, make_dataclass
from typing import Callable, Iterator, Optional, Sequence, Tuple

import numpy as np

# A latency or a round trip of an hour is no planning request: a recorded one beyond it is damage.
MAX_LATENCY_S = 3600.0
# p_t, the local planning rate in d_t per second of local planning (online/plan_rate.py): MEASURED_RATES. d_t is
# at most ln(cells) (a corner-to-corner request: n is at most the map's cells), under 20 on any map the planner
# takes, and plans under 10 us are not timed, so a rate over 1e6 is a broken timer or a record of the old p_t
# (cells settled per second, 4e6-7e7 here): the bag reader skips it, never reads it as a rate. The log floor
# sits below any robot's real rate, so measured rates keep their log spacing and "not measured yet" (0, also the
# value of records from before the field) lands at log(floor): apart from every measured robot.
MAX_PLAN_RATE = 1e6
PLAN_RATE_LOG_FLOOR = 1e-1
_RESERVED = ("as_array", "as_tuple", "as_dict", "SCHEMA")   # State's own attributes


@dataclass(frozen=True)
class StateField:
    """One feature of s_t."""
    name: str
    """the State attribute, the transition-table column (.npz array, CSV header), the OffloadDecision field and
    the request-log column: one name everywhere."""
    symbol: str
    """the paper's symbol (d_t, u_t, b_t): labels in summaries and reports."""
    unit: str
    """unit of the value ("" for a ratio or a normalised number)."""
    meaning: str
    """what the value is and where it comes from."""
    low: float
    """physical bounds, inclusive: State and the transition table refuse a value outside [low, high] or not
    finite; high = inf bounds it above by finiteness alone."""
    high: float = math.inf
    recorded_max: Optional[float] = None
    """a recorded value above this is damage or hostility, not a measurement (one such row would own every
    figure): the bag reader skips its request and counts it. None: `high`."""
    log_floor: Optional[float] = None
    """normalisation hint: the network and the offline latency models see log(max(x, 0) + log_floor) (when the
    DQN config's log_input_size is on); None: x as it is."""
    missing: Optional[float] = None
    """the value of a decision recorded before this field existed (an older OffloadDecision definition in a
    bag); None: the field is required."""

    def __post_init__(self):
        if not self.name.isidentifier() or self.name.startswith("_") or self.name in _RESERVED:
            raise ValueError(f"state field name {self.name!r} is not a usable attribute name")
        if not (math.isfinite(self.low) and self.low < self.high):
            raise ValueError(f"state field {self.name}: bounds [{self.low}, {self.high}] are not an interval")
        if not (math.isfinite(self.recorded_high) and self.low < self.recorded_high <= self.high):
            raise ValueError(f"state field {self.name}: recorded_max {self.recorded_max} must be finite, above "
                             f"low and at most high")
        if self.log_floor is not None and not (self.log_floor > 0 and math.isfinite(self.log_floor)):
            raise ValueError(f"state field {self.name}: log_floor must be positive, got {self.log_floor}")
        if self.missing is not None and not self.low <= self.missing <= self.recorded_high:
            raise ValueError(f"state field {self.name}: missing value {self.missing} is outside its recorded bounds")

    @property
    def recorded_high(self) -> float:
        return self.high if self.recorded_max is None else self.recorded_max

    @property
    def bounds_text(self) -> str:
        """The bounds as the table's errors say them: ">= 0", "in [0, 1]"."""
        return f">= {self.low:g}" if math.isinf(self.high) else f"in [{self.low:g}, {self.high:g}]"

    @property
    def rule(self) -> str:
        """What a valid value is, finiteness included (a closed interval implies it)."""
        return f"finite and {self.bounds_text}" if math.isinf(self.high) else self.bounds_text

    def valid(self, value: float) -> bool:
        return self.low <= value <= self.high and math.isfinite(value)


class StateSchema:
    """The fields of s_t in order: the order of State's attributes, of a raw state's array and of the
    transition table's state columns."""

    def __init__(self, fields: Sequence[StateField]):
        self.fields: Tuple[StateField, ...] = tuple(fields)
        self.names: Tuple[str, ...] = tuple(f.name for f in self.fields)
        self.units: Tuple[str, ...] = tuple(f.unit for f in self.fields)   # part of what a saved model was fitted on
        if not self.fields or len(set(self.names)) != len(self.names):
            raise ValueError(f"a state schema needs distinct field names, got {self.names}")
        self._index = {name: i for i, name in enumerate(self.names)}
        self.log_columns: Tuple[Tuple[int, float], ...] = tuple(
            (i, f.log_floor) for i, f in enumerate(self.fields) if f.log_floor is not None)

    def __len__(self) -> int:
        return len(self.fields)

    def __iter__(self) -> Iterator[StateField]:
        return iter(self.fields)

    def __getitem__(self, name: str) -> StateField:
        return self.fields[self.index(name)]

    def index(self, name: str) -> int:
        """The column of a field in a raw state array."""
        try:
            return self._index[name]
        except KeyError:
            raise KeyError(f"{name!r} is not a state field; the state is {self.names}") from None

    def stack(self, column: Callable[[str], np.ndarray]) -> np.ndarray:
        """N x len(schema) float64 raw states from a column getter (a table's attribute, a log's column)."""
        return np.stack([np.asarray(column(name), dtype=np.float64) for name in self.names], axis=1)

    def log_scaled(self, states: np.ndarray) -> np.ndarray:
        """A float64 copy of N x len(schema) raw states with every log-hinted field as log(max(x, 0) + floor)."""
        out = np.array(states, dtype=np.float64, copy=True)
        for i, floor in self.log_columns:
            out[:, i] = np.log(np.maximum(out[:, i], 0.0) + floor)
        return out


STATE_SCHEMA = StateSchema((
    StateField("input_size", "d_t", "", "input size: n ln n (eq. 11-12) over the map's cell count (the paper's "
               "values ran from 0 to 5)", low=0.0, recorded_max=1e6, log_floor=1e-6),
    StateField("cpu_availability", "u_t", "", "CPU availability of the robot's own CPUs when the request "
               "arrives", low=0.0, high=1.0),
    StateField("round_trip_s", "b_t", "s", "round-trip latency to the cloud, last measured by the link",
               low=0.0, recorded_max=MAX_LATENCY_S),
    StateField("local_plan_rate", "p_t", "d_t/s", "the robot's own local planning rate: the input size d_t its "
               "local planner gets through per second of planning, whatever its search, an EWMA of its recent "
               "local plans (0: not measured yet)",
               low=0.0, recorded_max=MAX_PLAN_RATE, log_floor=PLAN_RATE_LOG_FLOOR, missing=0.0),
))
STATE_FIELDS = STATE_SCHEMA.names
STATE_SIZE = len(STATE_SCHEMA)


def node_count(distance_m: float, resolution_m: float) -> float:
    """Eq. 11: cells in the rectangle whose diagonal is the segment from start to goal, taken as a
    square of area x^2 / 2 (the largest rectangle with that diagonal)."""
    if resolution_m <= 0:
        raise ValueError(f"resolution_m must be positive, got {resolution_m}")
    if distance_m < 0:
        raise ValueError(f"distance_m must be non-negative, got {distance_m}")
    return (0.5 * distance_m * distance_m) / (resolution_m * resolution_m)


def raw_input_size(distance_m: float, resolution_m: float) -> float:
    """Eq. 12: d = n ln n with the natural log (the paper's worked example only matches ln).
    Below one node n ln n is negative, which means nothing for a cost, so it is clamped to 0."""
    n = node_count(distance_m, resolution_m)
    return n * math.log(n) if n > 1.0 else 0.0


def input_size(start_m: Sequence[float], goal_m: Sequence[float], resolution_m: float,
               map_cell_count: int) -> float:
    """Normalised input size d_t: n ln n divided by the map's cell count, as the paper normalised
    by the global map size (its values ran from 0 to 5)."""
    if map_cell_count <= 0:
        raise ValueError(f"map_cell_count must be positive, got {map_cell_count}")
    distance_m = math.hypot(goal_m[0] - start_m[0], goal_m[1] - start_m[1])
    return raw_input_size(distance_m, resolution_m) / map_cell_count


def input_size_from_cells(start_cell: Sequence[int], goal_cell: Sequence[int], resolution_m: float,
                          map_cell_count: int) -> float:
    """Same as input_size for grid cells (x, y): distances in cells times the resolution."""
    return input_size((start_cell[0] * resolution_m, start_cell[1] * resolution_m),
                      (goal_cell[0] * resolution_m, goal_cell[1] * resolution_m),
                      resolution_m, map_cell_count)


def state_class(schema: StateSchema, name: str = "State") -> type:
    """A frozen dataclass with one float attribute per schema field, in schema order, that refuses a value
    outside the field's physical bounds."""

    def __post_init__(self):
        for f in schema:
            value = getattr(self, f.name)
            if not f.valid(value):
                raise ValueError(f"{f.name} must be {f.rule}, got {value}")

    def as_tuple(self) -> tuple:
        return tuple(getattr(self, n) for n in schema.names)

    def as_array(self) -> np.ndarray:
        return np.array(self.as_tuple(), dtype=np.float64)

    def as_dict(self) -> dict:
        """Field name -> value: the state's part of an OffloadDecision."""
        return {n: getattr(self, n) for n in schema.names}

    doc = "One observation s_t (`{}` in that order):\n{}".format(", ".join(schema.names), "\n".join(
        f"    {f.name}: {f.symbol}, {f.meaning}{f' ({f.unit})' if f.unit else ''}; {f.rule}" for f in schema))
    return make_dataclass(name, [(f.name, float) for f in schema], frozen=True, namespace={
        "__post_init__": __post_init__, "as_tuple": as_tuple, "as_array": as_array, "as_dict": as_dict,
        "SCHEMA": schema, "__doc__": doc, "__module__": __name__})


State = state_class(STATE_SCHEMA)
