"""How the off-policy comparison weighs what probes alone can say (found by `make mutate` over
offline/off_policy_combined.py, #31: 42 of 168 run survived, among them the weight of a stratum its probes stand
for and the probe minimum's comparison)."""
import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.offline import off_policy
from offload_learner_py.offline.off_policy_combined import MIN_PROBE_ROWS, evaluate_policy
from statetools import raw_states


def greedy_local_log(n=400, probe_every=20, seed=3):
    """A deployed robot that always planned locally (propensity 1) and probed every probe_every-th request."""
    rng = np.random.default_rng(seed)
    states = raw_states(rng.uniform(0.1, 2, n), rng.uniform(0.2, 1, n), rng.uniform(0.02, 0.06, n))
    local_s, cloud_s = rng.uniform(0.02, 0.05, n), rng.uniform(0.06, 0.09, n)
    probe = np.arange(n) % probe_every == 0
    return off_policy.LoggedSteps(states=states, action=np.full(n, LOCAL), propensity=np.ones(n), latency_s=local_s,
                                  probe=probe, local_s=local_s, cloud_s=np.where(probe, cloud_s, np.nan)), cloud_s


def test_a_policy_the_logger_never_ran_is_its_probes_mean_when_they_are_enough():
    steps, cloud_s = greedy_local_log()       # 20 probes: the only measurements of the cloud
    figures = evaluate_policy(steps, np.full(len(steps), CLOUD))
    expected = cloud_s[steps.probe].mean()
    for name in ("snips", "dr", "ips"):
        value = figures[f"latency_{name}_s"]
        assert value.value == pytest.approx(expected, rel=1e-9), name
        assert value.low < expected < value.high


def test_probes_above_the_minimum_but_not_at_it_still_stand_for_the_stratum():
    steps, cloud_s = greedy_local_log(n=13 * 20, probe_every=20)     # 13 probes
    assert steps.probe.sum() == 13 > MIN_PROBE_ROWS
    assert evaluate_policy(steps, np.full(len(steps), CLOUD))["latency_s"].available


def test_too_few_probes_say_nothing():
    steps, _ = greedy_local_log(n=(MIN_PROBE_ROWS - 1) * 20, probe_every=20)
    value = evaluate_policy(steps, np.full(len(steps), CLOUD))["latency_s"]
    assert not value.available and "probes" in value.reason
