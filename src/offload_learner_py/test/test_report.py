"""The section V report from bags: every figure, the paper's numbers beside ours, markdown and a
self-contained HTML page."""
import json
import os
import re

import numpy as np
from PIL import Image

from bagtools import make_requests, write
from offload_learner_py.data import bags
from offload_learner_py.offline import report
from offload_learner_py.offline import retrain
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.evaluation import evaluate

FIGURES = ("fig6_loss_reward.png", "fig7_action_vs_input_size.png", "fig11_action_vs_cpu.png", "fig12_confusion.png",
           "fig13_dqn_vs_lstm.png")


def test_the_report_renders_every_figure_with_the_papers_numbers_beside_ours(tmp_path):
    path = write(tmp_path / "run.bag", make_requests(240, seed=2, probe_every=1) + make_requests(
        60, seed=3, probe_every=1000, first_id=5000))   # the last 59 with one latency
    out = tmp_path / "report"
    md_path = report.report([path], str(out), gradient_steps=60, lstm_epochs=2)
    md = open(md_path).read()
    for name in FIGURES:
        with Image.open(out / "figures" / name) as image:
            assert image.format == "PNG" and image.size[0] > 200
        assert f"figures/{name}" in md
    for published in ("71.28", "88.38", "73.46", "140.88", "175.81", "146.09", "1.1", "0.61", "84", "81.62",
                      "72.08", "83.32", "74.12"):
        assert published in md, published
    numbers = json.load(open(out / "report.json"))
    assert numbers["requests"] == 300 and numbers["probe_rows"] == 241
    table = bags.read_bags([path]).transition_table()
    scores = evaluate(table.action, table)
    assert numbers["latency"]["mean_ms"]["chosen"] == scores["mean_latency_s"] * 1000
    assert f"{scores['mean_latency_s'] * 1000:.2f}" in md
    assert f"{scores['mean_latency_always_local_s'] * len(table):.2f}" in md   # cumulative, seconds
    assert set(numbers["fig13"]) == {"DQN, first 500", "LSTM, first 500", "DQN, all", "LSTM, all"}
    page = open(out / "report.html").read()
    assert page.count('src="data:image/png;base64,') == len(FIGURES)
    assert not re.search(r'src="(?!data:)', page)   # self-contained: nothing to fetch
    assert "<table>" in page and "71.28" in page
    assert "SNIPS (ms)" in md and "probes only (ms)" in md


def test_the_model_option_reads_the_offload_point_from_that_checkpoint(tmp_path):
    path = write(tmp_path / "run.bag", make_requests(120, seed=4))
    data = bags.read_bags([path])
    retrain.retrain(data, str(tmp_path / "model"), DQNConfig(seed=1), gradient_steps=50)
    checkpoint = str(tmp_path / "model" / "checkpoint.pt")
    report.report(out_dir=str(tmp_path / "r"), model=checkpoint, data=data, gradient_steps=20, lstm_epochs=1)
    numbers = json.load(open(tmp_path / "r" / "report.json"))
    assert checkpoint in numbers["q_source"]


def test_report_run_uses_the_run_directorys_bag_and_checkpoint(tmp_path):
    run = tmp_path / "20260101-000000"
    run.mkdir()
    path = write(run / "offload.bag", make_requests(100, seed=5))
    retrain.retrain(bags.read_bags([path]), str(tmp_path / "m"), DQNConfig(seed=1), gradient_steps=20)
    os.replace(tmp_path / "m" / "checkpoint.pt", run / "checkpoint.pt")
    os.replace(path, str(run / "offload.bag.active"))   # the recorder was stopped before closing it
    md = report.report_run(str(run), gradient_steps=20, lstm_epochs=1)
    assert md == str(run / "report" / "report.md")
    numbers = json.load(open(run / "report" / "report.json"))
    assert numbers["requests"] == 100 and str(run / "checkpoint.pt") in numbers["q_source"]


def test_too_little_data_gives_a_report_that_says_so_and_status_2(tmp_path, capsys):
    path = write(tmp_path / "few.bag", make_requests(5))
    assert report.main([path, "--out", str(tmp_path / "r"), "--quiet"]) == 2
    assert "Not enough data" in open(tmp_path / "r" / "report.md").read()
    assert os.path.exists(tmp_path / "r" / "report.html")
    assert "report:" in capsys.readouterr().out
    assert not np.isnan(0.0)


def test_the_report_shows_its_progress(tmp_path, capsys):
    """Minutes of fitting must not be silent: a progress bar names each step on stderr."""
    from bagtools import make_requests, write
    from offload_learner_py.offline import report as report_module
    bag = write(tmp_path / "run.bag", make_requests(60, probe_every=1))
    report_module.report([bag], str(tmp_path / "out"), gradient_steps=20, lstm_epochs=2, workers=1, progress=True)
    err = capsys.readouterr().err
    for step in ("report: Q-function", "report: figures 6-12", "report: Fig. 13", "report: latency table"):
        assert step in err, err[-500:]


def test_the_report_page_wraps_wide_blocks_and_flags_a_tiny_held_out_set(tmp_path):
    from bagtools import make_requests, write
    from offload_learner_py.offline import report as report_module
    bag = write(tmp_path / "run.bag", make_requests(60, probe_every=1))
    path = report_module.report([bag], str(tmp_path / "out"), gradient_steps=20, lstm_epochs=2, workers=1)
    page = open(tmp_path / "out" / "report.html").read()
    assert "pre{white-space:pre-wrap" in page
    text = open(path).read()
    assert "held-out 20 % is under 30 steps" in text and "repeat the 'all' bars" in text
    assert "Compare the rows with each other" in text
