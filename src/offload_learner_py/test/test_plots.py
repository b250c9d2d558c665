import os

import numpy as np

from offload_learner_py.offline.plots import (plot_accuracy_bars, plot_action_vs_cpu, plot_action_vs_input_size,
                                      plot_confusion_matrix, plot_training)


def _is_png(path):
    with open(path, "rb") as image:
        return image.read(8) == b"\x89PNG\r\n\x1a\n" and os.path.getsize(path) > 1000


def test_every_figure_is_written(tmp_path):
    rng = np.random.default_rng(0)
    loss = np.where(rng.random(300) < 0.5, rng.random(300), np.nan)
    actions = rng.integers(0, 2, 300)
    paths = [
        plot_training(loss, rng.uniform(-1, 1, 300), str(tmp_path / "training.png")),
        plot_action_vs_input_size(10.0 ** rng.uniform(-4, 0, 300), actions, str(tmp_path / "d.png")),
        plot_action_vs_cpu(rng.uniform(0.5, 0.7, 300), actions, str(tmp_path / "u.png"), 0.61, 0.6),
        plot_action_vs_cpu(rng.uniform(0.5, 0.7, 300), actions, str(tmp_path / "u_nan.png"), float("nan")),
        plot_confusion_matrix([[10, 2], [3, 15]], str(tmp_path / "confusion.png")),
        plot_accuracy_bars({"dqn": 0.83, "lstm": 0.74}, str(tmp_path / "bars.png")),
    ]
    assert all(_is_png(path) for path in paths)
