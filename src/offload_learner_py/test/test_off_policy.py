"""Off-policy estimates against the truth on logs whose logging policy is state dependent, so the
naive average of the logged latencies is biased and only reweighting recovers the truth."""
import math

import numpy as np
import pytest

from bagtools import write
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.data import bags
from offload_learner_py.offline import off_policy
from offload_demos.bag_writer import probe_request
from offload_learner_py.core.reward import reward
from statetools import raw_states


def logged_steps(n=4000, seed=3, probe_rate=1.0):
    rng = np.random.default_rng(seed)
    d = 10 ** rng.uniform(-2, 0.7, n)
    u = rng.uniform(0.2, 1.0, n)
    b = rng.uniform(0.02, 0.06, n)
    local_s = (0.005 + 0.04 * d / u) * rng.lognormal(0, 0.2, n)
    cloud_s = (b + 0.01 * d) * rng.lognormal(0, 0.2, n)
    # the logging policy mostly offloads big inputs: taken latencies over-represent cheap choices
    p_cloud = np.where(d > 1.0, 0.9, 0.15)
    action = (rng.random(n) < p_cloud).astype(np.int64)
    propensity = np.where(action == CLOUD, p_cloud, 1 - p_cloud)
    probe = rng.random(n) < probe_rate
    steps = off_policy.LoggedSteps(states=raw_states(d, u, b), action=action, propensity=propensity,
                                   latency_s=np.where(action == CLOUD, cloud_s, local_s), probe=probe,
                                   local_s=np.where(probe | (action == LOCAL), local_s, np.nan),
                                   cloud_s=np.where(probe | (action == CLOUD), cloud_s, np.nan))
    return steps, local_s, cloud_s


@pytest.mark.parametrize("seed", [3, 4])
def test_ips_and_dr_intervals_contain_the_true_mean_latency_where_the_naive_mean_is_biased(seed):
    steps, local_s, cloud_s = logged_steps(seed=seed, probe_rate=0.1)
    d = steps.states[:, 0]
    policies = {"local": np.full(len(d), LOCAL), "cloud": np.full(len(d), CLOUD),
                "threshold": np.where(d > 0.3, CLOUD, LOCAL)}
    predicted = off_policy.fit_latency_model(steps.states, steps.action, steps.latency_s)
    for name, actions in policies.items():
        truth = float(np.where(actions == CLOUD, cloud_s, local_s).mean())
        pi = off_policy.target_probabilities(actions)
        # the counterfactual estimators alone, on every request's taken side
        raw = {"ips": off_policy.ips(pi, steps.action, steps.propensity, steps.latency_s),
               "snips": off_policy.snips(pi, steps.action, steps.propensity, steps.latency_s),
               "dr": off_policy.doubly_robust(pi, steps.action, steps.propensity, steps.latency_s, predicted)}
        for estimator, estimate in raw.items():
            assert estimate.contains(truth), (name, estimator)
        assert raw["dr"].std_error < raw["ips"].std_error, name
        # probes scored directly, the other requests by each estimator
        result = off_policy.evaluate_policy(steps, actions)
        for estimator in ("ips", "snips", "dr"):
            assert result[f"latency_{estimator}_s"].contains(truth), (name, estimator)
        assert result["latency_s"] is result["latency_snips_s"]
        assert 0 < result["effective_sample_size"] <= len(d)
        assert result["counterfactual_steps"] == int((~steps.probe).sum())
        probes = result["latency_probe_s"]   # one 95 % interval (on seed 3, always-cloud's misses by a little)
        assert abs(probes.value - truth) < 4 * probes.std_error and probes.n == steps.probe.sum()
        # the naive estimate (mean of the logged latencies where the policy agrees) misses the truth
        agree = steps.action == actions
        naive = steps.latency_s[agree].mean()
        if name != "threshold":
            assert abs(naive - truth) > 4 * raw["ips"].std_error, name


def test_accuracy_on_probe_steps_agrees_with_the_truth():
    steps, local_s, cloud_s = logged_steps(probe_rate=0.3)
    actions = np.full(len(steps), CLOUD)
    result = off_policy.evaluate_policy(steps, actions)
    truth = float(np.mean(cloud_s <= local_s))
    assert result["probe_steps"] == int(steps.probe.sum())
    assert result["accuracy_probe"].contains(truth)
    assert "accuracy_ips" not in result   # accuracy needs both sides: the probes measure it directly


def test_wilson_interval_known_values():
    estimate = off_policy.wilson_interval(8, 10)
    assert estimate.value == 0.8
    assert estimate.low == pytest.approx(0.4902, abs=1e-4) and estimate.high == pytest.approx(0.9433, abs=1e-4)
    assert off_policy.wilson_interval(0, 0).n == 0


def test_ips_of_the_logging_policy_itself_is_the_plain_mean():
    steps, _, _ = logged_steps(n=500)
    pi = off_policy.target_probabilities(steps.action)
    # a deterministic target equal to the logged actions: weight 1 / mu on every step
    expected = np.mean(steps.latency_s / steps.propensity)
    assert off_policy.ips(pi, steps.action, steps.propensity, steps.latency_s).value == pytest.approx(expected)


def test_from_bags_with_a_small_probe_rate(tmp_path):
    rng = np.random.default_rng(5)
    requests = []
    for i in range(600):
        d, u = float(10 ** rng.uniform(-2, 0.7)), float(rng.uniform(0.2, 1))
        local_s, cloud_s = 0.005 + 0.04 * d / u, 0.03 + 0.01 * d
        p_cloud = 0.9 if d > 1 else 0.1
        action = int(rng.random() < p_cloud)
        propensity = p_cloud if action == CLOUD else 1 - p_cloud
        requests.append(probe_request(i + 1, d, u, 0.03, local_s, cloud_s, action, propensity,
                                      reward(action, local_s, cloud_s), probe=rng.random() < 0.2))
    data = bags.read_bags([write(tmp_path / "deployed.bag", requests)])
    steps = off_policy.LoggedSteps.from_log(data.log)
    assert len(steps) == 600 and 60 < steps.probe.sum() < 180
    assert np.all(np.isfinite(steps.latency_s))
    results = {name: off_policy.evaluate_policy(steps, actions)
               for name, actions in off_policy.candidate_actions(steps).items()}
    truth_local = np.mean([0.005 + 0.04 * r[0]["input_size"] / r[0]["cpu_availability"] for r in requests])
    assert results["always_local"]["latency_dr_s"].contains(truth_local)
    text = off_policy.format_results(results)
    assert "always_cloud" in text and "n/a" not in text.splitlines()[1]


def test_cli_prints_estimates_and_fails_cleanly_on_nothing(tmp_path, capsys):
    path = write(tmp_path / "x.bag", [probe_request(i + 1, 0.5, 0.5, 0.03, 0.02, 0.03, i % 2, 0.5,
                                                    reward(i % 2, 0.02, 0.03)) for i in range(40)])
    assert off_policy.main([path]) == 0
    assert "always_local" in capsys.readouterr().out
    empty = tmp_path / "empty.bag"
    empty.write_bytes(b"")
    assert off_policy.main([str(empty)]) == 2
    assert math.isnan(off_policy.wilson_interval(0, 0).value)


def test_snips_and_effective_sample_size_by_hand():
    pi = off_policy.target_probabilities(np.array([1, 1, 1]))
    action, propensity, latency = np.array([1, 0, 1]), np.array([0.5, 0.5, 0.5]), np.array([1.0, 9.0, 3.0])
    assert off_policy.snips(pi, action, propensity, latency).value == pytest.approx(2.0)   # (2*1 + 2*3) / 4
    assert off_policy.ips(pi, action, propensity, latency).value == pytest.approx(8.0 / 3)
    assert off_policy.effective_sample_size(pi, action, propensity) == pytest.approx(2.0)


def test_snips_interval_is_the_jackknifes():
    pi = off_policy.target_probabilities(np.array([1, 1, 1, 1]))
    action, propensity = np.array([1, 1, 0, 1]), np.array([0.5, 0.25, 0.5, 0.5])
    latency = np.array([1.0, 5.0, 9.0, 3.0])
    estimate = off_policy.snips(pi, action, propensity, latency)
    # Leave-one-out ratios and pseudo-values by hand: sum w y = 2 + 20 + 6 = 28, sum w = 8, value 3.5.
    loo = np.array([26 / 6, 8 / 4, 28 / 8, 22 / 6])
    pseudo = 4 * 3.5 - 3 * loo
    assert estimate.value == pytest.approx(3.5)
    assert estimate.std_error == pytest.approx(pseudo.std(ddof=1) / 2)
    assert estimate.low < 3.5 < estimate.high
    # One row holding all the weight leaves nothing to leave out: the interval is unbounded, not zero wide.
    alone = off_policy.snips(pi, np.array([1, 0, 0, 0]), propensity, latency)
    assert alone.value == pytest.approx(1.0) and alone.low == -math.inf and alone.high == math.inf


def test_interval_quantile_is_students_t_on_satterthwaites_degrees_of_freedom():
    # Symmetric terms (no skewness): the interval is value +- t * std_error, t on 2 n / (kurtosis - 1) degrees.
    terms = np.array([-10.0] * 2 + [0.0] * 96 + [10.0] * 2)      # a few rows carry all the variance
    pi = off_policy.target_probabilities(np.ones(100, dtype=np.int64))
    estimate = off_policy.ips(pi, np.ones(100, dtype=np.int64), np.ones(100), terms)
    deviation = terms - terms.mean()
    second = np.sum(deviation ** 2) / 99
    kurtosis = np.mean(deviation ** 4) / second ** 2
    from scipy.stats import t
    quantile = t.ppf(0.975, 2 * 100 / (kurtosis - 1))
    assert 2 * 100 / (kurtosis - 1) < 10                          # heavy tails: few degrees of freedom
    assert estimate.high - estimate.value == pytest.approx(quantile * estimate.std_error)
    assert estimate.value - estimate.low == pytest.approx(quantile * estimate.std_error)
    # Normal-looking terms keep about the normal quantile.
    normal = np.random.default_rng(3).normal(0.0, 1.0, 4000)
    wide = off_policy.ips(off_policy.target_probabilities(np.ones(4000, dtype=np.int64)), np.ones(4000, dtype=np.int64),
                          np.ones(4000), normal)
    assert (wide.high - wide.low) / (2 * wide.std_error) == pytest.approx(off_policy.Z_95, rel=0.02)


def test_shares_stay_shares_and_an_estimate_that_cannot_say_says_why():
    from offload_learner_py.offline.off_policy import Estimate, clipped, format_results, not_available
    over = clipped(Estimate(1.4, 0.801, 1.999, 0.3, 10), 0.0, 1.0)
    assert (over.value, over.low, over.high) == (1.0, 0.801, 1.0)
    empty = not_available("too few effective samples: 4 among 12 requests with one side measured, and 0 probes")
    result = {"latency_ips_s": empty, "latency_snips_s": empty, "latency_dr_s": empty, "effective_sample_size": 4.0}
    text = format_results({"few": result})
    assert "n/a for few: too few effective samples: 4 among 12" in text and "0.00" not in text
    assert "n/a for" not in format_results({"many": {**result, **{key: Estimate(0.1, 0.09, 0.11, 0.005, 300)
                                                                  for key in ("latency_ips_s", "latency_snips_s",
                                                                              "latency_dr_s")}}})


def test_a_request_the_router_kept_local_whatever_the_draw_has_propensity_one(tmp_path):
    # An exploring policy drew cloud with propensity 0.05, but the open breaker (or the slow-link guard) sent the
    # request to the local planner: local was certain, so its latency must not be weighted 1 / 0.05.
    requests = []
    for i, breaker in enumerate(("closed", "open", "slow")):
        decision, outcome = probe_request(4000 + i, 1.0, 0.5, 0.05, 0.1, 0.2, CLOUD, 0.05, 0.0, probe=False)
        decision.update(routed=LOCAL, breaker=breaker, action=CLOUD)
        outcome.update(action=CLOUD, delivered=LOCAL, local_measured=True, local_s=0.1, cloud_measured=False,
                       cloud_s=0.0)
        requests.append((decision, outcome))
    data = bags.read_bags([write(tmp_path / "kept_local.bag", requests)])
    steps = off_policy.LoggedSteps.from_log(data.log)
    assert list(steps.action) == [LOCAL] * 3
    assert list(steps.propensity) == [0.05, 1.0, 1.0]


def few_requests(n, probe=False, action=CLOUD, propensity=0.001, latency=1.2):
    states = np.tile(raw_states(1.0, 0.5, 0.05), (n, 1))
    other = np.full(n, np.nan) if not probe else np.full(n, 0.5)
    return off_policy.LoggedSteps(states=states, action=np.full(n, action), propensity=np.full(n, propensity),
                                  latency_s=np.full(n, latency), probe=np.full(n, probe),
                                  local_s=np.full(n, latency) if action == LOCAL else other,
                                  cloud_s=np.full(n, latency) if action == CLOUD else other)


def test_three_heavily_weighted_requests_give_no_estimate_rather_than_a_huge_one():
    """#31: three requests logged at propensity 0.001 printed an IPS of 1.2e9 ms with a negative lower bound."""
    steps = few_requests(3)
    result = off_policy.evaluate_policy(steps, np.full(3, CLOUD))
    for estimator in off_policy.ESTIMATORS:
        estimate = result[f"latency_{estimator}_s"]
        assert not estimate.available and estimate.format(1000) == "n/a"
        assert "too few effective samples" in estimate.reason
    assert "n/a for always_cloud: too few effective samples" in off_policy.format_results({"always_cloud": result})


def test_a_policy_no_request_supports_is_n_a_not_zero():
    """#31: always-cloud on requests that all ran locally with certainty printed 0.00 ms."""
    steps = few_requests(50, action=LOCAL, propensity=1.0, latency=0.02)
    result = off_policy.evaluate_policy(steps, np.full(50, CLOUD))
    assert result["unsupported_steps"] == 50
    assert result["latency_ips_s"].format(1000) == "n/a" and "no support" in result["latency_ips_s"].reason
    local = off_policy.evaluate_policy(steps, np.full(50, LOCAL))["latency_snips_s"]   # what was run: measured
    assert local.value == pytest.approx(0.02) and local.low == local.high == pytest.approx(0.02)


def test_every_request_a_probe_scores_the_measured_latency_whatever_the_propensities():
    """Learning mode: both sides measured on every request and the greedy action logged at propensity 1. Before,
    IPS counted 0 ms for every request the policy would have run on the other side (always-local 36 ms against
    the measured 77 on a demo bag)."""
    from ope_rows import load_rows

    rows = load_rows(__file__.rsplit("/", 1)[0] + "/data/learning_demo_rows.npz")
    n = len(rows["action"])
    steps = off_policy.LoggedSteps(states=raw_states(rows["input_size"], rows["cpu_availability"],
                                                    rows["round_trip_s"]),
                                   action=rows["action"], propensity=np.ones(n),
                                   latency_s=np.where(rows["action"] == CLOUD, rows["cloud_s"], rows["local_s"]),
                                   probe=np.ones(n, dtype=bool), local_s=rows["local_s"], cloud_s=rows["cloud_s"])
    for side, measured in ((LOCAL, rows["local_s"]), (CLOUD, rows["cloud_s"])):
        result = off_policy.evaluate_policy(steps, np.full(n, side))
        for estimator in off_policy.ESTIMATORS:
            estimate = result[f"latency_{estimator}_s"]
            assert estimate.value == pytest.approx(measured.mean())
            assert 0 < estimate.low < measured.mean() < estimate.high < measured.max()


def test_parts_combine_by_share_with_summed_variances():
    from offload_learner_py.offline.off_policy_intervals import combine, part
    rng = np.random.default_rng(1)
    a, b = rng.normal(1.0, 0.1, 400), rng.normal(3.0, 0.5, 100)
    combined = combine([part(a, 0.75), part(b, 0.25)])
    assert combined.value == pytest.approx(0.75 * a.mean() + 0.25 * b.mean())
    variance = 0.75 ** 2 * a.var(ddof=1) / 400 + 0.25 ** 2 * b.var(ddof=1) / 100
    assert combined.std_error == pytest.approx(np.sqrt(variance))
    assert combined.high - combined.low == pytest.approx(2 * off_policy.Z_95 * combined.std_error, rel=0.02)
    assert part(a[:1], 0.5) is None and part(np.array([]), 0.0).variance == 0.0
    exact = combine([part(np.zeros(5), 0.5), part(np.array([]), 0.0)])
    assert (exact.value, exact.low, exact.high) == (0.0, 0.0, 0.0)


def test_a_latency_model_extrapolates_no_further_than_ten_times_what_was_measured():
    states = raw_states(np.r_[np.full(60, 0.1), 1e5], np.full(61, 0.5), np.full(61, 0.03))
    local_s = np.r_[0.01 * np.exp(np.linspace(0, 3, 60)), np.nan]   # grows with the row, never seen at d = 1e5
    predicted = off_policy.cross_fitted_latencies(states, local_s, np.full(61, 0.05))
    assert predicted.max() <= 10 * np.nanmax(local_s) + 1e-12
