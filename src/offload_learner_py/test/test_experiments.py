import json
import os
import subprocess
import sys

import numpy as np
import pytest

from offload_learner_py.offline import experiments
from offload_learner_py.data.dataset import COLUMNS
from offload_learner_py.data.synthetic import generate_synthetic


def test_synthetic_command_writes_metrics_and_plots(tmp_path, capsys):
    out = tmp_path / "cpu"
    assert experiments.main(["synthetic", "--kind", "cpu", "--steps", "300", "--seed", "4", "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert 0.0 <= metrics["accuracy"] <= 1.0 and "accuracy_taken" in metrics
    assert "learned_threshold" in metrics and metrics["generating_threshold"] == 0.6
    for policy in ("dqn", "dqn_taken", "always_local", "always_cloud", "random", "threshold_d", "oracle", "lstm"):
        assert metrics["mean_latency_s"][policy] > 0
    for name in ("training.png", "action_vs_input_size.png", "action_vs_cpu.png", "confusion_matrix.png",
                 "accuracy.png", "transitions.npz", "transitions.csv", "dqn.pt"):
        assert (out / name).exists(), name
    captured = capsys.readouterr()
    assert "step 300/300" in captured.err  # progress is visible
    assert json.loads(captured.out.strip().splitlines()[-1])["accuracy"] == metrics["accuracy"]


def test_config_overrides_reach_the_learner(tmp_path):
    out = tmp_path / "local"
    experiments.main(["synthetic", "--kind", "local", "--steps", "250", "--seed", "2", "--out", str(out),
                      "--gamma", "0.9", "--set", "target_update_interval=25", "--set", "hidden_sizes=[64,64,64]"])
    config = json.loads((out / "metrics.json").read_text())["dqn_config"]
    assert (config["gamma"], config["target_update_interval"], config["hidden_sizes"], config["seed"]) == \
        (0.9, 25, [64, 64, 64], 2)
    assert experiments.main(["synthetic", "--kind", "local", "--out", str(out), "--set", "gama=0.9"]) == 2
    assert experiments.main(["synthetic", "--kind", "local", "--out", str(out), "--set", "batch_size=\"x\""]) == 2


def _cli(*args, cwd):
    # the learner's sources first, then what the workspace provides (the planner package it depends on)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.path.join(os.path.dirname(__file__), "..", "src"),
                                                        os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "offload_learner_py.offline.experiments", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_a_missing_data_file_is_one_error_line_and_exit_2(tmp_path):
    result = _cli("compare", "--data", "absent.npz", "--out", "o", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.startswith("error: absent.npz: cannot read transition table")
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_bad_user_input_is_an_error_message_and_exit_2(tmp_path, capsys):
    (tmp_path / "text.npz").write_text("not an archive")
    (tmp_path / "short.csv").write_text(",".join(COLUMNS) + "\n0,0.1,0.5\n")
    out = str(tmp_path / "o")
    cases = [(["compare", "--data", str(tmp_path / "text.npz"), "--out", out], "text.npz is not a transition table"),
             (["compare", "--data", str(tmp_path / "short.csv"), "--out", out], "short.csv line 2: 3 fields"),
             (["synthetic", "--kind", "cpu", "--trace", str(tmp_path / "absent.npz"), "--out", out],
              "cannot read planning trace"),
             (["synthetic", "--kind", "cpu", "--out", out, "--set", "learning_rate=NaN"], "learning_rate must be")]
    for args, message in cases:
        assert experiments.main(args) == 2, args
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err, (args, err)
    with pytest.raises(SystemExit) as exit_info:  # argparse: usage error, exit 2
        experiments.main(["generate", "--kind", "cpu", "--steps", "0", "--out", "x.npz"])
    assert exit_info.value.code == 2 and "--steps must be in 1.." in capsys.readouterr().err


def test_compare_command_scores_every_policy_on_one_table(tmp_path, bundled_trace, capsys):
    data = str(tmp_path / "cpu.npz")
    generate_synthetic("cpu", bundled_trace, 400, seed=9).save_npz(data)
    out = tmp_path / "compare"
    assert experiments.main(["compare", "--data", data, "--out", str(out), "--set", "learning_starts=100"]) == 0
    result = json.loads((out / "comparison.json").read_text())
    assert set(result["accuracy"]) == {"dqn", "always_local", "always_cloud", "random", "threshold_d", "oracle",
                                       "lstm", "lstm_all_features"}
    assert result["accuracy"]["oracle"] == 1.0 and result["test_rows"] == 200
    # Eq. 15: the cloud is faster exactly when u < 0.6, so that is where the oracle offloads.
    test = experiments.TransitionTable.load_npz(data).slice(200, 400)
    assert result["policies"]["oracle"]["cloud_share"] == pytest.approx(np.mean(test.cpu_availability < 0.6))
    assert result["policies"]["oracle"]["mean_latency_s"] == pytest.approx(
        np.where(test.cpu_availability < 0.6, test.cloud_s, test.local_s).mean())
    table = (out / "comparison.md").read_text()
    assert "| dqn |" in table and "| lstm |" in table
    for name in ("accuracy.png", "confusion_matrix_dqn.png", "action_vs_cpu.png", "training.png"):
        assert (out / name).exists()
    assert "| oracle | 100.0%" in capsys.readouterr().out


def test_compare_reads_csv_too(tmp_path, small_trace):
    data = str(tmp_path / "local.csv")
    generate_synthetic("local", small_trace, 120, seed=1).to_csv(data)
    result = experiments.run_compare(data, str(tmp_path / "out"), experiments.DQNConfig(learning_starts=30,
                                                                                       batch_size=16))
    assert result["accuracy"]["always_local"] == 1.0


def test_sweep_summarises_mean_and_spread(tmp_path):
    summary = experiments.run_sweep("cloud", [1, 2], 200, str(tmp_path), experiments.DQNConfig(learning_starts=50))
    assert summary["accuracy"]["values"] and len(summary["accuracy"]["values"]) == 2
    assert {"mean", "std", "min", "max"} <= set(summary["accuracy"])
    assert os.path.exists(tmp_path / "seed_1" / "metrics.json") and os.path.exists(tmp_path / "summary.json")


def test_generate_command_writes_npz_and_csv(tmp_path):
    out = str(tmp_path / "cloud.npz")
    assert experiments.main(["generate", "--kind", "cloud", "--steps", "50", "--seed", "3", "--out", out]) == 0
    table = experiments.TransitionTable.load_npz(out)
    assert len(table) == 50 and table.metadata["kind"] == "cloud"
    assert len(experiments.TransitionTable.from_csv(str(tmp_path / "cloud.csv"))) == 50


# --- command-line values and strict JSON -----------------------------

def _no_work(*args, **kwargs):
    raise AssertionError("work started before the command-line values were checked")


def test_absurd_learning_rates_and_sizes_are_refused_by_validation(tmp_path, capsys):
    out = str(tmp_path / "o")
    for assignment, message in [("learning_rate=1e308", "learning_rate must be in (0, 1]"),
                                ("weight_decay=1e308", "weight_decay must be in [0, 1]"),
                                ("replay_capacity=1000000000000", "replay_capacity must be at most")]:
        assert experiments.main(["synthetic", "--kind", "cpu", "--out", out, "--set", assignment]) == 2, assignment
        err = capsys.readouterr().err
        assert err.startswith("error: invalid DQN configuration: ") and message in err, err
    assert not os.path.exists(out)


def test_set_seed_is_not_overridden_by_the_default_of_seed(tmp_path, capsys):
    out = tmp_path / "seeded"
    assert experiments.main(["synthetic", "--kind", "cloud", "--steps", "120", "--out", str(out),
                             "--set", "seed=7", "--set", "learning_starts=50"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["seed"] == 7 and metrics["dqn_config"]["seed"] == 7
    capsys.readouterr()
    assert experiments.main(["synthetic", "--kind", "cloud", "--steps", "120", "--out", str(out), "--seed", "3",
                             "--set", "seed=7"]) == 2
    assert "--seed 3 and --set seed=7 disagree" in capsys.readouterr().err
    assert experiments.main(["sweep", "--kind", "cloud", "--seeds", "1", "2", "--out", str(out),
                             "--set", "seed=7"]) == 2
    assert "--seeds" in capsys.readouterr().err


def test_generate_writes_exactly_the_files_it_names(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert experiments.main(["generate", "--kind", "cloud", "--steps", "20", "--out", "t.csv"]) == 2
    assert "--out must end in .npz" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []
    assert experiments.main(["generate", "--kind", "cloud", "--steps", "20", "--out", "t.npz"]) == 0
    assert sorted(os.listdir(tmp_path)) == ["t.csv", "t.npz"]
    assert "wrote t.npz and t.csv" in capsys.readouterr().out


def test_save_npz_writes_the_path_it_is_given(tmp_path, small_trace):
    table = generate_synthetic("cloud", small_trace, 10, seed=1)
    table.save_npz(str(tmp_path / "table.bin"))
    assert os.listdir(tmp_path) == ["table.bin"]
    assert len(experiments.TransitionTable.load_npz(str(tmp_path / "table.bin"))) == 10


@pytest.mark.parametrize("command", [
    ["generate", "--kind", "cpu", "--steps", "20", "--out", "{blocked}/t.npz"],
    ["synthetic", "--kind", "cpu", "--steps", "20", "--out", "{blocked}/dir"],
    ["compare", "--data", "{data}", "--out", "{blocked}/dir"],
    ["sweep", "--kind", "cpu", "--seeds", "1", "--steps", "20", "--out", "{blocked}/dir"],
])
def test_an_unwritable_out_is_an_error_before_any_work(tmp_path, capsys, monkeypatch, small_trace, command):
    blocked = tmp_path / "a_file"  # a regular file: nothing can be written below it, not even by root
    blocked.write_text("")
    data = str(tmp_path / "data.npz")
    generate_synthetic("cpu", small_trace, 40, seed=1).save_npz(data)
    for name in ("generate_synthetic", "run_online", "run_synthetic", "run_sweep", "run_compare"):
        monkeypatch.setattr(experiments, name, _no_work)
    args = [part.format(blocked=blocked, data=data) for part in command]
    assert experiments.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "a_file" in err and "cannot write" in err, err


def _strict_json(path):
    def refuse(constant):
        raise ValueError(f"{path} holds {constant}, which strict JSON parsers reject")
    return json.loads(path.read_text(), parse_constant=refuse)


def test_comparison_json_is_strict_json(tmp_path, small_trace):
    # Always-local data: the DQN never switches to the cloud, so there is no CPU threshold (NaN in memory).
    data = str(tmp_path / "local.npz")
    generate_synthetic("local", small_trace, 120, seed=1).save_npz(data)
    result = experiments.run_compare(data, str(tmp_path / "out"), experiments.DQNConfig(learning_starts=30,
                                                                                       batch_size=16))
    assert np.isnan(result["learned_threshold"])
    written = _strict_json(tmp_path / "out" / "comparison.json")
    assert written["learned_threshold"] is None and written["accuracy"]["always_local"] == 1.0
    assert "no threshold" in (tmp_path / "out" / "comparison.md").read_text()


