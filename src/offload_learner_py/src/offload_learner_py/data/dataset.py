"""The one transition table of the project: a step per row with (t, the state s_t's fields, l_local,
l_cloud, action, action propensity, reward). The state columns are the state schema's fields in its order
(`core/state.py`: d, u, b, p). Saved as .npz (columns as arrays plus JSON metadata) and exportable to CSV.
Both latencies are in every row, as the paper measured both at every step, so any policy can be scored
offline against the oracle.

A table without a state column that the schema gives a value for older records (`missing`: p_t) takes that
value in every row: a table saved before the field existed (.npz or CSV), or one of data that never had it (the
paper's synthetic datasets), reads as the bag reader reads an older decision."""
import csv
import os
from typing import Dict, Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.state import STATE_FIELDS, STATE_SCHEMA
from offload_learner_py.data.npz_io import VersionedNpz

OUTCOME_COLUMNS = ("local_s", "cloud_s", "action", "action_propensity", "reward")
COLUMNS = ("t", *STATE_FIELDS, *OUTCOME_COLUMNS)
# State columns a table may lack (filled with the schema's value for older records).
OPTIONAL_COLUMNS = tuple(f.name for f in STATE_SCHEMA if f.missing is not None)
TABLE_FORMAT = "offload_learner_py.transitions/1"
_INTEGER_COLUMNS = ("t", "action")
# A CSV is parsed into Python objects (about 50 bytes per field): 64 MiB, about a million rows, stays
# within a few hundred MiB. Larger tables belong in .npz.
MAX_CSV_BYTES = 64 * 2 ** 20


class InvalidTableError(ValueError):
    """A column breaks a rule of the transition table; `row` is the first bad row (None if not one row)."""

    def __init__(self, message: str, column: str, row=None):
        super().__init__(message)
        self.column, self.row = column, row


def _column(name: str, values) -> np.ndarray:
    """One column as a 1-D int64 (t, action) or float64 array, every value finite (and whole for ints)."""
    try:
        array = np.asarray(values)
        if name in _INTEGER_COLUMNS and array.dtype.kind in "biu":
            array = array.astype(np.int64)
        else:
            array = array.astype(np.float64)
    except (TypeError, ValueError) as error:
        raise InvalidTableError(f"column {name} is not numeric: {error}", name) from error
    if array.ndim != 1:
        raise InvalidTableError(f"column {name} must be one-dimensional, got shape {array.shape}", name)
    if array.dtype == np.float64:
        bad = np.flatnonzero(~np.isfinite(array))
        if len(bad):
            raise InvalidTableError(f"{name} must be finite in every row; row {bad[0]} is {array[bad[0]]}",
                                    name, int(bad[0]))
        if name in _INTEGER_COLUMNS:
            bad = np.flatnonzero((array != np.round(array)) | (np.abs(array) >= 2.0 ** 53))
            if len(bad):
                raise InvalidTableError(f"{name} must hold whole numbers below 2**53; row {bad[0]} is "
                                        f"{array[bad[0]]}",
                                        name, int(bad[0]))
            array = array.astype(np.int64)
    return array


def _require(table: "TransitionTable", name: str, ok: np.ndarray, rule: str) -> None:
    bad = np.flatnonzero(~ok)
    if len(bad):
        value = getattr(table, name)[bad[0]]
        raise InvalidTableError(f"{name} must be {rule} in every row; row {bad[0]} is {value}", name, int(bad[0]))


class TransitionTable(VersionedNpz):
    """Columns by name (`table.local_s`, `table.cpu_availability`), one row per step: every name of COLUMNS
    given as a keyword, plus optional `metadata`."""
    NPZ_FORMAT, NPZ_ARRAYS, NPZ_OPTIONAL, NPZ_WHAT = TABLE_FORMAT, COLUMNS, OPTIONAL_COLUMNS, "transition table"

    def __init__(self, *, metadata: Optional[Dict] = None, **columns):
        missing = [n for n in COLUMNS if n not in columns and n not in OPTIONAL_COLUMNS]
        unknown = sorted(set(columns) - set(COLUMNS))
        if missing or unknown:
            raise TypeError(f"a transition table has the columns {', '.join(COLUMNS)}"
                            + (f"; missing {', '.join(missing)}" if missing else "")
                            + (f"; unknown {', '.join(unknown)}" if unknown else ""))
        rows = len(np.atleast_1d(columns["t"]))
        for name in COLUMNS:
            values = columns[name] if name in columns else np.full(rows, STATE_SCHEMA[name].missing)
            setattr(self, name, _column(name, values))
        self.metadata = {} if metadata is None else metadata
        lengths = {name: len(getattr(self, name)) for name in COLUMNS}
        if len(set(lengths.values())) != 1:
            raise ValueError(f"columns have different lengths: {lengths}")
        _require(self, "action", (self.action == LOCAL) | (self.action == CLOUD), f"{LOCAL} (local) or {CLOUD} (cloud)")
        for f in STATE_SCHEMA:
            values = getattr(self, f.name)
            _require(self, f.name, (values >= f.low) & (values <= f.high), f.bounds_text)
        _require(self, "local_s", self.local_s > 0, "> 0")
        _require(self, "cloud_s", self.cloud_s > 0, "> 0")
        _require(self, "action_propensity", (self.action_propensity > 0) & (self.action_propensity <= 1), "in (0, 1]")
        _require(self, "reward", (self.reward >= -1) & (self.reward <= 1), "in [-1, 1]")

    def __repr__(self) -> str:
        return f"TransitionTable({len(self)} rows, columns {', '.join(COLUMNS)})"

    def __len__(self) -> int:
        return len(self.t)

    @property
    def states(self) -> np.ndarray:
        """N x STATE_SIZE raw states, the schema's fields in order."""
        return STATE_SCHEMA.stack(lambda name: getattr(self, name))

    def state_columns(self) -> Dict[str, np.ndarray]:
        """The state columns by name, for a table of the same steps with other outcomes."""
        return {name: getattr(self, name) for name in STATE_FIELDS}

    def slice(self, start: int, stop: int) -> "TransitionTable":
        return TransitionTable(**{name: getattr(self, name)[start:stop] for name in COLUMNS},
                               metadata=dict(self.metadata))

    def to_csv(self, path: str) -> None:
        with open(path, "w", newline="") as out:
            writer = csv.writer(out)
            writer.writerow(COLUMNS)
            for row in zip(*(getattr(self, name) for name in COLUMNS)):
                writer.writerow([int(v) if isinstance(v, np.integer) else repr(float(v)) for v in row])

    @classmethod
    def from_csv(cls, path: str, max_bytes: int = MAX_CSV_BYTES) -> "TransitionTable":
        """The table in a CSV written by to_csv: the header must be COLUMNS (an older table's may lack
        OPTIONAL_COLUMNS) and every row must have one number per column (blank lines are skipped). Anything
        else, or a file over max_bytes, raises ValueError naming the file and the line."""
        lines = []
        try:
            size = os.path.getsize(path)
            if size > max_bytes:
                raise ValueError(f"{path}: {size} bytes, over the {max_bytes}-byte cap of a transition table CSV "
                                 f"(use .npz for larger tables)")
            with open(path, newline="") as source:
                reader = csv.reader(source)
                header = next(reader, None)
                if header is None:
                    raise ValueError(f"{path} is empty: a transition table CSV starts with the header "
                                     f"{','.join(COLUMNS)}")
                names = tuple(header)
                if names != tuple(n for n in COLUMNS if n in names or n not in OPTIONAL_COLUMNS):
                    raise ValueError(f"{path} line 1: header {','.join(header)} is not {','.join(COLUMNS)}")
                values = {name: [] for name in names}
                for row in reader:
                    if not row:
                        continue
                    if len(row) != len(names):
                        raise ValueError(f"{path} line {reader.line_num}: {len(row)} fields, expected "
                                         f"{len(names)} ({','.join(names)})")
                    for name, text in zip(names, row):
                        values[name].append(_parse_number(text, path, reader.line_num, name))
                    lines.append(reader.line_num)
        except OSError as error:
            raise ValueError(f"{path}: cannot read transition table: {error}") from error
        except UnicodeDecodeError as error:
            raise ValueError(f"{path}: not a text CSV file: {error}") from error
        except csv.Error as error:
            raise ValueError(f"{path} line {reader.line_num}: {error}") from error
        try:
            return cls(**values)
        except InvalidTableError as error:
            where = f" line {lines[error.row]}" if error.row is not None else ""
            raise ValueError(f"{path}{where}: invalid transition table: {error}") from error


def _parse_number(text: str, path: str, line: int, name: str):
    """An int where the text is one (t and action keep full precision), else a float."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"{path} line {line}: {name} {text!r} is not a number") from None
