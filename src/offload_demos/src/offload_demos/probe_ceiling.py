"""How much of the best hindsight threshold's probe regret the DQN could remove on a scenario had its learning met
every request's both sides, against what the bench's learning run gave it.

A bench-policies run with two or more hedge repeats has, in each, both sides of every request (every phase of the
scenario). The DQN trained on one hedge run's rows (offline/retrain's training, the fleet learner's: every row alike)
and scored on another hedge run's probes is the method with all the data one pass of the scenario holds, judged on
the same conditions met again: a ceiling for what more learning, a longer learning run or the fleet could buy with
this state. Scored on the run it trained on, it would learn that run's own noise (printed as `in-sample`: no
ceiling). Figures are probe regrets (offload_demos.oracle_agreement: the latency of the side taken less the faster
side's, on the scored run's probes) and the share of threshold_best's regret removed.

    python -m offload_demos.probe_ceiling runs/bench-policies-<time> [--seeds 1,2]
"""
import argparse
import json
import pathlib
import sys

import numpy as np

from offload_learner_py.core.checkpoint import load_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.data.bags import read_bags
from offload_learner_py.data.records import cloud_answered, transition_table
from offload_learner_py.offline.retrain import train_offline
from offload_demos.oracle_agreement import agreement, runs_of


def hedge_rows(run_dir: pathlib.Path):
    """(transition table, which rows' cloud side answered) of one run's bag."""
    data = read_bags([str(run_dir / "offload.bag")], workers=1)
    if data.report.failed:
        raise RuntimeError(data.report.failed[0].error)
    return transition_table(data.log), cloud_answered(data.log)


def regret_s(actions, table) -> float:
    return agreement(np.asarray(actions), table.local_s, table.cloud_s)["probe_regret_s"]


def cross_run(runs, seeds) -> dict:
    """Per scored run k: the mean probe regret of DQNs trained on each other run (one per seed), and in-sample."""
    agents = [(j, train_offline(table, DQNConfig(seed=seed), cloud_answered=answered).agent)
              for seed in seeds for j, (table, answered) in enumerate(runs)]
    figures = {}
    for k, (scored, _) in enumerate(runs):
        regrets = [(j == k, regret_s(agent.greedy_actions(scored.states), scored)) for j, agent in agents]
        figures[k] = {"cross_run_s": float(np.mean([r for inside, r in regrets if not inside])),
                      "in_sample_s": float(np.mean([r for inside, r in regrets if inside]))}
    return figures


def _cell(regret, rule) -> str:
    if regret is None:
        return f"{'n/a':>18}"
    share = f" ({100 * (1 - regret / rule):.0f} %)" if rule > 0 else ""
    return f"{f'{1e3 * regret:.2f}{share}':>18}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bench_dir", type=pathlib.Path)
    parser.add_argument("--seeds", default="1,2", help="comma list of training seeds, each run's figure their mean")
    args = parser.parse_args(argv)
    hedges = runs_of(args.bench_dir, "hedge")
    if len(hedges) < 2:
        parser.error(f"{args.bench_dir} needs two or more hedge repeats (--repeats 2): one run cannot score another")
    try:
        threshold = json.loads((args.bench_dir / "results.json").read_text())["threshold_best"]["threshold"]
    except (OSError, ValueError, KeyError, TypeError) as err:
        parser.error(f"{args.bench_dir}: no threshold_best in results.json ({err})")
    checkpoints = sorted((args.bench_dir / "learning").glob("*/checkpoint.pt"))
    try:
        runs = [hedge_rows(run) for run in hedges]
        learned = load_checkpoint(str(checkpoints[0])) if checkpoints else None
        figures = cross_run(runs, [int(seed) for seed in args.seeds.split(",")])
    except (RuntimeError, OSError, ValueError) as err:     # a corrupt bag or checkpoint, a run with no probe
        parser.error(f"{args.bench_dir}: {err}")
    print(f"probe regret ms on each hedge run (share of threshold_best's d_t > {threshold:.4g} removed)")
    print(f"{'scored run':<12}{'threshold_best':>16}{'learning run':>18}{'ceiling':>18}{'in-sample':>18}")
    for k, (table, _) in enumerate(runs):
        rule = regret_s((table.input_size > threshold).astype(np.int64), table)
        cells = [regret_s(learned.greedy_actions(table.states), table) if learned else None,
                 figures[k]["cross_run_s"], figures[k]["in_sample_s"]]
        print(f"{'hedge ' + str(k + 1):<12}{1e3 * rule:>16.2f}" + "".join(_cell(cell, rule) for cell in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
