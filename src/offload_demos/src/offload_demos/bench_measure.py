"""bench-policies' figures of one policy from its runs' bags and summaries (the pooled request log, the oracle
on probes, the robot's whole CPU from each run's samples)."""
import pathlib

import numpy as np

from offload_msgs.srv import PlanPathResponse
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.data.bags import read_bags
from offload_learner_py.online.breaker import OPEN
from offload_learner_py.offline.summary import delivered_figures
from offload_demos import robot_cpu

# PlanPath statuses of a cloud call the link failed (offload_msgs/PlanPath: CLOUD_TIMEOUT, CLOUD_ERROR).
LINK_FAILED = (PlanPathResponse.CLOUD_TIMEOUT, PlanPathResponse.CLOUD_ERROR)


def measure(run_dirs, cloud_timeout_s: float) -> dict:
    """The figures of one policy over its runs (repeats pooled: every request of every run counts once)."""
    run_dirs = [run_dirs] if isinstance(run_dirs, pathlib.Path) else list(run_dirs)
    data = read_bags([str(run_dir / "offload.bag") for run_dir in run_dirs], workers=1)
    if data.report.failed:
        raise RuntimeError(data.report.failed[0].error)
    figures = delivered_figures(data.log, cloud_timeout_s)
    if "mean_s" not in figures:
        raise RuntimeError(f"no request was answered in {', '.join(map(str, run_dirs))}: see demo.log beside it")
    table = data.transition_table({})
    if len(table):
        figures["probe_oracle_mean_s"] = float(np.minimum(table.local_s, table.cloud_s).mean())
        figures["probe_steps"] = len(table)
        # Both sides of every probe, for the hindsight threshold search (offload_demos.hindsight); popped by the bench
        figures["probe_rows"] = (table.input_size, table.local_s, table.cloud_s)
    log = data.log
    answered = np.asarray(log["has_outcome"], dtype=bool)
    if len(run_dirs) == 1:
        # Both sides' latencies of every request in request order (NaN: not measured or no path), for the live
        # oracle's actions (offload_demos.hindsight.faster_sides); popped by the bench.
        order = np.argsort(np.asarray(log["request_id"]), kind="stable")
        figures["request_sides_s"] = tuple(np.where(
            answered & np.asarray(log[f"outcome_{side}_measured"], dtype=bool)
            & (np.asarray(log[f"outcome_{side}_status"]) == PlanPathResponse.OK),
            np.asarray(log[f"outcome_{side}_s"], dtype=np.float64), np.nan)[order] for side in ("local", "cloud"))
    delivered_s = np.asarray(log["outcome_delivered_s"], dtype=np.float64)
    # Where both sides ran every request (the hedge run), the side delivered first is the oracle's choice: what
    # the oracle would have offloaded, and the robot planning CPU it would have spent (the local plans that won;
    # a losing local plan's CPU is the probe's cost, not the oracle's).
    delivered = np.asarray(log["outcome_delivered"])[answered]
    figures["cloud_share"] = float(np.mean(delivered == CLOUD))
    figures["first_local_cpu_s_per_request"] = float(np.mean(np.where(
        delivered == LOCAL, np.asarray(log["outcome_robot_cpu_s"], dtype=np.float64)[answered], 0.0)))
    figures["delivered_s"] = delivered_s[answered].tolist()
    # Once the breaker has opened, what a request waited beyond its own local plan (the bar: at most the
    # hedge deadline, and nothing at all for a request the open breaker routed locally).
    opened = np.nonzero(np.asarray(log["breaker"], dtype=object) == OPEN)[0]
    if len(opened):
        after = answered & (np.arange(len(log)) >= opened[0]) & (np.asarray(log["outcome_delivered"]) == 0)
        excess = delivered_s[after] - np.asarray(log["outcome_local_s"], dtype=np.float64)[after]
        figures["worst_wait_beyond_local_after_trip_s"] = float(np.nanmax(excess)) if len(excess) else 0.0
        figures["max_deadline_s"] = float(np.nanmax(np.asarray(log["deadline_s"], dtype=np.float64)))
    figures["cloud_failures"] = int(np.sum(answered & np.asarray(log["outcome_cloud_measured"], dtype=bool)
                                           & np.isin(np.asarray(log["outcome_cloud_status"]), LINK_FAILED)))
    figures["run_dir"] = ", ".join(map(str, run_dirs))
    order = [bag.path for bag in data.report.bags]
    # The robot's whole CPU (everything in its cgroup; the workload apart), each run over its own requests'
    # span, the runs pooled; None when a run has no samples (a run from before them).
    bag_of = np.asarray(log["bag"])
    runs = [robot_cpu.run_robot_cpu(run_dir / robot_cpu.SAMPLES_FILE,
                                    np.asarray(log["stamp_ns"])[bag_of == order.index(str(run_dir / "offload.bag"))],
                                    delivered_s[bag_of == order.index(str(run_dir / "offload.bag"))])
            for run_dir in run_dirs]
    figures["robot_cpu"] = robot_cpu.pool(runs)
    for name in ("total", "workload"):
        figures[f"robot_{name}_cpu_s_per_request"] = (figures["robot_cpu"] or {}).get(f"{name}_cpu_s_per_request")
    # Each run's request arrivals at the learner, seconds after its first: how closely they kept the open-loop schedule.
    stamps = np.asarray(log["stamp_ns"], dtype=np.float64)
    figures["arrivals_s"] = [((stamps[bag_of == k] - stamps[bag_of == k].min()) / 1e9).tolist()
                             for k in range(len(order)) if np.any(bag_of == k)]
    if len(run_dirs) > 1:     # each run's: the spread between repeats is the noise of the machine (mean_ratio.py)
        run = np.asarray(log["bag"])[answered]        # index into the reader's (sorted) bag list
        figures["run_delivered_s"] = [delivered_s[answered][run == order.index(str(run_dir / "offload.bag"))]
                                      for run_dir in run_dirs]     # popped by the bench
        figures["run_means_s"] = [float(run.mean()) for run in figures["run_delivered_s"]]
    return figures
