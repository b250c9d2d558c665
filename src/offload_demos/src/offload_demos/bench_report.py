"""bench-policies' printed table and figure."""
import pathlib

import numpy as np

from offload_demos.gap_share import gap_share, rounds_of
from offload_demos.hindsight import gap_closed


def _ms(value, width: int) -> str:
    return f"{'n/a':>{width}}" if value is None else f"{1e3 * value:>{width}.1f}"


def format_table(results: dict) -> str:
    header = (f"{'policy':<11}{'requests':>9}{'paths':>7}{'mean ms':>9}{'p50':>8}{'p95':>8}{'p99':>8}"
              f"{'plan CPU':>9}{'bridge':>8}{'learn':>7}{'robot':>7}{'wkld':>7}{'KiB/req':>9}{'timeouts':>9}{'cloud %':>8}"
              "   (CPU: robot ms per request; plan CPU, bridge, learn: the nodes' own accounting of the planner, the "
              "bridge and the learner's learning; robot: everything on the robot's side (its cgroup), the total the "
              "policy costs; wkld: the background workload's, apart; cloud %: paths from the cloud)")
    lines = [header]
    for name, f in results["policies"].items():
        lines.append(f"{name:<11}{f['requests']:>9}{f['paths_delivered']:>7}{1e3 * f['mean_s']:>9.1f}"
                     f"{1e3 * f['p50_s']:>8.1f}{1e3 * f['p95_s']:>8.1f}{1e3 * f['p99_s']:>8.1f}"
                     f"{_ms(f['robot_cpu_s_per_request'], 9)}{_ms(f['bridge_cpu_s_per_request'], 8)}"
                     f"{_ms(f.get('learner_cpu_s_per_request') or 0.0, 7)}"
                     f"{_ms(f.get('robot_total_cpu_s_per_request'), 7)}{_ms(f.get('robot_workload_cpu_s_per_request'), 7)}"
                     f"{f['link_bytes_per_request'] / 1024:>9.1f}"
                     f"{f['cloud_timeouts']:>9}{100 * (f.get('cloud_share') or 0.0):>8.0f}")
    for name, f in results["policies"].items():
        per_cloud = f.get("bridge_cpu_s_per_cloud_request")
        if f.get("cloud_calls") and per_cloud is not None and np.isfinite(per_cloud):
            lines.append(f"{name}: the bridge's own accounting per cloud request {1e3 * per_cloud:.3f} ms "
                         f"({f['cloud_calls']} requests asked the cloud)")
        cpu = f.get("robot_cpu")
        if cpu:
            lines.append(f"{name}: robot CPU {1e3 * cpu['total_cpu_s_per_request']:.2f} ms per request by process "
                         f"({cpu['source']}): planner {1e3 * cpu['planner_cpu_s_per_request']:.2f}, bridge "
                         f"{1e3 * cpu['bridge_cpu_s_per_request']:.2f}, learner {1e3 * cpu['learner_cpu_s_per_request']:.2f}, "
                         f"recorder {1e3 * cpu.get('recorder_cpu_s_per_request', 0.0):.2f}, "
                         f"other {1e3 * cpu['other_cpu_s_per_request']:.2f}, unattributed "
                         f"{1e3 * cpu['unattributed_cpu_s_per_request']:.2f}")
    if results.get("oracle_mean_s") is not None:
        lines.append(f"{'oracle (probes)':<11}{'':>5}{1e3 * results['oracle_mean_s']:>9.1f}   (the hedge run's probes: "
                     "the faster side of every request)")
    if results.get("oracle_robot_cpu_s_per_request") is not None:
        lines.append(f"oracle: {100 * results['oracle_cloud_share']:.0f} % offloaded, robot planning CPU "
                     f"{1e3 * results['oracle_robot_cpu_s_per_request']:.1f} ms per request (the hedge run's local "
                     "plans that came first)")
    return "\n".join(lines)


def gap_oracle(results: dict):
    """(mean, label) of the gap's oracle: the live replay of each request's faster side when it ran (the same footing
    as every policy's live mean), else the probe oracle (both sides at once: not a bound for a one-sided policy)."""
    live = results["policies"].get("oracle", {}).get("mean_s")
    return (live, "oracle") if live is not None else (results.get("oracle_mean_s"), "oracle (probes)")


def gap_closed_runs(results: dict, name: str):
    """The gap closed within each round of repeats (repeat r of the policy against repeat r of threshold_best and of
    the live oracle: the runs that met the same state of the machine), so the table shows how far the pooled share
    moves between rounds; None with one repeat, without the live oracle, or when a run's mean is missing."""
    runs = rounds_of(results, name)
    if runs is None or len(runs[0]) < 2:
        return None
    return [gap_closed(best, mean, oracle) for mean, best, oracle in zip(*runs)]


def gap_closed_interval(results: dict, name: str):
    """The gap share's interval over the rounds (offload_demos.gap_share: whether the bench can tell), as a dict;
    None without the rounds gap_closed_runs needs or with a run that has no mean (it answered nothing)."""
    runs = rounds_of(results, name)
    if runs is None or len(runs[0]) < 2 or not np.all(np.isfinite(runs)):
        return None
    return gap_share(*runs)._asdict()


def scenario_rows(results: dict) -> list:
    """The scenario's report, a row per policy: mean, p99, the robot's total CPU per request and the share of the
    gap between the best threshold in hindsight (its live run) and the oracle (gap_oracle) it closes. The probe
    oracle is a row of its own, labelled so."""
    best = results["policies"].get("threshold_best", {}).get("mean_s")
    oracle, _ = gap_oracle(results)
    rows = [{"policy": name, "mean_s": f["mean_s"], "p99_s": f["p99_s"],
             "robot_total_cpu_s_per_request": f.get("robot_total_cpu_s_per_request"),
             "gap_closed": gap_closed(best, f["mean_s"], oracle), "gap_closed_runs": gap_closed_runs(results, name),
             "gap_closed_interval": gap_closed_interval(results, name)}
            for name, f in results["policies"].items()]
    if results.get("oracle_mean_s") is not None:
        rows.append({"policy": "oracle (probes)", "mean_s": results["oracle_mean_s"], "p99_s": None,
                     "robot_total_cpu_s_per_request": None,
                     "gap_closed": gap_closed(best, results["oracle_mean_s"], oracle)})
    return rows


def _shares(shares) -> str:
    return "" if not shares else ", ".join("n/a" if share is None else f"{100 * share:.0f} %" for share in shares)


def _interval(interval) -> str:
    if not interval:
        return ""
    if interval["low"] is None:
        return "no bound"
    return f"{100 * interval['low']:.0f} to {100 * interval['high']:.0f} %"


def format_scenario_table(results: dict) -> str:
    pick = results.get("threshold_best") or {}
    lines = [f"scenario {results.get('scenario', 'stationary')}: {'policy':<15}{'mean ms':>9}{'p99 ms':>9}"
             f"{'robot CPU ms/req':>18}{'gap closed':>12}{'per repeat':>22}{'95 % interval':>18}   (gap: threshold_best's "
             f"live mean to the {gap_oracle(results)[1]}'s; 100 % is that oracle, 0 the best fixed d_t rule, below 0 "
             "worse than it; per repeat: within each round of runs, how far the pooled share moves with the machine; "
             "interval: over the rounds, offload_demos.gap_share; no bound: the gap is not told apart from zero)"]
    indent = " " * len(f"scenario {results.get('scenario', 'stationary')}: ")
    for row in scenario_rows(results):
        gap = row["gap_closed"]
        lines.append(f"{indent}{row['policy']:<15}{_ms(row['mean_s'], 9)}{_ms(row['p99_s'], 9)}"
                     f"{_ms(row['robot_total_cpu_s_per_request'], 18)}"
                     f"{'n/a' if gap is None else f'{100 * gap:.0f} %':>12}{_shares(row.get('gap_closed_runs')):>22}"
                     f"{_interval(row.get('gap_closed_interval')):>18}")
    oracle, label = gap_oracle(results)
    under = [row["policy"] for row in scenario_rows(results) if not row["policy"].startswith("oracle")
             and oracle is not None and row["mean_s"] < oracle]
    if under and label == "oracle":
        lines.append(f"{indent}below the live oracle: {', '.join(under)}. The oracle replays each request's faster "
                     "side in the hedge run, where every request also planned locally: a policy that sends fewer "
                     "requests to the robot's planner makes its local plans faster (its CPU budget is shared), so "
                     "the replay is not a lower bound either")
    elif under:
        lines.append(f"{indent}below the oracle: {', '.join(under)}. The oracle is the faster side of the hedge run's "
                     "probes, both sides planning at once on the robot's budget: not a lower bound for a policy "
                     "that runs one side, so a share over 100 % says the gap is measured against a slow oracle")
    if pick:
        lines.append(f"{indent}threshold_best: d_t > {pick['threshold']:.4g} ({100 * pick['cloud_share']:.0f} % "
                     f"offloaded), {1e3 * pick['hindsight_mean_s']:.1f} ms on the hedge run's probes (best of "
                     f"{pick['grid_size']} thresholds)")
    return "\n".join(lines)


def plot(results: dict, path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (cdf, cpu, gap) = plt.subplots(1, 3, figsize=(18, 4.5))
    names = list(results["policies"])
    for name in names:
        values = np.sort(np.asarray(results["delivered_s"][name])) * 1e3
        cdf.plot(values, np.arange(1, len(values) + 1) / len(values), label=name)
    cdf.set_xscale("log")
    cdf.set_xlabel("latency as the caller saw it (ms)")
    cdf.set_ylabel("share of requests")
    cdf.set_title(f"delivered latency, {results['map_name']}")
    cdf.legend()
    parts = (("planning (node)", "robot_cpu_s_per_request"), ("bridge (node)", "bridge_cpu_s_per_request"),
             ("learner (node)", "learner_cpu_s_per_request"), ("robot total (cgroup)", "robot_total_cpu_s_per_request"))
    width = 0.8 / len(parts)
    for k, (label, key) in enumerate(parts):
        values = [results["policies"][n].get(key) for n in names]
        cpu.bar(np.arange(len(names)) + (k - (len(parts) - 1) / 2) * width,
                [np.nan if value is None else 1e3 * value for value in values], width, label=label)
    cpu.set_xticks(np.arange(len(names)))
    cpu.set_xticklabels(names, rotation=30)
    cpu.set_ylabel("robot CPU per request (ms)")
    cpu.set_title("robot CPU per request (the workload's apart)")
    cpu.legend(fontsize="small")
    rows = [row for row in scenario_rows(results) if row["policy"] != "oracle (probes)"]
    means = [1e3 * row["mean_s"] for row in rows]
    gap.bar(np.arange(len(rows)), means, 0.6, color="tab:blue", label="mean")
    gap.plot(np.arange(len(rows)), [1e3 * row["p99_s"] for row in rows], "v", color="tab:red", label="p99")
    for reference, label, style in ((results.get("oracle_mean_s"), "oracle (probes)", "--"),
                                    (results["policies"].get("oracle", {}).get("mean_s"), "oracle (live)", "-."),
                                    (results["policies"].get("threshold_best", {}).get("mean_s"), "threshold_best", ":")):
        if reference is not None:
            gap.axhline(1e3 * reference, linestyle=style, color="black", label=label)
    for k, row in enumerate(rows):
        if row["gap_closed"] is not None:
            gap.annotate(f"{100 * row['gap_closed']:.0f} %", (k, means[k]), ha="center", va="bottom", fontsize="small")
    gap.set_xticks(np.arange(len(rows)))
    gap.set_xticklabels([row["policy"] for row in rows], rotation=30)
    gap.set_ylabel("delivered latency (ms)")
    gap.set_title(f"scenario {results.get('scenario', 'stationary')}: mean, p99, gap closed (%)")
    gap.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
