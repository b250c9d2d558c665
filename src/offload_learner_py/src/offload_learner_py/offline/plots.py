"""Figures in the manner of the paper's Fig. 6-13, drawn with matplotlib's Agg backend (no display).
Each function writes one PNG and returns its path."""
from typing import Dict, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (the backend must be chosen first)
import numpy as np  # noqa: E402

from offload_learner_py import ACTION_NAMES, CLOUD  # noqa: E402


def _moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last `window` finite values at each step (nan until one exists)."""
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    sums = np.cumsum(np.where(finite, values, 0.0))
    counts = np.cumsum(finite)
    sums[window:] = sums[window:] - sums[:-window]
    counts[window:] = counts[window:] - counts[:-window]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def plot_training(loss: np.ndarray, reward: np.ndarray, path: str, title: str = "", window: int = 50) -> str:
    """Fig. 6/8/9/10: average loss and cumulative reward against the time step."""
    steps = np.arange(1, len(reward) + 1)
    figure, (loss_axis, reward_axis) = plt.subplots(1, 2, figsize=(11, 4))
    loss_axis.plot(steps, _moving_average(loss, window), color="tab:blue")
    loss_axis.set(xlabel="time step t", ylabel=f"average loss (last {window} steps)", title="loss")
    loss_axis.set_yscale("log")
    reward_axis.plot(steps, np.cumsum(reward), color="tab:green")
    reward_axis.set(xlabel="time step t", ylabel="cumulative reward", title="reward")
    figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def plot_action_vs_input_size(input_size: np.ndarray, actions: np.ndarray, path: str, title: str = "",
                              offload_point: Optional[float] = None) -> str:
    """Fig. 7: the chosen action of each step against its input size d_t, with the learned offload
    point (the d_t above which the greedy policy offloads) when given."""
    figure, axis = plt.subplots(figsize=(7, 4))
    steps = np.arange(len(actions))
    for action, colour in ((0, "tab:blue"), (1, "tab:orange")):
        chosen = np.asarray(actions) == action
        axis.scatter(input_size[chosen], steps[chosen], s=6, color=colour, label=ACTION_NAMES[action])
    if offload_point is not None and np.isfinite(offload_point):
        axis.axvline(offload_point, color="black", label=f"learned offload point {offload_point:.3g}")
    axis.set_xscale("log")
    axis.set(xlabel="input size d_t (normalised)", ylabel="time step t", title=title or "action vs input size")
    axis.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def plot_action_vs_cpu(cpu_availability: np.ndarray, actions: np.ndarray, path: str,
                       learned_threshold: Optional[float] = None, true_threshold: Optional[float] = None,
                       title: str = "") -> str:
    """Fig. 11: the chosen action against CPU availability u_t, with the learned threshold."""
    figure, axis = plt.subplots(figsize=(7, 4))
    actions = np.asarray(actions)
    jitter = np.random.default_rng(0).uniform(-0.15, 0.15, len(actions))  # fixed: the figure is reproducible
    axis.scatter(cpu_availability, actions + jitter, s=6, c=np.where(actions == CLOUD, "tab:orange", "tab:blue"))
    if learned_threshold is not None and np.isfinite(learned_threshold):
        axis.axvline(learned_threshold, color="black", label=f"learned threshold {learned_threshold:.3f}")
    if true_threshold is not None:
        axis.axvline(true_threshold, color="gray", linestyle="--", label=f"generating threshold {true_threshold:.2f}")
    axis.set_yticks([0, 1], [ACTION_NAMES[0], ACTION_NAMES[1]])
    axis.set(xlabel="CPU availability u_t", ylabel="action", title=title or "action vs CPU availability")
    if axis.get_legend_handles_labels()[1]:
        axis.legend(loc="center right")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def plot_confusion_matrix(matrix, path: str, title: str = "") -> str:
    """Fig. 12: rows the oracle's action, columns the chosen action."""
    matrix = np.asarray(matrix)
    figure, axis = plt.subplots(figsize=(4.5, 4))
    axis.imshow(matrix, cmap="Blues")
    for row in range(2):
        for column in range(2):
            axis.text(column, row, str(int(matrix[row, column])), ha="center", va="center",
                      color="white" if matrix[row, column] > matrix.max() / 2 else "black")
    axis.set_xticks([0, 1], ACTION_NAMES)
    axis.set_yticks([0, 1], ACTION_NAMES)
    total = matrix.sum()
    accuracy = np.trace(matrix) / total if total else float("nan")
    axis.set(xlabel="chosen action", ylabel="oracle action", title=title or f"accuracy {accuracy:.1%}")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def plot_accuracy_bars(accuracies: Dict[str, float], path: str, title: str = "") -> str:
    """Fig. 13: accuracy per policy."""
    figure, axis = plt.subplots(figsize=(max(5, 1.1 * len(accuracies)), 4))
    names = list(accuracies)
    values = [100.0 * accuracies[name] for name in names]
    bars = axis.bar(names, values, color="tab:blue")
    for bar, value in zip(bars, values):
        axis.text(bar.get_x() + bar.get_width() / 2, value + 1, f"{value:.1f}", ha="center")
    axis.set(ylabel="accuracy against the oracle (%)", ylim=(0, 110), title=title or "accuracy")
    plt.setp(axis.get_xticklabels(), rotation=20, ha="right")
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path
