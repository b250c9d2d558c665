"""Round-trip variants: what a measured cloud plan would have cost at another round trip.

A cloud latency measured over the link is the round trip plus the cloud's own work (the request out, planning, the
path back): l_cloud = b + w. The work w does not depend on the round trip, and l_local does not depend on it at
all, so one request whose cloud side was measured also says what offloading it would have cost at any round trip
b' the robot has seen: b' + w, with l_local unchanged. The learner adds such variants of its measured requests
to the DQN's replay (DQNConfig.round_trip_variants), so the network learns that the round trip adds to the
cloud's latency wherever the robot's load and the request's size put it, not only in the conditions each round
trip happened to meet.

Variants go one way: to round trips above the request's own, never below. A variant then only ever makes the cloud
slower than a measurement showed, so it can teach the DQN to offload less on a worse link, never to offload more
than its measurements justify. Replayed from two learning runs' bags on the held-out load pulse (six seeds each,
scored on the same day's probes), one-way variants gave 44.6 and 49.4 ms, two-way ones 44.7 and 50.1, none 46.0
and 50.9.

Why (#33): on a held-out load pulse the learning run met a 70 ms round trip only while the robot was loaded
(where the cloud still won); later, idle, the same round trip came back and the DQN offloaded 13 of 15 requests
whose local plans were faster. Replayed from the learning run's bag, the same training with one variant a
request cut that phase's regret on the probes from 8-12 to 2-4 ms.

The state keeps the round trip as the link last measured it, a little before the request's own; a cloud latency
below its state's round trip gives a work of 0, never a negative one. Failed and timed-out cloud calls cost the
timeout, which is no round trip plus work: they get no variants."""
import collections
import threading
from typing import Tuple

import numpy as np

from offload_learner_py.core.state import STATE_SCHEMA

ROUND_TRIP = STATE_SCHEMA.index("round_trip_s")


def at_round_trips(states, cloud_s, round_trips) -> Tuple[np.ndarray, np.ndarray]:
    """N raw states with their round trip b replaced by `round_trips` (N of them, or one for all), and the cloud
    latencies b' + max(l_cloud - b, 0) they would have had."""
    states = np.array(states, dtype=np.float64, ndmin=2, copy=True)
    cloud_s = np.asarray(cloud_s, dtype=np.float64)
    round_trips = np.broadcast_to(np.asarray(round_trips, dtype=np.float64), cloud_s.shape)
    work = np.maximum(cloud_s - states[:, ROUND_TRIP], 0.0)
    states[:, ROUND_TRIP] = round_trips
    return states, round_trips + work


class RoundTripPool:
    """The round trips the robot's requests met, the last `capacity` of them, to draw variants' round trips from:
    the variants stay within the links the robot knows. Thread-safe."""

    def __init__(self, capacity: int, seed: int):
        if capacity < 1:
            raise ValueError(f"a round-trip pool needs a capacity of at least 1, got {capacity}")
        self._seen = collections.deque(maxlen=capacity)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._seen)

    def add(self, round_trip_s: float) -> None:
        with self._lock:
            self._seen.append(float(round_trip_s))

    def draw_above(self, round_trip_s: float, count: int) -> np.ndarray:
        """Up to `count` round trips drawn uniformly from those seen above `round_trip_s` (none if none is)."""
        with self._lock:
            if not self._seen or count < 1:
                return np.zeros(0)
            drawn = draw_above(np.sort(np.asarray(self._seen)), np.full(count, float(round_trip_s)), self._rng)
        return drawn[np.isfinite(drawn)]


def table_variants(states, local_s, cloud_s, count: int, rng: np.random.Generator):
    """Up to `count` variants of each of N measured requests (states, l_local, l_cloud), their round trips drawn
    from the N requests' own above the request's (training from bags, where the rows are the round trips the
    robots met); a request with no higher round trip among them gets none. Returns the variants' states, l_local
    and l_cloud."""
    states = np.asarray(states, dtype=np.float64)
    if count < 1 or len(states) == 0:
        return states[:0], np.zeros(0), np.zeros(0)
    rows = np.tile(np.arange(len(states)), count)
    ordered = np.sort(states[:, ROUND_TRIP])
    drawn = draw_above(ordered, states[rows, ROUND_TRIP], rng)
    keep = np.isfinite(drawn)
    rows, drawn = rows[keep], drawn[keep]
    moved_states, moved_cloud = at_round_trips(states[rows], np.asarray(cloud_s, dtype=np.float64)[rows], drawn)
    return moved_states, np.asarray(local_s, dtype=np.float64)[rows], moved_cloud


def draw_above(ordered: np.ndarray, round_trips, rng: np.random.Generator) -> np.ndarray:
    """For each round trip, one drawn uniformly from the sorted `ordered` strictly above it; nan where none is."""
    round_trips = np.atleast_1d(np.asarray(round_trips, dtype=np.float64))
    first = np.searchsorted(ordered, round_trips, side="right")
    above = len(ordered) - first
    pick = first + np.floor(rng.random(len(round_trips)) * np.maximum(above, 1)).astype(np.int64)
    return np.where(above > 0, ordered[np.minimum(pick, len(ordered) - 1)], np.nan)
