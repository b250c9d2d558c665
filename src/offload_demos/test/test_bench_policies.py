"""bench-policies' figures: one policy's repeated runs are pooled request by request, and each run's mean is
kept to show the spread between repeats."""
import numpy as np
import pytest

from bagtools import make_requests, write
from offload_demos.bench_policies import measure


def test_repeated_runs_are_pooled_and_each_runs_mean_is_kept(tmp_path):
    runs = []
    for k, n in enumerate((30, 50)):
        run = tmp_path / f"repeat{k + 1}"
        run.mkdir()
        write(run / "offload.bag", make_requests(n, seed=k, probe_every=3, first_id=1000 * (k + 1)))
        runs.append(run)
    alone = [measure(run, 5.0) for run in runs]
    pooled = measure(runs, 5.0)
    assert pooled["requests"] == 80 and len(pooled["delivered_s"]) == 80
    assert pooled["run_means_s"] == pytest.approx([figures["mean_s"] for figures in alone])
    assert pooled["mean_s"] == pytest.approx((30 * alone[0]["mean_s"] + 50 * alone[1]["mean_s"]) / 80)
    assert pooled["p99_s"] == pytest.approx(np.percentile(alone[0]["delivered_s"] + alone[1]["delivered_s"], 99))
    assert "run_means_s" not in alone[0]
    # each mean is its own run's, whatever order the runs are given in (the reader sorts the bags)
    assert measure(runs[::-1], 5.0)["run_means_s"] == pytest.approx(pooled["run_means_s"][::-1])
