"""The 95 % intervals of off-policy evaluation: an estimate with its interval (Estimate), the interval of a
mean of per-request terms corrected for their skewness, and the combination of independent parts (strata)
into one estimate whose interval accounts for every part. No estimator lives here (off_policy_estimators)."""
import math
from dataclasses import dataclass
from typing import Iterable, Optional

import numpy as np

Z_95 = 1.959963984540054


@dataclass
class Estimate:
    value: float
    low: float
    high: float
    std_error: float
    n: int
    reason: str = ""        # why there is no estimate ("n/a"): no support, too few effective samples

    def contains(self, x: float) -> bool:
        return self.low <= x <= self.high

    @property
    def available(self) -> bool:
        return self.n > 0 and math.isfinite(self.value)

    def format(self, scale: float = 1.0, digits: int = 2) -> str:
        if not self.available:
            return "n/a"
        return (f"{self.value * scale:.{digits}f} [{self.low * scale:.{digits}f}, "
                f"{self.high * scale:.{digits}f}]")


def not_available(reason: str, n: int = 0) -> Estimate:
    """No estimate: its interval is the whole line, so `contains` is true of anything and a gate refuses."""
    return Estimate(math.nan, -math.inf, math.inf, math.nan, 0, reason)


def _mean_interval(terms: np.ndarray) -> Estimate:
    terms = np.asarray(terms, dtype=np.float64)
    n = len(terms)
    if n == 0:
        return Estimate(math.nan, math.nan, math.nan, math.nan, 0)
    value = float(terms.mean())
    std_error = float(terms.std(ddof=1) / math.sqrt(n)) if n > 1 else math.inf
    return Estimate(value, value - Z_95 * std_error, value + Z_95 * std_error, std_error, n)


def _hall_interval(value: float, std_error: float, a: float, degrees_of_freedom: float, n: int) -> Estimate:
    """Hall's transformation of the studentised estimate with a = the estimate's own skewness (the terms'
    skewness / sqrt(n) for a mean), on Student's t with the given degrees of freedom."""
    quantile = _t_quantile(degrees_of_freedom)
    if not math.isfinite(a) or abs(a) < 1e-12:
        return Estimate(value, value - quantile * std_error, value + quantile * std_error, std_error, n)
    inverse = lambda t: 3.0 / a * (float(np.cbrt(1.0 + a * (t - a / 6.0))) - 1.0)  # noqa: E731  g^-1 of Hall's g
    return Estimate(value, value - std_error * inverse(quantile), value - std_error * inverse(-quantile), std_error, n)


def _skew_corrected(value: float, std_error: float, skewness: float, n: int, kurtosis: float = 3.0) -> Estimate:
    """95 % interval of a mean from Hall's transformation of the studentised mean (P. Hall, "On the
    removal of skewness by transformation", JRSS B 54, 1992), which removes the first-order effect of
    the terms' skewness on the t statistic. Importance-weighted latencies are zero where the policies
    disagree and large on the few rows a rare logged action was taken with a heavy-tailed latency: when
    those rows happen to be few or cheap the mean is low and so is the sample variance, so the normal
    interval misses on the low side far more often than 2.5 %. The transformed interval extends upward
    by as much as the skewness says. With no skewness it is the symmetric t interval below.

    The quantile is Student's t with Satterthwaite's degrees of freedom for a variance estimated from terms
    of this kurtosis, 2 n / (kurtosis - 1) (n for normal terms): when a handful of rows carry the variance,
    the variance is itself known only from that handful, and the interval widens accordingly."""
    if not (math.isfinite(std_error) and math.isfinite(skewness)) or std_error == 0:
        return Estimate(value, value - Z_95 * std_error, value + Z_95 * std_error, std_error, n)
    df = 2.0 * n / (kurtosis - 1.0) if kurtosis > 1.0 else math.inf
    return _hall_interval(value, std_error, skewness / math.sqrt(n), df, n)


def _t_quantile(degrees_of_freedom: float) -> float:
    """The 97.5 % quantile of Student's t (Z_95 for infinite degrees of freedom)."""
    if not math.isfinite(degrees_of_freedom) or degrees_of_freedom > 1e6:
        return Z_95
    from scipy.stats import t
    return float(t.ppf(0.975, max(degrees_of_freedom, 1.0)))


def _shape(deviation: np.ndarray) -> tuple:
    """Skewness and kurtosis of terms from their deviations from the mean (second moment with n - 1)."""
    n = len(deviation)
    second = float(np.sum(deviation ** 2) / (n - 1))
    if not second > 0:
        return 0.0, 3.0
    return float(np.mean(deviation ** 3)) / second ** 1.5, float(np.mean(deviation ** 4)) / second ** 2


def wilson_interval(successes: int, n: int) -> Estimate:
    """95 % Wilson score interval of a proportion (honest near 0 and 1, unlike the normal one)."""
    if n == 0:
        return Estimate(math.nan, math.nan, math.nan, math.nan, 0)
    p = successes / n
    denominator = 1 + Z_95 ** 2 / n
    centre = (p + Z_95 ** 2 / (2 * n)) / denominator
    half = Z_95 * math.sqrt(p * (1 - p) / n + Z_95 ** 2 / (4 * n * n)) / denominator
    return Estimate(p, centre - half, centre + half, math.sqrt(p * (1 - p) / n), n)


def clipped(estimate: Estimate, low: float, high: float) -> Estimate:
    clip = lambda value: min(max(value, low), high) if math.isfinite(value) else value  # noqa: E731
    return Estimate(clip(estimate.value), clip(estimate.low), clip(estimate.high), estimate.std_error, estimate.n,
                    estimate.reason)


@dataclass
class Part:
    """One stratum's share of an estimate: share x the mean of its per-request terms, with the variance and
    third cumulant of that product and the degrees of freedom its variance is known with."""
    value: float
    variance: float
    third: float
    degrees_of_freedom: float
    n: int


def part(terms: np.ndarray, share: float) -> Optional[Part]:
    """The part of a stratum whose requests make up `share` of all, estimated by the mean of `terms` (one
    per sampled request, independent). None with fewer than two terms: no variance to go on."""
    terms = np.asarray(terms, dtype=np.float64)
    n = len(terms)
    if share == 0:
        return Part(0.0, 0.0, 0.0, math.inf, n)
    if n < 2:
        return None
    mean = float(terms.mean())
    deviation = terms - mean
    second = float(np.sum(deviation ** 2) / (n - 1))
    skewness, kurtosis = _shape(deviation)
    df = 2.0 * n / (kurtosis - 1.0) if kurtosis > 1.0 else math.inf
    # the mean's variance is second / n and its third cumulant skewness * second^1.5 / n^2
    return Part(share * mean, share ** 2 * second / n, share ** 3 * skewness * second ** 1.5 / n ** 2,
                min(df, n - 1.0), n)


def combine(parts: Iterable[Part]) -> Estimate:
    """The sum of independent parts: variances and third cumulants add; the degrees of freedom are
    Welch-Satterthwaite's, (sum v)^2 / sum v^2 / df; the interval is Hall's on the sum's skewness."""
    parts = list(parts)
    value = sum(p.value for p in parts)
    variance = sum(p.variance for p in parts)
    n = sum(p.n for p in parts)
    if variance <= 0:
        return Estimate(value, value, value, 0.0, n)
    spread = sum(p.variance ** 2 / p.degrees_of_freedom for p in parts if p.variance > 0)
    df = variance ** 2 / spread if spread > 0 else math.inf
    std_error = math.sqrt(variance)
    return _hall_interval(value, std_error, sum(p.third for p in parts) / std_error ** 3, df, n)
