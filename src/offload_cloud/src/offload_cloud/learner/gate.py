"""The one rule that lets a trained model reach the fleet: on each contributing robot's recent rows, off-policy
evaluation must say the new policy is not worse than the one in use, judged on the interval, not the point.

Rule (until the trustworthy comparison of the `ope` branch lands on main, then `gate` calls its `not_worse`): the
paired difference mean latency(new) - mean latency(current) over the same logged requests, estimated by IPS with
pi = pi_new - pi_current (each row's term is (1[new takes a_i] - 1[current takes a_i]) / mu_i * y_i: exactly 0
where the two policies agree, so only the requests they decide differently carry the comparison), with
off_policy.ips' 95 % interval (skewness-corrected, Student's t on Satterthwaite's degrees of freedom). Accepted
only when that whole interval lies at or below `margin_s`: an interval that cannot be computed, or one reaching
above the margin (too few exploratory rows where the policies differ, or a worse policy), is refused. Pairing
cancels the rows both policies share, so the interval is far narrower than comparing two separate intervals
(new's upper bound against current's lower bound would refuse almost everything; new's upper bound against
current's upper bound would accept a worse policy whose interval is merely as wide)."""
import math
from typing import Tuple

import numpy as np

from offload_learner_py.offline.off_policy import Estimate, LoggedSteps, ips, target_probabilities


def gate(steps: LoggedSteps, actions_new: np.ndarray, actions_current: np.ndarray,
         margin_s: float = 0.0) -> Tuple[bool, Estimate]:
    """(accepted, the estimate of latency(new) - latency(current) in seconds with its 95 % interval) on one
    robot's logged requests; the signature of the ope branch's off_policy `not_worse`."""
    if len(steps) == 0:
        return False, Estimate(math.nan, math.nan, math.nan, math.nan, 0)
    pi = target_probabilities(actions_new) - target_probabilities(actions_current)
    difference = ips(pi, steps.action, steps.propensity, steps.latency_s)
    return bool(difference.n > 0 and math.isfinite(difference.high) and difference.high <= margin_s), difference
