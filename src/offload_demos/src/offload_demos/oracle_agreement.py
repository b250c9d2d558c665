"""How close each policy's choices came to the oracle's, request by request, in a bench-policies run directory.

A live mean moves by several per cent between two runs of one policy on this shared machine, so a policy's mean
alone says little about its choices. This compares the choices themselves: for request k, the side a policy took
against the side that was faster in the hedge run's probes (the oracle's actions the bench wrote,
`oracle_actions.txt`), and what that choice would have cost on those probes (the probe regret: the hedge run's
latency of the side taken less the faster side's, averaged over the requests). The probe latencies are those of the
hedge run, where every request also planned locally, so the regret weighs the choices, not the policy's live
latency.

    python -m offload_demos.oracle_agreement runs/bench-policies-<time>
"""
import argparse
import pathlib
import sys

import numpy as np

from offload_learner_py.data.bags import read_bags
from offload_demos.bench_measure import measure
from offload_demos.hindsight import faster_sides


def request_actions(run_dir: pathlib.Path) -> np.ndarray:
    """The side each request of one run was routed to, in request order."""
    data = read_bags([str(run_dir / "offload.bag")], workers=1)
    if data.report.failed:
        raise RuntimeError(data.report.failed[0].error)
    log = data.log
    return np.asarray(log["action"], dtype=np.int64)[np.argsort(np.asarray(log["request_id"]), kind="stable")]


def agreement(actions, local_s, cloud_s) -> dict:
    """A policy's choices against the probes' faster sides, over the requests both have."""
    local_s, cloud_s = np.asarray(local_s, dtype=np.float64), np.asarray(cloud_s, dtype=np.float64)
    n = min(len(actions), len(local_s))
    actions, local_s, cloud_s = np.asarray(actions[:n]), local_s[:n], cloud_s[:n]
    oracle = faster_sides(local_s, cloud_s)
    both = ~(np.isnan(local_s) | np.isnan(cloud_s))
    regret = np.where(actions == 1, cloud_s, local_s) - np.minimum(local_s, cloud_s)
    return {"requests": int(n), "agree": float(np.mean(actions == oracle)), "cloud_share": float(np.mean(actions)),
            "oracle_cloud_share": float(np.mean(oracle)), "probe_regret_s": float(np.mean(regret[both]))}


def runs_of(bench_dir: pathlib.Path, policy: str) -> list:
    """A policy's run directories (one, or one per repeat)."""
    return sorted(path.parent for path in (bench_dir / policy).glob("**/offload.bag"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bench_dir", type=pathlib.Path)
    parser.add_argument("--cloud-timeout-s", type=float, default=5.0)
    args = parser.parse_args(argv)
    hedge = runs_of(args.bench_dir, "hedge")
    if not hedge:
        parser.error(f"{args.bench_dir} has no hedge run")
    local_s, cloud_s = measure(hedge[0], args.cloud_timeout_s)["request_sides_s"]
    print(f"against the faster side of each request in {hedge[0]} ({100 * np.mean(faster_sides(local_s, cloud_s)):.0f} % "
          "cloud); probe regret: the hedge run's latency of the side taken less the faster side's, mean per request")
    print(f"{'policy':<16}{'run':>5}{'cloud %':>9}{'agree %':>9}{'probe regret ms':>17}")
    for policy in sorted(path.name for path in args.bench_dir.iterdir() if path.is_dir()):
        for k, run in enumerate(runs_of(args.bench_dir, policy)):
            actions = request_actions(run)
            if not len(actions):
                continue      # a run that failed before its first request
            figures = agreement(actions, local_s, cloud_s)
            print(f"{policy:<16}{k + 1:>5}{100 * figures['cloud_share']:>9.0f}{100 * figures['agree']:>9.1f}"
                  f"{1e3 * figures['probe_regret_s']:>17.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
