"""The sceptic's fixed rule, chosen in hindsight: the best single input-size threshold on a run's probes.

The hedge run measures both sides of every request (its probes), so for any rule "offload when d_t > t" the mean
latency it would have had on that run is known exactly: cloud_s where d_t > t, local_s elsewhere. Every distinct
such rule is one cut between two neighbouring distinct d_t values (plus "always cloud" and "always local"), so the
grid of those cuts is exhaustive: the threshold it picks is the best any fixed d_t rule could be on that run. The
direction is the paper's and the node's `threshold` policy's (cloud above), so bench-policies can run the pick live.
This is analysis, not a policy a robot could run: it reads the latencies of requests already served. So is
`faster_sides`, the live oracle's actions: each request's faster side in the probes, replayed in a run of its own."""
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ThresholdSearch:
    threshold: float          # the pick: offload when d_t > threshold
    mean_s: float             # its mean latency on the probes
    grid: np.ndarray          # every candidate threshold, ascending
    means_s: np.ndarray       # the mean latency of each candidate on the probes
    cloud_share: float        # the pick's share of offloaded requests

    def as_dict(self) -> dict:
        return {"threshold": self.threshold, "hindsight_mean_s": self.mean_s, "cloud_share": self.cloud_share,
                "grid_size": int(len(self.grid))}


def threshold_grid(input_size) -> np.ndarray:
    """0 (offload everything with d_t > 0: always cloud), each midpoint between neighbouring distinct d_t values,
    and a threshold above the largest (always local)."""
    d = np.unique(np.asarray(input_size, dtype=np.float64))
    if not len(d):
        raise ValueError("no probes to choose a threshold on")
    return np.unique(np.concatenate([[0.0], (d[:-1] + d[1:]) / 2.0, [d[-1] + 1.0]]))


def rule_mean_s(threshold: float, input_size, local_s, cloud_s) -> float:
    """The mean latency of "offload when d_t > threshold" on requests whose both sides were measured."""
    d = np.asarray(input_size, dtype=np.float64)
    return float(np.mean(np.where(d > threshold, np.asarray(cloud_s, dtype=np.float64),
                                  np.asarray(local_s, dtype=np.float64))))


def best_threshold(input_size, local_s, cloud_s) -> ThresholdSearch:
    """The threshold of the grid with the lowest mean latency on the probes (the lowest such threshold on a tie)."""
    d = np.asarray(input_size, dtype=np.float64)
    local, cloud = np.asarray(local_s, dtype=np.float64), np.asarray(cloud_s, dtype=np.float64)
    if not (len(d) == len(local) == len(cloud)) or not np.all(np.isfinite(np.concatenate([d, local, cloud]))):
        raise ValueError("input_size, local_s and cloud_s must be finite and of one length")
    grid = threshold_grid(d)
    # Sorted by d, a threshold t offloads the requests from the first d > t on: total = sum(local before) +
    # sum(cloud from there), for every t at once.
    order = np.argsort(d, kind="stable")
    d_sorted = d[order]
    local_before = np.concatenate([[0.0], np.cumsum(local[order])])
    cloud_from = np.concatenate([np.cumsum(cloud[order][::-1])[::-1], [0.0]])
    first_above = np.searchsorted(d_sorted, grid, side="right")
    means = (local_before[first_above] + cloud_from[first_above]) / len(d)
    best = int(np.argmin(means))
    return ThresholdSearch(float(grid[best]), float(means[best]), grid, means,
                           float(np.mean(d > grid[best])))


def faster_sides(local_s, cloud_s) -> np.ndarray:
    """The oracle's action per request of a probe run, in request order: 1 (cloud) where the cloud side was strictly
    faster, else 0 (local); a side not measured (NaN: failed, not run) loses to one that was, and with neither
    measured the request plans locally. bench-policies replays these live (the learner's `replay` policy)."""
    local = np.asarray(local_s, dtype=np.float64)
    cloud = np.asarray(cloud_s, dtype=np.float64)
    if local.shape != cloud.shape or local.ndim != 1:
        raise ValueError("local_s and cloud_s must be 1-d and of one length")
    return np.where(np.isnan(cloud), 0, np.where(np.isnan(local), 1, (cloud < local).astype(np.int64))).astype(np.int64)


def gap_closed(threshold_mean_s, policy_mean_s, oracle_mean_s):
    """The share of the hindsight threshold's gap to the oracle a policy closes: 1 at the oracle, 0 at the
    threshold, negative when worse than it; None without a gap (the threshold is the oracle) or a figure."""
    if None in (threshold_mean_s, policy_mean_s, oracle_mean_s):
        return None
    gap = threshold_mean_s - oracle_mean_s
    if gap <= 1e-12:
        return None
    return (threshold_mean_s - policy_mean_s) / gap
