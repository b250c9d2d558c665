"""The fleet learning benchmark's figures, from request logs (#30 item 8). No ROS import.

Runs of one robot meet the same conditions request by request (the seeded goals, the RTT trace and the workload
schedule start together and the requests arrive open-loop, as in bench-policies), so request k of every run of a
robot is the same request: the oracle of request k is the faster side where both sides were measured on it (a
probe, or every request of an oracle run), pooled over that robot's runs.

- requests to within 5 %: the first k (k >= window) at which the mean delivered latency of requests
  [k - window, k) is at most (1 + tolerance) x the oracle's mean over the same requests (those of them with a
  known oracle: at least `min_oracle` of them, else that window cannot be judged);
- the mean over the first 300 requests (fewer if the run is shorter: the count is reported);
- a bad model pushed on purpose: the requests decided by it until the robot's guard rolled it back, and what it
  cost: the delivered latency of those requests less the oracle's (summed and per request)."""
from typing import Dict, Optional, Sequence

import numpy as np


def request_oracle(runs: Sequence[Dict[str, np.ndarray]], length: Optional[int] = None) -> np.ndarray:
    """Per request index, the faster side's latency where some run measured both sides on that request (NaN
    elsewhere); where several did, their mean. Each run: local_s, cloud_s and both_measured arrays, request
    index order."""
    length = max(len(run["local_s"]) for run in runs) if length is None else length
    total, count = np.zeros(length), np.zeros(length)
    for run in runs:
        both = np.asarray(run["both_measured"], dtype=bool)[:length]
        best = np.minimum(np.asarray(run["local_s"], dtype=np.float64), np.asarray(run["cloud_s"], dtype=np.float64))
        best = best[:length]
        index = np.nonzero(both & np.isfinite(best))[0]
        total[index] += best[index]
        count[index] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def requests_to_within(delivered_s: Sequence[float], oracle_s: Sequence[float], tolerance: float = 0.05,
                       window: int = 50, min_oracle: int = 5) -> Optional[int]:
    """The first number of requests k at which the trailing window's delivered mean is within `tolerance` of the
    oracle's mean over the window's requests of known oracle (at least min_oracle of them); None if never."""
    if not 0 <= tolerance < 1 or window < 1 or min_oracle < 1:
        raise ValueError(f"tolerance in [0, 1), window and min_oracle >= 1, got {tolerance}, {window}, {min_oracle}")
    delivered = np.asarray(delivered_s, dtype=np.float64)
    oracle = np.asarray(oracle_s, dtype=np.float64)
    if len(oracle) < len(delivered):
        oracle = np.concatenate([oracle, np.full(len(delivered) - len(oracle), np.nan)])
    known = np.isfinite(oracle)
    # prefix sums: every window in one pass
    delivered_sum = np.concatenate([[0.0], np.cumsum(np.nan_to_num(delivered))])
    oracle_sum = np.concatenate([[0.0], np.cumsum(np.where(known, oracle, 0.0))])
    oracle_count = np.concatenate([[0], np.cumsum(known[:len(delivered)])])
    for k in range(window, len(delivered) + 1):
        n_oracle = oracle_count[k] - oracle_count[k - window]
        if n_oracle < min_oracle:
            continue
        delivered_mean = (delivered_sum[k] - delivered_sum[k - window]) / window
        oracle_mean = (oracle_sum[k] - oracle_sum[k - window]) / n_oracle
        if delivered_mean <= (1.0 + tolerance) * oracle_mean:
            return k
    return None


def first_mean(delivered_s: Sequence[float], first: int = 300) -> Dict:
    delivered = np.asarray(delivered_s, dtype=np.float64)[:first]
    return {"mean_s": float(np.mean(delivered)) if len(delivered) else float("nan"), "requests": len(delivered)}


def bad_model_cost(versions: Sequence[str], bad_version: str, delivered_s: Sequence[float],
                   oracle_s: Sequence[float], rolled_back_at: Optional[int] = None) -> Dict:
    """What a bad model cost a robot: the requests decided by `bad_version` (from its first to the rollback, or
    to the run's end when it never came), their delivered latency less the oracle's (over those of known
    oracle), and whether and after how many of its requests the guard rolled it back."""
    versions = np.asarray(versions, dtype=object)
    delivered = np.asarray(delivered_s, dtype=np.float64)
    oracle = np.asarray(oracle_s, dtype=np.float64)
    under = np.nonzero(versions == bad_version)[0]
    if not len(under):
        return {"requests_under_bad": 0, "rolled_back": rolled_back_at is not None, "requests_to_rollback": None,
                "excess_s": 0.0, "excess_s_per_request": None, "oracle_known": 0}
    first = int(under[0])
    end = len(versions) if rolled_back_at is None else int(rolled_back_at)
    chosen = under[under < end]
    known = chosen[np.isfinite(oracle[chosen])] if len(oracle) else chosen[:0]
    excess = delivered[known] - oracle[known]
    return {"requests_under_bad": int(len(chosen)), "rolled_back": rolled_back_at is not None,
            "requests_to_rollback": (int(rolled_back_at) - first) if rolled_back_at is not None else None,
            "excess_s": float(excess.sum()) if len(excess) else None,
            "excess_s_per_request": float(excess.mean()) if len(excess) else None,
            "delivered_mean_s": float(delivered[chosen].mean()) if len(chosen) else None,
            "oracle_known": int(len(known))}


def rollback_index(versions: Sequence[str], bad_version: str) -> Optional[int]:
    """The request at which the robot stopped deciding with `bad_version` (its guard rolled it back: the first
    request after the bad version's first with another version), or None if it never did."""
    versions = np.asarray(versions, dtype=object)
    under = np.nonzero(versions == bad_version)[0]
    if not len(under):
        return None
    after = np.nonzero(versions[under[0]:] != bad_version)[0]
    return int(under[0] + after[0]) if len(after) else None


def run_arrays(log) -> Dict[str, np.ndarray]:
    """A request log's columns this module reads, answered requests only, in request order."""
    answered = np.asarray(log["has_outcome"], dtype=bool)
    pick = lambda name: np.asarray(log[name])[answered]  # noqa: E731
    local_s = np.where(pick("outcome_local_measured").astype(bool), pick("outcome_local_s").astype(np.float64), np.nan)
    cloud_s = np.where(pick("outcome_cloud_measured").astype(bool), pick("outcome_cloud_s").astype(np.float64), np.nan)
    # both sides' latencies, as the transition table takes them (its rows are the oracle everywhere else)
    both = pick("outcome_reward_valid").astype(bool)
    return {"delivered_s": pick("outcome_delivered_s").astype(np.float64), "local_s": local_s, "cloud_s": cloud_s,
            "both_measured": both & np.isfinite(local_s) & np.isfinite(cloud_s),
            "stamp_ns": pick("stamp_ns").astype(np.int64), "model_version": pick("model_version").astype(str)}
