"""The summary of an online run: the chosen actions against always-local, always-cloud and the oracle
on the run's own probe steps, over the whole run and its second half; accuracy; timeouts; paths
delivered; the learned offload point in d_t and threshold in u_t; and the oracle's cloud share by
tercile of each state field (d_t, u_t, b_t), which shows whether each feature matters on this run."""
import math
from typing import Callable, Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.dqn import greedy_actions
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.evaluation import accuracy, evaluate, learned_cpu_threshold, oracle_actions
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.core.reward import DEFAULT_CLOUD_TIMEOUT_S
from offload_learner_py.data.records import NO_PATH_DELIVERED, RequestLog
from offload_learner_py.online.breaker import OPEN, SLOW

FEATURES = tuple((f.name, f.symbol) for f in STATE_SCHEMA)   # (column, label) of every state field


def learned_offload_input_size(q_values: Callable[[np.ndarray], np.ndarray], states: np.ndarray,
                               points: int = 400) -> float:
    """The d_t above which the greedy policy offloads, with u_t and b_t at their medians: Q(cloud) -
    Q(local) scanned over the observed d range (log-spaced) and its last local-to-cloud sign change
    interpolated. NaN when the policy does not switch that way in the range."""
    states = np.asarray(states, dtype=np.float64)
    d = STATE_SCHEMA.index("input_size")
    positive = states[:, d][states[:, d] > 0]
    if len(positive) < 2:
        return float("nan")
    grid = np.geomspace(positive.min(), positive.max(), points)
    probe = np.tile(np.median(states, axis=0), (points, 1))
    probe[:, d] = grid
    q = np.asarray(q_values(probe))
    difference = q[:, CLOUD] - q[:, LOCAL]
    rising = np.nonzero((difference[:-1] <= 0) & (difference[1:] > 0))[0]
    if len(rising) == 0:
        return float("nan")
    i = rising[-1]
    fraction = -difference[i] / (difference[i + 1] - difference[i])
    return float(np.exp(np.log(grid[i]) + fraction * (np.log(grid[i + 1]) - np.log(grid[i]))))


def oracle_share_by_tercile(table: TransitionTable) -> dict:
    """Per feature: the tercile bounds and the oracle's cloud share in each tercile."""
    oracle = oracle_actions(table)
    shares = {}
    for column, label in FEATURES:
        values = getattr(table, column)
        if len(values) < 3:
            shares[label] = {"bounds": [], "cloud_share": []}
            continue
        bounds = np.quantile(values, [1 / 3, 2 / 3])
        tercile = np.searchsorted(bounds, values, side="right")
        shares[label] = {"bounds": [float(b) for b in bounds],
                         "cloud_share": [float(np.mean(oracle[tercile == k] == CLOUD)) if np.any(tercile == k)
                                         else float("nan") for k in range(3)]}
    return shares


def delivered_figures(log: RequestLog, cloud_timeout_s: float = DEFAULT_CLOUD_TIMEOUT_S) -> dict:
    """What the robot got and paid, request by request, with the decisions acting: latency from arrival
    to path as the caller saw it (mean and tail), paths delivered, robot planning CPU-seconds and link
    bytes per request, cloud timeouts and the requests that waited at least the cloud timeout."""
    requests = len(log)
    answered = log["has_outcome"].astype(bool) if requests else np.zeros(0, bool)
    figures = {"requests": requests, "answered": int(answered.sum())}
    if not answered.any():
        return figures
    pick = lambda name: np.asarray(log[name], dtype=np.float64)[answered]  # noqa: E731
    delivered_s = pick("outcome_delivered_s")
    breaker = np.asarray(log["breaker"], dtype=object)[answered]

    def cost_per_request(name: str, where=None) -> float:   # NaN in bags from before robot cost accounting
        values = pick(name) if where is None else pick(name)[where]
        return float(np.mean(values)) if len(values) and np.all(np.isfinite(values)) else float("nan")

    # The requests that asked the cloud (its reply, failure or timeout measured): what #30's bridge bar is per.
    asked_cloud = pick("outcome_cloud_measured") > 0
    figures.update({
        "paths_delivered": int(np.sum(pick("outcome_delivered") != NO_PATH_DELIVERED)),
        "mean_s": float(np.mean(delivered_s)), "p50_s": float(np.percentile(delivered_s, 50)),
        "p95_s": float(np.percentile(delivered_s, 95)), "p99_s": float(np.percentile(delivered_s, 99)),
        "max_s": float(np.max(delivered_s)),
        "robot_cpu_s_per_request": cost_per_request("outcome_robot_cpu_s"),
        "bridge_cpu_s_per_request": cost_per_request("outcome_bridge_cpu_s"),
        "bridge_cpu_s_per_cloud_request": cost_per_request("outcome_bridge_cpu_s", asked_cloud),
        "cloud_calls": int(np.sum(asked_cloud)),
        "learner_cpu_s_per_request": cost_per_request("outcome_learner_cpu_s"),
        "link_bytes_per_request": float(np.mean(pick("outcome_link_bytes_sent") + pick("outcome_link_bytes_received"))),
        "cloud_timeouts": int(np.sum(pick("outcome_cloud_timeout") > 0)),
        "waited_the_timeout": int(np.sum(delivered_s >= cloud_timeout_s)),
        "hedged": int(np.sum(pick("outcome_hedged") > 0)),
        "probes": int(np.sum(np.asarray(log["probe"], dtype=bool)[answered])),
        "breaker_open": int(np.sum(breaker == OPEN)),
        "slow_link_local": int(np.sum(breaker == SLOW)),
    })
    return figures


def summarise(log: RequestLog, table: TransitionTable, q_values: Optional[Callable] = None) -> dict:
    """Everything the demo prints, as plain JSON-able numbers."""
    requests = len(log)
    answered = log["has_outcome"].astype(bool) if requests else np.zeros(0, bool)
    delivered = int(np.sum(answered & (log["outcome_delivered"] != NO_PATH_DELIVERED))) if requests else 0
    timeouts = int(np.sum(answered & log["outcome_cloud_timeout"].astype(bool))) if requests else 0
    result = {"requests": requests, "answered": int(answered.sum()), "paths_delivered": delivered,
              "probe_steps": len(table), "cloud_timeouts": timeouts, "cloud_calls": 0,
              "policy": str(log["policy"][0]) if requests else ""}
    if requests:
        result["delivered"] = delivered_figures(log)
        result["cloud_calls"] = result["delivered"].get("cloud_calls", 0)   # none answered: none counted
        result["mean_delivered_s"] = result["delivered"].get("mean_s", float("nan"))
    if len(table) == 0:
        return result
    result["whole_run"] = evaluate(table.action, table)
    half = len(table) // 2
    second = table.slice(half, len(table))
    result["second_half"] = evaluate(second.action, second)
    result["second_half_beats_both"] = bool(result["second_half"]["mean_latency_s"] < min(
        result["second_half"]["mean_latency_always_local_s"], result["second_half"]["mean_latency_always_cloud_s"]))
    oracle = oracle_actions(table)
    result["oracle_cloud_share"] = float(np.mean(oracle == CLOUD))
    result["oracle_mean_latency_s"] = float(np.minimum(table.local_s, table.cloud_s).mean())
    result["oracle_cumulative_latency_s"] = float(np.minimum(table.local_s, table.cloud_s).sum())
    result["second_half_oracle_mean_latency_s"] = float(np.minimum(second.local_s, second.cloud_s).mean())
    result["oracle_cloud_share_by_tercile"] = oracle_share_by_tercile(table)
    if q_values is not None:
        states = table.states
        q = np.asarray(q_values(states))
        greedy = greedy_actions(q)
        result["final_greedy_accuracy"] = accuracy(greedy, table)
        result["final_greedy_second_half_accuracy"] = accuracy(greedy[half:], second)
        result["learned_offload_input_size"] = learned_offload_input_size(q_values, states)
        result["learned_cpu_threshold"] = learned_cpu_threshold(q_values, states)
    return result


def _ms(seconds: float) -> str:
    return f"{1000.0 * seconds:8.1f}"


def format_summary(summary: dict) -> str:
    """The table printed at the end of `make demo`."""
    lines = [f"requests {summary['requests']}, paths delivered {summary['paths_delivered']}/"
             f"{summary['requests']}, probe steps {summary['probe_steps']}, cloud timeouts "
             f"{summary['cloud_timeouts']}/{summary['cloud_calls']} cloud calls, policy {summary['policy']}"]
    delivered = summary.get("delivered", {})
    if "mean_s" in delivered:
        lines.append(f"as the caller saw it: mean {_ms(delivered['mean_s']).strip()} ms, p95 "
                     f"{_ms(delivered['p95_s']).strip()} ms, p99 {_ms(delivered['p99_s']).strip()} ms; per request: robot "
                     f"planning CPU {1000 * delivered['robot_cpu_s_per_request']:.1f} ms, cloud bridge CPU "
                     f"{1000 * delivered['bridge_cpu_s_per_request']:.1f} ms, learner CPU "
                     f"{1000 * delivered['learner_cpu_s_per_request']:.1f} ms, link "
                     f"{delivered['link_bytes_per_request'] / 1024:.1f} KiB")
    unfinished = summary["requests"] - summary["answered"]
    if unfinished:
        lines.append(f"({unfinished} request(s) still in flight when the run stopped: no outcome recorded)")
    if "whole_run" not in summary:
        lines.append("no probe step finished: nothing to compare")
        return "\n".join(lines)
    whole, second = summary["whole_run"], summary["second_half"]
    lines.append("")
    lines.append(f"{'':28}{'whole run':>22}{'second half':>22}")
    lines.append(f"{'latency (ms)':28}{'mean':>10}{'total (s)':>12}{'mean':>10}{'total (s)':>12}")

    def row(name, mean_w, total_w, mean_s, total_s):
        lines.append(f"{name:28}{_ms(mean_w):>10}{total_w:12.2f}{_ms(mean_s):>10}{total_s:12.2f}")

    n_whole, n_second = whole["steps"], second["steps"]
    row(f"chosen ({summary['policy']})", whole["mean_latency_s"], whole["cumulative_latency_s"],
        second["mean_latency_s"], second["cumulative_latency_s"])
    row("always local", whole["mean_latency_always_local_s"], whole["mean_latency_always_local_s"] * n_whole,
        second["mean_latency_always_local_s"], second["mean_latency_always_local_s"] * n_second)
    row("always cloud", whole["mean_latency_always_cloud_s"], whole["mean_latency_always_cloud_s"] * n_whole,
        second["mean_latency_always_cloud_s"], second["mean_latency_always_cloud_s"] * n_second)
    row("oracle", summary["oracle_mean_latency_s"], summary["oracle_cumulative_latency_s"],
        summary["second_half_oracle_mean_latency_s"], summary["second_half_oracle_mean_latency_s"] * n_second)
    lines.append(f"{'savings vs local (%)':28}{whole['savings_vs_local_pct']:10.1f}{'':12}"
                 f"{second['savings_vs_local_pct']:10.1f}")
    lines.append(f"{'savings vs cloud (%)':28}{whole['savings_vs_cloud_pct']:10.1f}{'':12}"
                 f"{second['savings_vs_cloud_pct']:10.1f}")
    lines.append(f"{'beats both fixed policies':28}{'':22}{'yes' if summary['second_half_beats_both'] else 'no':>10}")
    lines.append(f"{'accuracy, actions taken (%)':28}{100 * whole['accuracy']:10.1f}{'':12}"
                 f"{100 * second['accuracy']:10.1f}")
    if "final_greedy_accuracy" in summary:
        lines.append(f"{'accuracy, final greedy (%)':28}{100 * summary['final_greedy_accuracy']:10.1f}{'':12}"
                     f"{100 * summary['final_greedy_second_half_accuracy']:10.1f}")
        lines.append("")
        point, threshold = summary["learned_offload_input_size"], summary["learned_cpu_threshold"]
        lines.append("learned offload point: " + (f"d_t > {point:.4g}" if math.isfinite(point) else
                                                  "none in the observed d_t range") +
                     " (u_t, b_t at their medians); learned CPU threshold: " +
                     (f"u_t < {threshold:.3f}" if math.isfinite(threshold) else "none in the observed u_t range"))
    lines.append(f"oracle picks the cloud on {100 * summary['oracle_cloud_share']:.1f}% of probe steps; by tercile "
                 f"(low / mid / high):")
    for label, entry in summary["oracle_cloud_share_by_tercile"].items():
        shares = " / ".join(f"{100 * s:5.1f}%" for s in entry["cloud_share"])
        bounds = ", ".join(f"{b:.4g}" for b in entry["bounds"])
        lines.append(f"  {label}: {shares}   (tercile bounds {bounds})")
    return "\n".join(lines)
