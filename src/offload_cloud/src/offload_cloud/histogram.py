"""Bucketed counts of measured seconds, kept by one thread (the cloud server's broker) and read as a snapshot by
STATS and the Prometheus endpoint: an observation is a bisect and two additions, so the request path does not
pay for a metrics library's locks."""
import bisect
from typing import Sequence

# From a cached-map plan on a small map (well under a millisecond) to the longest a robot waits (seconds).
SECONDS_BOUNDS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


class Histogram:
    """Counts per bucket with Prometheus' meaning of a bound: an observation equal to a bound is in its bucket."""

    def __init__(self, bounds: Sequence[float] = SECONDS_BOUNDS):
        if list(bounds) != sorted(set(bounds)) or not bounds:
            raise ValueError(f"bucket bounds must be increasing and distinct, got {bounds}")
        self.bounds = tuple(float(bound) for bound in bounds)
        self.counts = [0] * (len(self.bounds) + 1)   # the last: above every bound
        self.sum = 0.0

    def observe(self, value: float) -> None:
        self.counts[bisect.bisect_left(self.bounds, value)] += 1
        self.sum += value

    def to_dict(self) -> dict:
        """JSON-ready: the bounds, the count in each bucket (not cumulative; one more than bounds), the sum."""
        return {"le": list(self.bounds), "counts": list(self.counts), "sum": self.sum}
