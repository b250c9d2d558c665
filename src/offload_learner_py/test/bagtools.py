"""Small bags for the tests, written by the tests themselves (rosbags writer, the workspace's own
message definitions or older ones)."""
import math

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_demos.bag_writer import probe_request, write_requests
from offload_learner_py.core.reward import reward


def make_requests(n, seed=0, probe_every=1, first_id=1000):
    """n requests whose faster side depends on d and u; every probe_every-th one is a probe step."""
    rng = np.random.default_rng(seed)
    requests = []
    for i in range(n):
        d = float(10 ** rng.uniform(-2, 0.7))
        u = float(rng.uniform(0.2, 1.0))
        b = float(rng.uniform(0.02, 0.06))
        local_s = 0.005 + 0.04 * d / u
        cloud_s = b + 0.01 * d + float(rng.uniform(0, 0.01))
        action = int(rng.integers(0, 2))
        propensity = 0.5   # actions are drawn uniformly
        probe = i % probe_every == 0
        requests.append(probe_request(first_id + i, d, u, b, local_s, cloud_s, action, propensity,
                                      reward(action, local_s, cloud_s), probe=probe,
                                      loss=0.1 / (i + 1) if probe else math.nan))
    return requests


def write(path, requests, **kwargs):
    return write_requests(str(path), requests, **kwargs)


__all__ = ["make_requests", "write", "LOCAL", "CLOUD"]
