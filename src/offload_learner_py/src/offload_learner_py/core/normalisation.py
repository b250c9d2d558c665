"""State normalisation: the network sees each feature of s_t centred and scaled, the fields the state schema
hints so (d_t, p_t) on a log scale first. It is fitted on warm-up states; moving it alone would silently change what
the learned weights mean, so a DQN that re-fits it later (normalisation_refit_interval) re-expresses its first
layer in the new one at the same time (core/dqn.py). It is saved with every checkpoint for the same reason,
with the state's field names and units, so a checkpoint of another state (fields added, removed or reordered, a
field whose meaning changed: p_t from cells/s to d_t/s) is refused rather than fed columns it never learned."""
from dataclasses import dataclass

import numpy as np

from offload_learner_py.core.state import STATE_FIELDS, STATE_SCHEMA, STATE_SIZE

# A constant feature (e.g. a steady round trip) has no spread; it is centred but not blown up.
MIN_SCALE = 1e-3
# Normalised d_t spans about four orders of magnitude (a few cells to the whole map) and is 0 for a
# goal next to the start; log(d + floor) spreads it evenly and stays finite at 0. The floor is the schema's.
INPUT_SIZE_LOG_FLOOR = STATE_SCHEMA["input_size"].log_floor
# The fields of a checkpoint saved before they were recorded with its normalisation.
PAPER_STATE_FIELDS = ("input_size", "cpu_availability", "round_trip_s")
# The units of a normalisation saved before they were recorded with it: p_t then counted cells settled per
# second, which jump points collapse; a model fitted on that is of another state (the other fields' units held).
UNITS_BEFORE_SAVED = {"local_plan_rate": "cells/s"}


class OtherStateError(ValueError):
    """A saved normalisation (of a checkpoint or a model file) of another state than this code's schema."""


def _rows(states) -> np.ndarray:
    """Raw states as N x STATE_SIZE float64 (one state: 1 x STATE_SIZE); another width is refused, never
    reshaped (a table of the paper's three fields must not be read as rows of four)."""
    states = np.asarray(states, dtype=np.float64)
    rows = states[None] if states.ndim == 1 else states
    if rows.ndim != 2 or rows.shape[1] != STATE_SIZE:
        raise ValueError(f"a raw state has {STATE_SIZE} fields ({', '.join(STATE_FIELDS)}), got an array of shape "
                         f"{states.shape}")
    return rows


def _named(fields, units) -> str:
    return ", ".join(f"{name} [{unit}]" for name, unit in zip(fields, units))


@dataclass(frozen=True)
class StateNormalisation:
    mean: tuple
    scale: tuple
    log_input_size: bool = True
    """log-scale the fields the state schema hints so (`log_floor`: the input size, the local planning rate)."""

    @classmethod
    def identity(cls, log_input_size: bool = True) -> "StateNormalisation":
        return cls(mean=(0.0,) * STATE_SIZE, scale=(1.0,) * STATE_SIZE, log_input_size=log_input_size)

    @classmethod
    def fit(cls, states: np.ndarray, log_input_size: bool = True) -> "StateNormalisation":
        states = _rows(states)
        if len(states) == 0:
            raise ValueError("cannot fit a normalisation on zero states")
        features = cls._features(states, log_input_size)
        scale = np.maximum(features.std(axis=0), MIN_SCALE)
        return cls(mean=tuple(float(v) for v in features.mean(axis=0)),
                   scale=tuple(float(v) for v in scale), log_input_size=log_input_size)

    @staticmethod
    def _features(states: np.ndarray, log_input_size: bool) -> np.ndarray:
        if log_input_size:
            return STATE_SCHEMA.log_scaled(states)
        return np.array(states, dtype=np.float64, copy=True)

    def apply(self, states: np.ndarray) -> np.ndarray:
        """Raw states (N x STATE_SIZE or STATE_SIZE, in schema order) to network inputs, float32."""
        states = np.asarray(states, dtype=np.float64)
        single = states.ndim == 1
        features = self._features(_rows(states), self.log_input_size)
        out = ((features - np.asarray(self.mean)) / np.asarray(self.scale)).astype(np.float32)
        return out[0] if single else out

    def to_dict(self) -> dict:
        return {"mean": list(self.mean), "scale": list(self.scale), "log_input_size": self.log_input_size,
                "fields": list(STATE_FIELDS), "units": list(STATE_SCHEMA.units)}

    @classmethod
    def from_dict(cls, values: dict) -> "StateNormalisation":
        fields = values.get("fields", PAPER_STATE_FIELDS)
        if not (isinstance(fields, (list, tuple)) and all(isinstance(name, str) for name in fields)):
            raise ValueError(f"normalisation fields must be a list of names, got {fields!r}")
        if tuple(fields) != STATE_FIELDS:
            raise OtherStateError(f"normalisation is of the state ({', '.join(map(str, fields))}), this code's state is "
                             f"({', '.join(STATE_FIELDS)})")
        units = values.get("units", [UNITS_BEFORE_SAVED.get(name, f.unit) for name, f in zip(fields, STATE_SCHEMA)])
        if not (isinstance(units, (list, tuple)) and tuple(units) == STATE_SCHEMA.units):
            raise OtherStateError(f"normalisation is of the state ({_named(fields, units)}), this code's state is "
                                  f"({_named(STATE_FIELDS, STATE_SCHEMA.units)})")
        mean, scale = tuple(float(v) for v in values["mean"]), tuple(float(v) for v in values["scale"])
        if len(mean) != STATE_SIZE or len(scale) != STATE_SIZE:
            raise ValueError(f"normalisation must have {STATE_SIZE} features, got {len(mean)}")
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(scale)) and min(scale) > 0):
            raise ValueError(f"normalisation must have finite means and positive finite scales, got mean {mean}, "
                             f"scale {scale}")
        return cls(mean=mean, scale=scale, log_input_size=bool(values["log_input_size"]))
