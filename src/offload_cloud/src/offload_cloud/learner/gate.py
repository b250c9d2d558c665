"""The one rule that lets a trained model reach the fleet: on each contributing robot's recent rows, off-policy
evaluation must say the new policy is not worse than the one in use, judged on the interval, not the point.

The rule is offload_learner_py.offline.off_policy_combined.not_worse (the learner package's trustworthy
comparison): the paired difference mean latency(new) - mean latency(current) over the same logged requests,
exactly 0 where the two policies decide alike, measured on probes, estimated elsewhere, with its 95 % interval;
accepted only when the whole interval is at or below `margin_s`, so an estimate that cannot say ("n/a") is refused.
Before it landed this module computed the same paired difference by IPS with off_policy.ips' interval; `gate` is
the one place the training round asks."""
from typing import Tuple

import numpy as np

from offload_learner_py.offline.off_policy_combined import not_worse
from offload_learner_py.offline.off_policy_intervals import Estimate
from offload_learner_py.offline.off_policy_steps import LoggedSteps


def gate(steps: LoggedSteps, actions_new: np.ndarray, actions_current: np.ndarray,
         margin_s: float = 0.0) -> Tuple[bool, Estimate]:
    """(accepted, the estimate of latency(new) - latency(current) in seconds with its 95 % interval) on one
    robot's logged requests."""
    if len(steps) == 0:
        from offload_learner_py.offline.off_policy_intervals import not_available
        return False, not_available("no logged requests")
    return not_worse(steps, actions_new, actions_current, margin_s)
