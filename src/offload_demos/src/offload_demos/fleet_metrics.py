"""The fleet learning benchmark's figures, from request logs (#30 item 8). No ROS import.

Runs of one robot meet the same conditions request by request (the seeded goals, the RTT trace and the workload
schedule start together and the requests arrive open-loop, as in bench-policies), so request k of every run of a
robot is the same request. What is scored is the arm's decisions, like with like:

- the side table: per request k, both sides' own latencies (the planner's, and the cloud's round trip: the sides'
  latencies, not the delivered one) averaged over every run of the robot that measured both on request k (the
  oracle run on every request, the others on their probes). Every arm's decision
  on request k is scored with the table's latency of the side it decided, and the best decision on request k is
  the table's faster side. The delivered latency (the side plus the robot's routing: the learner's service,
  decision, thread and publishes, about 1 ms) and the run's own machine noise (local plans of the same requests
  averaged 2.8, 3.7 and 3.2 ms in three runs of 2026-11-26) are the same for every decision and left out, so
  "within 5 %" means the decisions are within 5 % of the best decisions; the live delivered mean is reported
  beside it, labelled as such;
- requests to within 5 %: the first k (k >= window) at which the mean decision latency of the requests of
  [k - window, k) with both sides in the table is at most (1 + tolerance) x the best decisions' mean over the same
  requests (at least `min_known` of them, else that window cannot be judged);
- the mean over the first 300 requests (fewer if the run is shorter: the count is reported), of the decisions and
  of the delivered latency;
- a bad model pushed on purpose: the requests decided by it until the robot's guard rolled it back, and what its
  decisions cost over the best decisions (summed and per request)."""
from typing import Dict, Optional, Sequence

import numpy as np

from offload_learner_py import CLOUD, LOCAL


def side_table(runs: Sequence[Dict[str, np.ndarray]], length: Optional[int] = None) -> np.ndarray:
    """(2, length): per request index, the two sides' latencies (row LOCAL, row CLOUD) averaged over the runs that
    measured both sides on it (the oracle run, probes of the others), NaN where none did. A run that measured one
    side only does not count: each pair is one moment of the machine, so neither side is scored under another
    run's load. Each run: local_s and cloud_s arrays (NaN where not measured), request index order."""
    length = max(len(run["local_s"]) for run in runs) if length is None else length
    total, count = np.zeros((2, length)), np.zeros(length)
    for run in runs:
        pair = np.stack([np.asarray(run["local_s"], dtype=np.float64)[:length],
                         np.asarray(run["cloud_s"], dtype=np.float64)[:length]])
        index = np.nonzero(np.isfinite(pair).all(axis=0))[0]
        total[:, index] += pair[:, index]
        count[index] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def decision_latency(actions: Sequence[int], table: np.ndarray) -> np.ndarray:
    """Per request, the table's latency of the side decided (NaN where the table lacks it or past its end)."""
    actions = np.asarray(actions, dtype=np.int64)
    scored = np.full(len(actions), np.nan)
    n = min(len(actions), table.shape[1])
    index = np.arange(n)
    valid = (actions[:n] == LOCAL) | (actions[:n] == CLOUD)
    scored[index[valid]] = table[actions[:n][valid], index[valid]]
    return scored


def best_latency(table: np.ndarray) -> np.ndarray:
    """Per request, the best decision's latency: the faster side where the table has both, else NaN."""
    both = np.isfinite(table).all(axis=0)
    return np.where(both, np.nanmin(np.where(np.isfinite(table), table, np.inf), axis=0), np.nan)


def requests_to_within(decided_s: Sequence[float], best_s: Sequence[float], tolerance: float = 0.05,
                       window: int = 50, min_known: int = 5) -> Optional[int]:
    """The first number of requests k at which the trailing window's decision mean is within `tolerance` of the
    best decisions' mean over the same requests (those with both known: at least min_known); None if never.
    Both arrays are side latencies from one table (decision_latency, best_latency), never a delivered one."""
    if not 0 <= tolerance < 1 or window < 1 or min_known < 1:
        raise ValueError(f"tolerance in [0, 1), window and min_known >= 1, got {tolerance}, {window}, {min_known}")
    decided = np.asarray(decided_s, dtype=np.float64)
    best = np.asarray(best_s, dtype=np.float64)
    if len(best) < len(decided):
        best = np.concatenate([best, np.full(len(decided) - len(best), np.nan)])
    known = np.isfinite(decided) & np.isfinite(best[:len(decided)])
    # prefix sums over the known requests: every window in one pass
    decided_sum = np.concatenate([[0.0], np.cumsum(np.where(known, decided, 0.0))])
    best_sum = np.concatenate([[0.0], np.cumsum(np.where(known, best[:len(decided)], 0.0))])
    count = np.concatenate([[0], np.cumsum(known)])
    for k in range(window, len(decided) + 1):
        n = count[k] - count[k - window]
        if n >= min_known and decided_sum[k] - decided_sum[k - window] <= (1.0 + tolerance) * (
                best_sum[k] - best_sum[k - window]):
            return k
    return None


def arm_figures(run: Dict[str, np.ndarray], table: np.ndarray, first: int = 300, tolerance: float = 0.05,
                window: int = 50) -> Dict:
    """One arm's figures against its robot's side table: requests to within, and its first requests' means of
    the decisions (table), of the best decisions and of what was delivered live."""
    decided = decision_latency(run["action"], table)
    best = best_latency(table)[:len(decided)]
    head = slice(0, first)
    known = np.isfinite(decided[head]) & np.isfinite(best[head])
    return {"requests": len(decided), "requests_to_within": requests_to_within(decided, best, tolerance, window),
            "first": {**first_mean(run["delivered_s"], first),
                      "decided_mean_s": float(np.mean(decided[head][known])) if known.any() else None,
                      "best_mean_s": float(np.mean(best[head][known])) if known.any() else None,
                      "scored": int(known.sum()),
                      "local_share": float(np.mean(np.asarray(run["action"])[head] == LOCAL))}}


def first_mean(delivered_s: Sequence[float], first: int = 300) -> Dict:
    delivered = np.asarray(delivered_s, dtype=np.float64)[:first]
    return {"mean_s": float(np.mean(delivered)) if len(delivered) else float("nan"), "requests": len(delivered)}


def bad_model_cost(versions: Sequence[str], bad_version: str, decided_s: Sequence[float],
                   best_s: Sequence[float], rolled_back_at: Optional[int] = None) -> Dict:
    """What a bad model cost a robot: the requests decided by `bad_version` (from its first to the rollback, or
    to the run's end when it never came), their decisions' latency less the best decisions' (decision_latency,
    best_latency: over those with both known), and whether and after how many of its requests the guard rolled
    it back."""
    versions = np.asarray(versions, dtype=object)
    decided = np.asarray(decided_s, dtype=np.float64)
    best = np.asarray(best_s, dtype=np.float64)
    under = np.nonzero(versions == bad_version)[0]
    if not len(under):
        return {"requests_under_bad": 0, "rolled_back": rolled_back_at is not None, "requests_to_rollback": None,
                "excess_s": 0.0, "excess_s_per_request": None, "scored": 0}
    first = int(under[0])
    end = len(versions) if rolled_back_at is None else int(rolled_back_at)
    chosen = under[under < end]
    inside = chosen[(chosen < len(best)) & (chosen < len(decided))]
    known = inside[np.isfinite(best[inside]) & np.isfinite(decided[inside])]
    excess = decided[known] - best[known]
    return {"requests_under_bad": int(len(chosen)), "rolled_back": rolled_back_at is not None,
            "requests_to_rollback": (int(rolled_back_at) - first) if rolled_back_at is not None else None,
            "excess_s": float(excess.sum()) if len(excess) else None,
            "excess_s_per_request": float(excess.mean()) if len(excess) else None,
            "decided_mean_s": float(decided[known].mean()) if len(known) else None, "scored": int(len(known))}


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
    return {"delivered_s": pick("outcome_delivered_s").astype(np.float64), "local_s": local_s, "cloud_s": cloud_s,
            "action": pick("action").astype(np.int64),     # the policy's decision (a probe runs both sides)
            "stamp_ns": pick("stamp_ns").astype(np.int64), "model_version": pick("model_version").astype(str)}
