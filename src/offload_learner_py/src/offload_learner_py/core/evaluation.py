"""Scoring chosen actions against the oracle (the faster of the two measured latencies) and reading
the learned CPU threshold out of a Q-function."""
from typing import Callable, Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.data.dataset import TransitionTable


def faster_actions(local_s, cloud_s, tie_breaker=None) -> np.ndarray:
    """The faster action per step. On equal latencies both actions are optimal: the tie goes to
    tie_breaker's action (the evaluated policy's, so a tie is never scored as a mistake) or local."""
    local_s, cloud_s = np.asarray(local_s), np.asarray(cloud_s)
    ties = tie_breaker if tie_breaker is not None else np.full(local_s.shape, LOCAL)
    return np.where(cloud_s < local_s, CLOUD, np.where(cloud_s > local_s, LOCAL, ties))


def oracle_actions(table: TransitionTable, tie_breaker: Optional[np.ndarray] = None) -> np.ndarray:
    """The faster action of each table row (see faster_actions)."""
    return faster_actions(table.local_s, table.cloud_s, tie_breaker)


def chosen_latency_s(actions: np.ndarray, table: TransitionTable) -> np.ndarray:
    return np.where(np.asarray(actions) == CLOUD, table.cloud_s, table.local_s)


def accuracy(actions: np.ndarray, table: TransitionTable) -> float:
    """Share of steps where the chosen action was (one of) the fastest."""
    actions = np.asarray(actions)
    return float(np.mean(oracle_actions(table, actions) == actions)) if len(actions) else float("nan")


def confusion_matrix(actions: np.ndarray, table: TransitionTable) -> np.ndarray:
    """2 x 2 counts, rows the oracle's action (local, cloud), columns the chosen one."""
    actions = np.asarray(actions)
    oracle = oracle_actions(table, actions)
    matrix = np.zeros((2, 2), dtype=np.int64)
    np.add.at(matrix, (oracle, actions), 1)
    return matrix


def evaluate(actions: np.ndarray, table: TransitionTable) -> dict:
    """Accuracy, confusion matrix, latency of the chosen actions against always-local and
    always-cloud, savings in percent and regret against the oracle."""
    actions = np.asarray(actions)
    chosen = chosen_latency_s(actions, table)
    best = np.minimum(table.local_s, table.cloud_s)
    mean_chosen = float(chosen.mean())
    mean_local, mean_cloud = float(table.local_s.mean()), float(table.cloud_s.mean())
    return {
        "steps": int(len(actions)),
        "accuracy": accuracy(actions, table),
        "confusion_matrix": confusion_matrix(actions, table).tolist(),
        "cloud_share": float(np.mean(actions == CLOUD)),
        "mean_latency_s": mean_chosen,
        "cumulative_latency_s": float(chosen.sum()),
        "mean_latency_always_local_s": mean_local,
        "mean_latency_always_cloud_s": mean_cloud,
        "savings_vs_local_pct": 100.0 * (mean_local - mean_chosen) / mean_local,
        "savings_vs_cloud_pct": 100.0 * (mean_cloud - mean_chosen) / mean_cloud,
        "regret_s": float((chosen - best).sum()),
        "mean_regret_s": float((chosen - best).mean()),
    }


def learned_cpu_threshold(q_values: Callable[[np.ndarray], np.ndarray], states: np.ndarray,
                          step: float = 0.0005, input_size: Optional[float] = None) -> float:
    """The u at which the greedy policy switches from cloud (below) to local (above): Q(s, cloud) -
    Q(s, local) is scanned over the observed range of u with d (or `input_size`) and b at their
    medians, and its sign change is located by linear interpolation. When the difference crosses
    zero more than once, the crossing whose single-threshold rule best agrees with the scanned
    greedy decisions wins. NaN when the policy never switches in the observed range."""
    states = np.asarray(states, dtype=np.float64)
    d, u = STATE_SCHEMA.index("input_size"), STATE_SCHEMA.index("cpu_availability")
    low, high = float(states[:, u].min()), float(states[:, u].max())
    grid_u = np.arange(low, high + step / 2, step)
    probe = np.tile(np.median(states, axis=0), (len(grid_u), 1))
    if input_size is not None:
        probe[:, d] = input_size
    probe[:, u] = grid_u
    q = np.asarray(q_values(probe))
    difference = q[:, CLOUD] - q[:, LOCAL]
    prefers_cloud = difference > 0
    switches = np.nonzero(prefers_cloud[:-1] & ~prefers_cloud[1:])[0]
    if len(switches) == 0:
        return float("nan")
    best_threshold, best_agreement = float("nan"), -1.0
    for i in switches:
        fraction = difference[i] / (difference[i] - difference[i + 1])
        threshold = float(grid_u[i] + fraction * (grid_u[i + 1] - grid_u[i]))
        agreement = float(np.mean((grid_u < threshold) == prefers_cloud))
        if agreement > best_agreement:
            best_threshold, best_agreement = threshold, agreement
    return best_threshold
