"""Real rows for the fleet learner's tests: OffloadDecision / OffloadOutcome serialized in ROS 1 wire format by the
rosbags type store from the installed .msg files (the bytes genpy's serialize() gives and a bag records), and
synthetic requests with a known truth."""
import math
import time

import numpy as np

from offload_demos.bag_writer import DECISION_TYPE, OUTCOME_TYPE, BagWriter, installed_definitions, probe_request, \
    typestore_for
from offload_learner_py.core.reward import CostWeights, reward

_STORE = typestore_for(*installed_definitions())


def definitions():
    """(definitions, md5) as a ROWS message carries them, in rosbag's stored form."""
    texts, sums = {}, {}
    for wire, msgtype in (("offload_msgs/OffloadDecision", DECISION_TYPE), ("offload_msgs/OffloadOutcome", OUTCOME_TYPE)):
        texts[wire], sums[wire] = _STORE.generate_msgdef(msgtype)
    return texts, sums


class _Builder(BagWriter):
    def __init__(self):   # build() only: no file
        self.store = _STORE


_BUILDER = _Builder()


def serialize(decision: dict, outcome: dict, stamp_ns: int = 0):
    stamp_ns = stamp_ns or time.time_ns()
    return (bytes(_STORE.serialize_ros1(_BUILDER.build(DECISION_TYPE, decision, stamp_ns), DECISION_TYPE)),
            bytes(_STORE.serialize_ros1(_BUILDER.build(OUTCOME_TYPE, outcome, stamp_ns + 1), OUTCOME_TYPE)))


def truth(u: np.ndarray):
    """Known truth: local takes 40 ms on a free CPU and 200 ms on a busy one; the cloud always 100 ms."""
    return np.where(u >= 0.5, 0.04, 0.2), np.full(len(u), 0.1)


def requests(n: int, seed: int = 0, start_id: int = 1, epsilon: float = 0.5, probe: bool = True,
             greedy_local_probe_every: int = 0):
    """(decision, outcome) dicts of n requests by a uniform random logger (propensity 0.5); with
    greedy_local_probe_every k, by a deployed robot that always plans locally (propensity 1) and probes every
    k-th request."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(0.0, 1.0, n)
    local_s, cloud_s = truth(u)
    local_s, cloud_s = local_s * rng.uniform(0.9, 1.1, n), cloud_s * rng.uniform(0.9, 1.1, n)
    action = np.zeros(n, dtype=np.int64) if greedy_local_probe_every else rng.integers(0, 2, n)
    propensity = 1.0 if greedy_local_probe_every else 0.5
    out = []
    for i in range(n):
        probed = i % greedy_local_probe_every == 0 if greedy_local_probe_every else probe
        r = reward(int(action[i]), float(local_s[i]), float(cloud_s[i]), CostWeights())
        out.append(probe_request(start_id + i, 1.0, float(u[i]), 0.03, float(local_s[i]), float(cloud_s[i]),
                                 int(action[i]), propensity, float(r), probe=probed))
    return out


def rows(n: int, seed: int = 0, start_id: int = 1, **kwargs):
    return [serialize(d, o, 1_700_000_000_000_000_000 + (start_id + i) * 1000)
            for i, (d, o) in enumerate(requests(n, seed, start_id, **kwargs))]


def nan_row(request_id: int, **changes):
    decision, outcome = requests(1, start_id=request_id)[0]
    decision.update(changes)
    return serialize(decision, outcome)


_ = math
