"""Per-side latency models: what a planner side would have taken for a state, with its uncertainty.

A deployed request runs one side, so eq. 10 lacks the other side's latency (bandit feedback). Each side's
log latency is modelled as a linear function of features of s_t = (d_t, u_t, b_t), fitted online by
recursive least squares with exponential forgetting (it follows a link or a workload that drifts) from
every measured latency of that side: both sides of a probe, the chosen side of a deployed request. Its
predictive distribution (normal in log space) gives

- the imputed latency of the side not run, exp(mean): the median, so under log-normal noise it is below the
  mean by a factor exp(var / 2). Eq. 10 is a ratio of latencies, so the imputed reward is biased towards the
  measured side being slower by that factor on noisy states; the bias is small where the model is confident
  and does not touch probes, whose rewards are both measured. Off-policy evaluation uses probes only.
- a deadline for the chosen side, a high quantile of its latency, which is when the hedge starts the other side.

Features: log d_t and its square (planning work grows as n ln n, measured against wall time on a shared
core), log u_t (time on a CPU budget scales with the share left) and u_t * log d_t, b_t and log b_t (the
link's share of the cloud's latency). Each side's model sees every feature, so one class serves both.
"""
import math
import threading
from dataclasses import dataclass
from statistics import NormalDist
from typing import Optional, Tuple

import numpy as np

from offload_learner_py.core.normalisation import INPUT_SIZE_LOG_FLOOR

N_FEATURES = 7
LATENCY_FLOOR_S = 1e-6


def features(input_size: float, cpu_availability: float, round_trip_s: float) -> np.ndarray:
    log_d = math.log(max(input_size, 0.0) + INPUT_SIZE_LOG_FLOOR)
    b = max(round_trip_s, 0.0)
    u = min(max(cpu_availability, 0.0), 1.0)
    return np.array((1.0, log_d, log_d * log_d, math.log(u + 0.05), u * log_d, b, math.log(b + 1e-3)),
                    dtype=np.float64)


@dataclass(frozen=True)
class LatencyModelConfig:
    forgetting: float = 0.995
    """weight of the past per observation (0.995: an effective memory of about 200 requests)."""
    prior_precision: float = 1e-2
    """ridge prior on the weights; small, so a few dozen samples dominate it."""
    min_samples: int = 20
    """observations before the model is trusted to impute or set a deadline."""

    def __post_init__(self):
        if not 0.5 <= self.forgetting <= 1.0:
            raise ValueError(f"forgetting must be in [0.5, 1], got {self.forgetting}")
        if not (self.prior_precision > 0 and math.isfinite(self.prior_precision)):
            raise ValueError(f"prior_precision must be positive, got {self.prior_precision}")
        if self.min_samples < 1:
            raise ValueError(f"min_samples must be >= 1, got {self.min_samples}")


class LatencyModel:
    """Online Bayesian linear regression of log latency on features(s). Thread-safe."""

    def __init__(self, config: LatencyModelConfig = LatencyModelConfig()):
        self.config = config
        self._lock = threading.Lock()
        self._weights = np.zeros(N_FEATURES)
        self._covariance = np.eye(N_FEATURES) / config.prior_precision   # P = (X'X + prior)^-1, forgetting applied
        self._residual_var = 1.0     # of log latency: running, then exponentially weighted, mean of squared errors
        self.samples = 0

    @property
    def ready(self) -> bool:
        return self.samples >= self.config.min_samples

    def observe(self, state: Tuple[float, float, float], latency_s: float) -> None:
        if not (math.isfinite(latency_s) and latency_s > 0):
            return
        x = features(*state)
        y = math.log(max(latency_s, LATENCY_FLOOR_S))
        lam = self.config.forgetting
        with self._lock:
            p_x = self._covariance @ x
            gain = p_x / (lam + x @ p_x)
            error = y - x @ self._weights
            self._weights = self._weights + gain * error
            self._covariance = (self._covariance - np.outer(gain, p_x)) / lam
            self._covariance = 0.5 * (self._covariance + self._covariance.T)   # keep it symmetric in floats
            # The error after the update: before it, the first errors measure the zero start, not the noise.
            residual = y - x @ self._weights
            self.samples += 1
            share = max(1.0 / self.samples, 1.0 - lam)
            self._residual_var = max((1 - share) * self._residual_var + share * residual * residual, 1e-6)

    def predict_log(self, state: Tuple[float, float, float]) -> Tuple[float, float]:
        """Mean and standard deviation of the log latency of the next request in `state`."""
        x = features(*state)
        with self._lock:
            mean = float(x @ self._weights)
            variance = self._residual_var * (1.0 + float(x @ self._covariance @ x))
        return mean, math.sqrt(max(variance, 0.0))

    def impute_s(self, state) -> Optional[float]:
        """Median latency for `state`, or None while the model is not ready."""
        if not self.ready:
            return None
        mean, _ = self.predict_log(state)
        return math.exp(min(mean, 50.0))

    def quantile_s(self, state, q: float) -> Optional[float]:
        """The q-quantile of the latency for `state`, or None while the model is not ready."""
        if not self.ready:
            return None
        mean, sd = self.predict_log(state)
        return math.exp(min(mean + NormalDist().inv_cdf(q) * sd, 50.0))
