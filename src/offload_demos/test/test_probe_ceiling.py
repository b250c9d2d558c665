"""probe_ceiling: the DQN trained on one hedge run's rows is scored on another run's probes, never on its own."""
import json

import numpy as np
import pytest

from bagtools import CLOUD, write
from offload_learner_py.core.reward import reward
from offload_demos.bag_writer import probe_request
from offload_demos.probe_ceiling import cross_run, hedge_rows, main


def _hedge_run(path, small_is_local: bool, n=160, seed=5):
    """A hedge run (both sides of every request) whose faster side is local below d_t = 1 or above it."""
    rng = np.random.default_rng(seed)
    requests = []
    for i in range(n):
        d = float(10 ** rng.uniform(-1, 0.6))
        local_s = 0.02 if (d < 1.0) == small_is_local else 0.08
        cloud_s = 0.05
        requests.append(probe_request(1000 + i, d, 0.8, 0.03, local_s, cloud_s, CLOUD, 1.0,
                                      reward(CLOUD, local_s, cloud_s), local_plan_rate=30.0))
    path.mkdir(parents=True)
    write(path / "offload.bag", requests)
    return path


def test_the_ceiling_is_scored_on_another_run_and_in_sample_apart(tmp_path):
    # The same states met twice with the faster side swapped: what one run teaches is wrong on the other.
    runs = [hedge_rows(_hedge_run(tmp_path / name, small)) for name, small in (("a", True), ("b", False))]
    figures = cross_run(runs, seeds=[1])
    for k in (0, 1):
        assert figures[k]["in_sample_s"] < 0.005        # learns its own run
        assert figures[k]["cross_run_s"] > 0.02         # the other run's lesson costs 30 ms on most requests


def test_the_cli_prints_each_hedge_runs_figures_and_needs_two_runs(tmp_path, capsys):
    bench = tmp_path / "bench"
    for k in (1, 2):
        _hedge_run(bench / "hedge" / f"repeat{k}" / "run", True, seed=k)
    (bench / "results.json").write_text(json.dumps({"threshold_best": {"threshold": 1.0}}))
    assert main([str(bench), "--seeds", "1"]) == 0
    out = capsys.readouterr().out
    assert "hedge 1" in out and "hedge 2" in out and "n/a" in out     # no learning run: its column is n/a
    with pytest.raises(SystemExit):
        main([str(tmp_path / "bench" / "hedge")])


def test_a_corrupt_hedge_bag_is_a_clear_error(tmp_path, capsys):
    bench = tmp_path / "bench"
    _hedge_run(bench / "hedge" / "repeat1" / "run", True)
    (bench / "hedge" / "repeat2" / "run").mkdir(parents=True)
    (bench / "hedge" / "repeat2" / "run" / "offload.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\xff" * 64)
    (bench / "results.json").write_text(json.dumps({"threshold_best": {"threshold": 1.0}}))
    with pytest.raises(SystemExit):
        main([str(bench), "--seeds", "1"])
    assert str(bench) in capsys.readouterr().err
