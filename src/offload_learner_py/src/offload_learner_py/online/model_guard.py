"""The robot's rollback guard for a model version from the fleet learner (no ROS).

The learner gates a version by off-policy evaluation on rows it has; the robot checks it live. The guard keeps
the latency the policy delivered on the robot's last `requests` requests of each version it holds. A new version is
judged against the reference: the last version the guard kept that was no slower than the reference before it
(at first the version before the first one judged), over the reference's last `requests` requests; once the new
version has decided `requests` requests of its own the guard judges it, once:

    worse  when  mean_new - mean_ref > margin * mean_ref, one-sided at `confidence`:
                 t = (mean_new - mean_ref - margin * mean_ref) / sqrt(var_new / n_new + var_ref / n_ref)
                 > the Student t quantile `confidence` with Welch-Satterthwaite degrees of freedom.

The reference does not move with each version: a version kept but slower (by its mean) than the reference leaves
the reference where it was, so a model drifting in steps each within the margin of the one before (the
warehouse robot of the fleet bench of 2026-11-26: 91 % local against the oracle's 60 %, every step passed) is
rolled back once the steps add up beyond it, to the reference. A kept version no slower becomes the reference.

So a version is rolled back only when it is slower than the reference by more than the relative margin (5 %
by default) beyond noise (Welch's test at 95 %); a version no worse, or one whose difference the noise cannot
tell, is kept. With both samples of no spread the test is the margin alone. A version with too small a baseline
(fewer than `requests // 2` requests of the reference, as after a start with no model) is kept without a test:
there is nothing live to compare with; its first full window makes it the reference. Each version is judged once;
a rolled-back version is never loaded again (the fleet learner is told, fleet_link.py).

The two samples are the same robot at different moments: a load or a link that changed exactly at the swap is
counted against (or for) the new version, and the reference's window may be older than the version before's
(it refills whenever the reference decides again, as after a rollback). The margin and a window of 30 keep that from
deciding on a few slow requests; a real regression of a few percent needs more requests than the window to be seen.

What is compared is the latency the policy's choice cost: on a probe (both sides ran) the decided side's
latency (a cloud failure costs the timeout), else the delivered latency (waits included)."""
import math
import threading
from collections import deque
from dataclasses import dataclass
from typing import Dict, NamedTuple, Optional


@dataclass(frozen=True)
class GuardConfig:
    requests: int = 30
    """requests of a new version judged against the reference version's last as many; 0: no guard."""
    margin: float = 0.05
    """relative slowdown tolerated (of the reference's mean) before the test may roll back."""
    confidence: float = 0.95
    """one-sided confidence of Welch's test that the new version is worse beyond the margin."""

    def __post_init__(self):
        if self.requests < 0 or self.requests == 1:
            raise ValueError(f"~guard_requests must be 0 (no guard) or at least 2, got {self.requests}")
        if not (0.0 <= self.margin < 10.0):
            raise ValueError(f"~guard_margin must be in [0, 10), got {self.margin}")
        if not (0.5 <= self.confidence < 1.0):
            raise ValueError(f"~guard_confidence must be in [0.5, 1), got {self.confidence}")


class Verdict(NamedTuple):
    version: str
    previous: str        # the reference it was judged against, and a worse one goes back to
    worse: bool
    mean_new_s: float
    mean_old_s: float
    t: float
    critical: float
    n_new: int
    n_old: int

    def describe(self) -> str:
        return (f"model {self.version[:12]} {'is worse than' if self.worse else 'is not worse than'} "
                f"{self.previous[:12] or 'the model before'}: mean {1e3 * self.mean_new_s:.1f} ms over its first "
                f"{self.n_new} requests against {1e3 * self.mean_old_s:.1f} ms over the last {self.n_old} "
                f"(t {self.t:.2f}, one-sided critical {self.critical:.2f})")


def welch_worse(new, old, margin: float, confidence: float):
    """(worse, t, critical) of the one-sided Welch test that mean(new) > (1 + margin) mean(old)."""
    from scipy.stats import t as student_t

    n_new, n_old = len(new), len(old)
    mean_new, mean_old = sum(new) / n_new, sum(old) / n_old
    var_new = sum((x - mean_new) ** 2 for x in new) / (n_new - 1)
    var_old = sum((x - mean_old) ** 2 for x in old) / (n_old - 1)
    excess = mean_new - mean_old - margin * mean_old
    se2 = var_new / n_new + var_old / n_old
    if se2 <= 0.0:
        return excess > 0.0, math.copysign(math.inf, excess) if excess else 0.0, 0.0
    df = se2 ** 2 / ((var_new / n_new) ** 2 / (n_new - 1) + (var_old / n_old) ** 2 / (n_old - 1))
    t, critical = excess / math.sqrt(se2), float(student_t.ppf(confidence, df))
    return t > critical, t, critical


class ModelGuard:
    """Feed it every decided request's latency with the version that decided it (`observe`), and each swap to a
    new version (`begin`). `observe` returns a Verdict once per new version, when its window is full; a verdict of
    worse names the reference to go back to (Verdict.previous)."""

    def __init__(self, config: GuardConfig = GuardConfig()):
        self.config = config
        self._recent: Dict[str, deque] = {}
        self._reference: Optional[str] = None   # the version new ones are judged against ("" : no model)
        self._watch: Optional[tuple] = None    # (version, reference, the reference's window at the swap)
        self._lock = threading.Lock()
        if config.requests:
            welch_worse([1.0, 2.0], [1.0, 2.0], config.margin, config.confidence)   # scipy loads here, not later

    def begin(self, version: str, previous: str) -> None:
        """`version` decides from now on; `previous` decided before it."""
        n = self.config.requests
        if not n:
            return
        with self._lock:
            enough = max(2, n // 2)
            if self._reference is None and len(self._recent.get(previous, ())) >= enough:
                self._reference = previous
            reference = self._reference
            kept = {version: deque(maxlen=n)}
            if reference is not None:
                kept[reference] = self._recent.get(reference, deque(maxlen=n))
            self._recent = kept
            baseline = list(kept[reference]) if reference is not None else []
            self._watch = (version, reference, baseline) if len(baseline) >= enough else None

    def observe(self, version: str, latency_s: float) -> Optional[Verdict]:
        n = self.config.requests
        if not n or not math.isfinite(latency_s):
            return None
        with self._lock:
            recent = self._recent.setdefault(version, deque(maxlen=n))
            recent.append(latency_s)
            watch = self._watch
            if watch is None and self._reference is None and len(recent) == n:
                self._reference = version     # nothing live to judge the first version against: it is the reference
            if watch is None or watch[0] != version or len(recent) < n:
                return None
            self._watch = None
            new = list(recent)
            _, reference, old = watch
            worse, t, critical = welch_worse(new, old, self.config.margin, self.config.confidence)
            mean_new, mean_old = sum(new) / len(new), sum(old) / len(old)
            if not worse and mean_new <= mean_old:
                self._reference = version
        return Verdict(version, reference, worse, mean_new, mean_old, t, critical, len(new), len(old))

    @property
    def reference(self) -> Optional[str]:
        """The version a new one is judged against and a worse one rolls back to (None before there is one)."""
        return self._reference

    @property
    def watching(self) -> Optional[str]:
        return self._watch[0] if self._watch else None
