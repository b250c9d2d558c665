"""The variable reward of the paper (eq. 7-10) and the cloud timeout rule of section V.A."""
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL

DEFAULT_CLOUD_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class CostWeights:
    """alpha weighs local execution (eq. 7) and beta cloud execution (eq. 8); alpha + beta = 1.
    alpha > beta favours offloading (local time costs more), alpha < beta favours the robot."""
    alpha: float = 0.5
    beta: float = 0.5

    def __post_init__(self):
        for name, value in (("alpha", self.alpha), ("beta", self.beta)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        if not math.isclose(self.alpha + self.beta, 1.0, abs_tol=1e-9):
            raise ValueError(f"alpha + beta must equal 1, got {self.alpha} + {self.beta}")


def cloud_latency_s(measured_s: Optional[float], timeout_s: float = DEFAULT_CLOUD_TIMEOUT_S) -> float:
    """l_cloud as the learner sees it: a reply that never came (None) or came after the timeout
    costs the full timeout, which is what punishes offloading over a dead link."""
    if timeout_s <= 0:
        raise ValueError(f"timeout_s must be positive, got {timeout_s}")
    if measured_s is None or measured_s >= timeout_s:
        return timeout_s
    return measured_s


def reward(action: int, local_s: float, cloud_s: float, weights: CostWeights = CostWeights()) -> float:
    """Eq. 10: r = -(c_alg - c_local) / (c_local + c_cloud). Zero for local, positive when
    offloading was cheaper, negative when it was dearer; always in [-1, 1]."""
    if not (local_s > 0 and cloud_s > 0 and math.isfinite(local_s) and math.isfinite(cloud_s)):
        raise ValueError(f"latencies must be finite and positive, got local_s={local_s}, cloud_s={cloud_s}")
    if action not in (LOCAL, CLOUD):
        raise ValueError(f"action must be {LOCAL} (local) or {CLOUD} (cloud), got {action}")
    local_cost = weights.alpha * local_s
    cloud_cost = weights.beta * cloud_s
    chosen_cost = cloud_cost if action == CLOUD else local_cost
    return -(chosen_cost - local_cost) / (local_cost + cloud_cost)


def rewards(actions, local_s, cloud_s, weights: CostWeights = CostWeights()):
    """Eq. 10 over arrays of steps (same rules as reward())."""
    actions = np.asarray(actions)
    local_s = np.asarray(local_s, dtype=np.float64)
    cloud_s = np.asarray(cloud_s, dtype=np.float64)
    if not (np.all(local_s > 0) and np.all(cloud_s > 0) and np.all(np.isfinite(local_s))
            and np.all(np.isfinite(cloud_s))):
        raise ValueError("latencies must be finite and positive")
    if not np.all((actions == LOCAL) | (actions == CLOUD)):
        raise ValueError(f"actions must be {LOCAL} (local) or {CLOUD} (cloud)")
    local_cost = weights.alpha * local_s
    cloud_cost = weights.beta * cloud_s
    chosen_cost = np.where(actions == CLOUD, cloud_cost, local_cost)
    return -(chosen_cost - local_cost) / (local_cost + cloud_cost)
