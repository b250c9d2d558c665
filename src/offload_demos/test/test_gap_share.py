"""The gap share's interval over rounds of repeats (offload_demos.gap_share) and its pooling over benches."""
import json

import numpy as np
import pytest
from scipy.stats import ttest_1samp

from offload_demos.gap_share import gap_share, main, pooled


def _rounds(seed, rounds, gap_ms, share, noise_ms):
    """Run means of (policy, threshold, oracle) over `rounds`, the machine moving every run of a round alike."""
    rng = np.random.default_rng(seed)
    machine = rng.normal(40.0, 3.0, rounds)          # each round's state of the machine moves all three runs
    threshold = machine + rng.normal(0, noise_ms, rounds)
    oracle = machine - gap_ms + rng.normal(0, noise_ms, rounds)
    policy = machine - share * gap_ms + rng.normal(0, noise_ms, rounds)
    return [list(1e-3 * policy), list(1e-3 * threshold), list(1e-3 * oracle)]


@pytest.mark.parametrize("seed", range(4))
def test_the_interval_is_every_share_a_paired_t_test_does_not_reject(seed):
    runs = _rounds(seed, 6, gap_ms=5.0, share=0.6, noise_ms=1.0)
    result = gap_share(*runs)
    assert result.low is not None and result.low < result.share < result.high
    policy, threshold, oracle = (np.asarray(r) for r in runs)
    gain, gap = threshold - policy, threshold - oracle
    assert result.share == pytest.approx(gain.mean() / gap.mean())
    # Inverting the test by brute force: s is inside exactly when mean(gain - s gap) = 0 is not rejected at 5 %.
    for s in np.linspace(result.low - 1.0, result.high + 1.0, 401):
        inside = result.low <= s <= result.high
        if min(abs(s - result.low), abs(s - result.high)) < 1e-3:
            continue            # at the bounds the two computations may round apart
        assert (ttest_1samp(gain - s * gap, 0.0).pvalue >= 0.05) == inside, s


def test_a_gap_inside_the_spread_between_rounds_gives_no_interval():
    # The oracle leads the threshold by 0.6 ms on average, by -1 to 3 ms in a round.
    threshold, oracle = [0.044, 0.040, 0.047, 0.041], [0.043, 0.041, 0.044, 0.0415]
    result = gap_share([0.0435, 0.0405, 0.045, 0.0412], threshold, oracle)
    assert result.share == pytest.approx((0.0005 - 0.0005 + 0.002 - 0.0002) / 4 / 0.000625)
    assert result.low is None and result.high is None
    assert "not told apart from zero" in result.why
    assert "over 4 rounds" in result.describe()


def test_one_round_gives_a_share_and_no_interval():
    result = gap_share([0.042], [0.044], [0.040])
    assert result.share == pytest.approx(0.5) and result.low is None and result.rounds == 1
    assert "one round" in result.why


def test_more_rounds_of_the_same_policy_narrow_the_interval():
    few = gap_share(*_rounds(7, 3, gap_ms=5.0, share=0.7, noise_ms=1.0))
    many = gap_share(*_rounds(7, 30, gap_ms=5.0, share=0.7, noise_ms=1.0))
    assert many.low is not None and many.low < 0.7 < many.high
    assert few.low is None or (many.high - many.low) < (few.high - few.low)


def test_garbage_run_means_are_refused():
    with pytest.raises(ValueError):
        gap_share([0.04, float("nan")], [0.05, 0.05], [0.03, 0.03])
    with pytest.raises(ValueError):
        gap_share([], [], [])


def _bench(tmp_path, name, runs):
    bench = tmp_path / name
    bench.mkdir()
    policies = {key: {"mean_s": float(np.mean(means)), "run_means_s": means}
                for key, means in zip(("dqn", "threshold_best", "oracle"), runs)}
    (bench / "results.json").write_text(json.dumps({"policies": policies}))
    return bench


def test_benches_pool_round_by_round_and_the_cli_prints_the_pooled_share(tmp_path, capsys):
    first = [[0.041, 0.039], [0.040, 0.046], [0.038, 0.036]]
    second = [[0.0455, 0.044, 0.043], [0.047, 0.045, 0.046], [0.044, 0.042, 0.041]]
    a, b = _bench(tmp_path, "a", first), _bench(tmp_path, "b", second)
    result = pooled([json.loads((d / "results.json").read_text()) for d in (a, b)], "dqn")
    assert result.rounds == 5
    expected = gap_share(*[one + two for one, two in zip(first, second)])
    assert result.share == pytest.approx(expected.share) and result.low == pytest.approx(expected.low)
    assert main([str(a), str(b)]) == 0
    assert f"dqn             {result.describe()}" in capsys.readouterr().out


def test_the_cli_names_a_policy_with_a_run_without_a_mean_and_goes_on(tmp_path, capsys):
    bench = _bench(tmp_path, "a", [[float("nan"), 0.039], [0.040, 0.046], [0.038, 0.036]])
    assert main([str(bench)]) == 0
    assert "dqn             no share: gap_share needs one finite run mean" in capsys.readouterr().out


def test_a_bench_without_readable_results_is_a_clear_error(tmp_path):
    (tmp_path / "results.json").write_text("{not json")
    with pytest.raises(SystemExit):
        main([str(tmp_path)])


def test_a_round_without_an_answered_request_leaves_the_table_without_an_interval_not_without_a_report():
    from offload_demos.bench_report import format_scenario_table, scenario_rows
    # A run that answered nothing has no mean (NaN): an hour's bench must still write its table.
    runs = {"threshold_best": [0.040, 0.046], "oracle": [0.038, 0.036], "dqn": [float("nan"), 0.039]}
    results = {"scenario": "pulse", "policies": {
        name: {"mean_s": 0.04, "p99_s": 0.1, "run_means_s": means} for name, means in runs.items()}}
    rows = {row["policy"]: row for row in scenario_rows(results)}
    assert rows["dqn"]["gap_closed_interval"] is None
    assert rows["oracle"]["gap_closed_interval"]["rounds"] == 2
    assert "pulse" in format_scenario_table(results)
