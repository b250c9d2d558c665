"""The gate a fleet learner publishes by: off_policy.not_worse(steps, actions_new, actions_current, margin_s),
judged on the interval of the paired difference of mean latencies, on synthetic deployed-like logs whose
truth is known (both latencies of every request are drawn, then the untaken side of non-probe requests is
dropped)."""
import math

import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.offline import off_policy
from statetools import raw_states


def population(n=3000, seed=11):
    rng = np.random.default_rng(seed)
    d = 10 ** rng.uniform(-2, 0.7, n)
    u = rng.uniform(0.2, 1.0, n)
    b = rng.uniform(0.02, 0.06, n)
    local_mean, cloud_mean = 0.005 + 0.04 * d / u, b + 0.01 * d
    local_s = local_mean * rng.lognormal(0, 0.3, n)
    cloud_s = cloud_mean * rng.lognormal(0, 0.3, n)
    return raw_states(d, u, b), local_s, cloud_s, local_mean, cloud_mean


STATES, LOCAL_S, CLOUD_S, LOCAL_MEAN, CLOUD_MEAN = population()
CURRENT = np.where(STATES[:, 0] > 1.5, CLOUD, LOCAL)                 # offloads big inputs only
BETTER = np.where(CLOUD_MEAN < LOCAL_MEAN, CLOUD, LOCAL)             # the faster side in expectation
WORSE = np.full(len(STATES), LOCAL)                                  # never offloads


def truth(actions) -> float:
    return float(np.where(actions == CLOUD, CLOUD_S, LOCAL_S).mean())


def deployed_log(seed=1, probe_rate=0.1, epsilon=0.1, logger=CURRENT) -> off_policy.LoggedSteps:
    rng = np.random.default_rng(seed)
    n = len(STATES)
    greedy = rng.random(n) >= epsilon / 2
    action = np.where(greedy, logger, 1 - logger)
    probe = rng.random(n) < probe_rate
    return off_policy.LoggedSteps(states=STATES, action=action, propensity=np.where(greedy, 1 - epsilon / 2, epsilon / 2),
                                  latency_s=np.where(action == CLOUD, CLOUD_S, LOCAL_S), probe=probe,
                                  local_s=np.where(probe | (action == LOCAL), LOCAL_S, np.nan),
                                  cloud_s=np.where(probe | (action == CLOUD), CLOUD_S, np.nan))


def test_the_truth_of_the_three_candidates():
    assert truth(BETTER) < truth(CURRENT) - 0.005 and truth(WORSE) > truth(CURRENT) + 0.02   # 31, 38, 69 ms


def test_a_better_policy_is_accepted_and_its_interval_holds_the_true_gain():
    accepted, difference = off_policy.not_worse(deployed_log(), BETTER, CURRENT)
    assert accepted and difference.high < 0.0
    assert difference.contains(truth(BETTER) - truth(CURRENT))


def test_the_same_policy_is_accepted_with_a_difference_of_exactly_zero():
    accepted, difference = off_policy.not_worse(deployed_log(), CURRENT.copy(), CURRENT)
    assert accepted and (difference.value, difference.low, difference.high) == (0.0, 0.0, 0.0)


def test_a_worse_policy_is_refused_and_its_interval_holds_the_true_loss():
    accepted, difference = off_policy.not_worse(deployed_log(), WORSE, CURRENT)
    assert not accepted and difference.low > 0.0
    assert difference.contains(truth(WORSE) - truth(CURRENT))
    # a margin above the whole interval lets it through: "not worse" is "at most margin_s slower"
    assert off_policy.not_worse(deployed_log(), WORSE, CURRENT, margin_s=difference.high + 1e-6)[0]


@pytest.mark.parametrize("estimator", off_policy.ESTIMATORS)
def test_each_estimator_judges_the_three_alike(estimator):
    log = deployed_log(seed=2)
    verdicts = [off_policy.not_worse(log, actions, CURRENT, estimator=estimator)[0]
                for actions in (BETTER, CURRENT, WORSE)]
    assert verdicts == [True, True, False]


def test_a_difference_the_logs_cannot_inform_is_refused_with_its_reason():
    """A frozen model (epsilon 0) never takes the other side, and no request is a probe: nothing says what
    never offloading would cost on the requests the model offloads. n/a, and the gate refuses."""
    accepted, difference = off_policy.not_worse(deployed_log(probe_rate=0.0, epsilon=0.0), WORSE, CURRENT)
    assert not accepted and not difference.available and "no support" in difference.reason
    assert math.isnan(difference.value)


def test_over_many_logs_a_worse_policy_is_rarely_let_through_and_a_better_one_mostly_is():
    """One-sided: the upper end of a 95 % interval is above the truth in about 97.5 % of logs, so a policy
    truly worse by any amount is accepted in at most a few per cent of them."""
    slightly_worse = np.where(STATES[:, 0] > 1.7, CLOUD, LOCAL)      # offloads a little later than the current
    loss = truth(slightly_worse) - truth(CURRENT)
    assert 0 < loss < 0.003
    logs = [deployed_log(seed=seed, probe_rate=0.05) for seed in range(60)]
    let_through = sum(off_policy.not_worse(log, slightly_worse, CURRENT)[0] for log in logs)
    accepted_better = sum(off_policy.not_worse(log, BETTER, CURRENT)[0] for log in logs)
    assert let_through <= 4 and accepted_better >= 55, (let_through, accepted_better)
