"""The one transition table of the project: a step per row with (t, d, u, b, l_local, l_cloud,
action, action propensity, reward). Saved as .npz (columns as arrays plus JSON metadata) and
exportable to CSV. Both latencies are in every row, as the paper measured both at every step, so
any policy can be scored offline against the oracle."""
import csv
from dataclasses import dataclass, field
from typing import Dict

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.npz_io import load_versioned_npz, save_versioned_npz

COLUMNS = ("t", "input_size", "cpu_availability", "round_trip_s", "local_s", "cloud_s", "action",
           "action_propensity", "reward")
TABLE_FORMAT = "offload_learner_py.transitions/1"
_INTEGER_COLUMNS = ("t", "action")


@dataclass
class TransitionTable:
    t: np.ndarray
    input_size: np.ndarray
    cpu_availability: np.ndarray
    round_trip_s: np.ndarray
    local_s: np.ndarray
    cloud_s: np.ndarray
    action: np.ndarray
    action_propensity: np.ndarray
    reward: np.ndarray
    metadata: Dict = field(default_factory=dict)

    def __post_init__(self):
        for name in COLUMNS:
            setattr(self, name, np.asarray(getattr(self, name),
                                           dtype=np.int64 if name in _INTEGER_COLUMNS else np.float64))
            if getattr(self, name).ndim != 1:
                raise ValueError(f"column {name} must be one-dimensional")
        lengths = {len(getattr(self, name)) for name in COLUMNS}
        if len(lengths) != 1:
            raise ValueError(f"columns have different lengths: {sorted(lengths)}")
        if not np.all((self.action == LOCAL) | (self.action == CLOUD)):
            raise ValueError(f"action must be {LOCAL} (local) or {CLOUD} (cloud) in every row")
        if np.any(self.local_s <= 0) or np.any(self.cloud_s <= 0):
            raise ValueError("local_s and cloud_s must be positive in every row")
        if np.any((self.action_propensity <= 0) | (self.action_propensity > 1)):
            raise ValueError("action_propensity must be in (0, 1] in every row")

    def __len__(self) -> int:
        return len(self.t)

    @property
    def states(self) -> np.ndarray:
        """N x 3 raw states (d, u, b)."""
        return np.stack([self.input_size, self.cpu_availability, self.round_trip_s], axis=1)

    def slice(self, start: int, stop: int) -> "TransitionTable":
        return TransitionTable(**{name: getattr(self, name)[start:stop] for name in COLUMNS},
                               metadata=dict(self.metadata))

    def save_npz(self, path: str) -> None:
        save_versioned_npz(path, TABLE_FORMAT, self.metadata, {name: getattr(self, name) for name in COLUMNS})

    @classmethod
    def load_npz(cls, path: str) -> "TransitionTable":
        arrays, metadata = load_versioned_npz(path, TABLE_FORMAT, COLUMNS, "transition table")
        return cls(**arrays, metadata=metadata)

    def to_csv(self, path: str) -> None:
        with open(path, "w", newline="") as out:
            writer = csv.writer(out)
            writer.writerow(COLUMNS)
            for row in zip(*(getattr(self, name) for name in COLUMNS)):
                writer.writerow([int(v) if isinstance(v, np.integer) else repr(float(v)) for v in row])

    @classmethod
    def from_csv(cls, path: str) -> "TransitionTable":
        with open(path, newline="") as source:
            reader = csv.reader(source)
            header = tuple(next(reader))
            if header != COLUMNS:
                raise ValueError(f"{path} header {header} is not {COLUMNS}")
            rows = [row for row in reader]
        columns = list(zip(*rows)) if rows else [()] * len(COLUMNS)
        return cls(**{name: np.array([float(v) for v in values]) for name, values in zip(COLUMNS, columns)})
