"""A bad model pushed to the fleet on purpose (`make bench-fleet-learning`, #30 item 8): a model file that always
picks one side, put in a running fleet learner's store and pinned for the whole fleet, as an operator's mistake
would be, at a set moment of a live run. The robot's guard (online/model_guard.py) must roll it back. No ROS."""
import threading
import time
from typing import Optional

import numpy as np

from offload_cloud.learner.store import ModelStore
from offload_learner_py import CLOUD
from offload_learner_py.core.model_file import load_model, model_bytes, model_version


def always_side_model(base: bytes, side: int = CLOUD) -> bytes:
    """`base`'s network and normalisation with its output layer made constant: Q(side) = 1, the other 0 for every
    state. A valid model file, so nothing but its decisions gives it away."""
    fast, normalisation = load_model(base)
    weights = [np.array(w, dtype=np.float64) for w in fast.weights]
    biases = [np.array(b, dtype=np.float64) for b in fast.biases]
    weights[-1][:] = 0.0
    biases[-1][:] = 0.0
    biases[-1][side] = 1.0
    return model_bytes(weights, biases, normalisation)


def push_bad_model(store_dir: str, side: int = CLOUD, base: Optional[bytes] = None, robot: str = "") -> str:
    """Puts an always-`side` model derived from the fleet's current version (or `base`) in the store and pins
    the fleet to it, and `robot` too: a robot whose guard rolled back an earlier version holds its own pin, which
    a fleet pin does not override (the bench of 2026-11-26 17:48 never reached its robot so); its version."""
    store = ModelStore(store_dir)
    if base is None:
        current = store.state()["current"]
        base = store.get(current) if current else None
        if base is None:
            raise ValueError(f"{store_dir}: no current version to derive a bad model from")
    data = always_side_model(base, side)
    store.put(data)
    store.pin(model_version(data), None)
    if robot:
        store.pin(model_version(data), robot)
    return model_version(data)


class DelayedPush:
    """push_bad_model at monotonic time `at` (a run's request epoch plus a delay), on a thread; `version` and
    `error` once it ran."""

    def __init__(self, store_dir: str, at: float, side: int = CLOUD, robot: str = ""):
        self.store_dir, self.at, self.side, self.robot = store_dir, at, side, robot
        self.version, self.error = "", ""
        self._thread = threading.Thread(target=self._run, daemon=True, name="bad-model-push")
        self._thread.start()

    def _run(self) -> None:
        time.sleep(max(0.0, self.at - time.monotonic()))
        try:
            self.version = push_bad_model(self.store_dir, self.side, robot=self.robot)
        except (OSError, ValueError) as error:
            self.error = str(error)

    def join(self, timeout: Optional[float] = None) -> None:
        self._thread.join(timeout)
