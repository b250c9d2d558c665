"""The paper's experiments as commands.

    python -m offload_learner_py.offline.experiments synthetic --kind {local,cloud,cpu} --steps N --seed S --out DIR
    python -m offload_learner_py.offline.experiments sweep --kind K --seeds 1 2 3 4 5 --steps N --out DIR
    python -m offload_learner_py.offline.experiments compare --data FILE --out DIR
    python -m offload_learner_py.offline.experiments generate --kind K --steps N --seed S --out FILE.npz

`synthetic` trains the DQN online over a synthetic stream (Algorithm 1) built on the bundled trace of
real planning times and writes DIR/metrics.json, the online transition table, a checkpoint and plots.
The headline `accuracy` is the greedy policy's decision on each step's state, taken online just
before the step is learned from, over the last half of the run; the accuracy of the actions actually
taken (10 % epsilon exploration included) is reported beside it as `accuracy_taken`. The baselines
are fitted on the first half and scored on the same last half.

`generate` writes a synthetic transition table (uniformly random logged actions) for `compare`.
`compare` splits a transition table in time (first part to fit, rest to score), fits every policy on
the same rows and writes comparison.md, comparison.json and plots.
"""
import argparse
import json
import os
import sys
from dataclasses import replace
from typing import Dict, List, Optional

import numpy as np
import torch

from offload_cloud.cli_args import bounded_float, bounded_int
from offload_learner_py.core.checkpoint import save_checkpoint
from offload_learner_py.core.config import EXPERIMENT_SCHEDULE, DQNConfig
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.evaluation import evaluate, learned_cpu_threshold
from offload_learner_py.core.lstm_baseline import LSTMConfig, LSTMPolicy
from offload_learner_py.offline.output import require_writable_dir, require_writable_file, write_json
from offload_learner_py.offline.simulation import print_progress, run_online
from offload_learner_py.offline.plots import (plot_accuracy_bars, plot_action_vs_cpu, plot_action_vs_input_size,
                                      plot_confusion_matrix, plot_training)
from offload_learner_py.core.policies import (AlwaysCloud, AlwaysLocal, DQNPolicy, InputSizeThreshold, OraclePolicy,
                                         RandomPolicy)
from offload_learner_py.core.reward import CostWeights
from offload_learner_py.core.state import STATE_FIELDS, STATE_SCHEMA
from offload_learner_py.data.synthetic import SYNTHETIC_KINDS, SyntheticSettings, generate_synthetic
from offload_learner_py.data.trace import PlanningTrace

MAX_COUNT = 10 ** 12   # steps, seeds and threads: any value a machine could run
BUNDLED_TRACE = os.path.join(os.path.dirname(__file__), "..", "data", "husky_playpen_trace.npz")


def baseline_policies(seed: int, progress: bool = False) -> list:
    """Every policy but the DQN, in report order. The LSTM reads the input size only, as in the
    paper; lstm_all_features also reads u and b, a stronger baseline than the paper's. With progress, the
    LSTM fits (the slow ones) show a bar over their epochs."""
    return [AlwaysLocal(), AlwaysCloud(), RandomPolicy(seed), InputSizeThreshold(), OraclePolicy(),
            LSTMPolicy(LSTMConfig(seed=seed), progress=progress),
            _named(LSTMPolicy(LSTMConfig(seed=seed, features=STATE_FIELDS), progress=progress), "lstm_all_features")]


def _named(policy, name: str):
    policy.name = name
    return policy


def _score_baselines(train: TransitionTable, test: TransitionTable, seed: int,
                     progress: bool = False) -> Dict[str, dict]:
    scores = {}
    for policy in baseline_policies(seed, progress):
        scores[policy.name] = evaluate(policy.fit(train).choose(test), test)
        if isinstance(policy, InputSizeThreshold):
            scores[policy.name]["threshold"] = policy.threshold
            scores[policy.name]["cloud_above"] = policy.cloud_above
    return scores


def _threshold_report(agent: DQNAgent, states: np.ndarray) -> dict:
    d = states[:, STATE_SCHEMA.index("input_size")]
    by_input_size = {f"d_q{q}": learned_cpu_threshold(agent.q_values, states, input_size=float(np.percentile(d, q)))
                     for q in (10, 50, 90)}
    return {"learned_threshold": learned_cpu_threshold(agent.q_values, states),
            "learned_threshold_by_input_size": by_input_size}


def run_synthetic(kind: str, steps: int, seed: int, out_dir: str, config: DQNConfig,
                  trace_path: str = BUNDLED_TRACE, weights: CostWeights = CostWeights(),
                  show_progress: bool = True) -> dict:
    os.makedirs(out_dir, exist_ok=True)
    trace = PlanningTrace.load_npz(trace_path)
    settings = SyntheticSettings()
    stream = generate_synthetic(kind, trace, steps, seed, weights, settings)
    agent = DQNAgent(replace(config, seed=seed))
    run = run_online(agent, stream, weights, progress=print_progress if show_progress else None)
    half = steps // 2
    test = stream.slice(half, steps)
    policies = {"dqn": evaluate(run.greedy_action[half:], test),
                "dqn_taken": evaluate(run.table.action[half:], test)}
    policies.update(_score_baselines(stream.slice(0, half), test, seed))
    metrics = {
        "kind": kind, "seed": seed, "steps": steps, "evaluated_steps": f"{half}..{steps - 1}",
        "accuracy": policies["dqn"]["accuracy"],
        "accuracy_taken": policies["dqn_taken"]["accuracy"],
        "accuracy_greedy_whole_run": evaluate(run.greedy_action, stream)["accuracy"],
        "accuracy_definition": "greedy action on each step's state, decided online before learning from "
                               "that step, against the faster measured latency (ties count as correct), "
                               "over the last half of the run",
        "mean_latency_s": {name: score["mean_latency_s"] for name, score in policies.items()},
        "policies": policies,
        "dqn_config": agent.config.to_dict(), "alpha": weights.alpha, "beta": weights.beta,
        "trace": os.path.basename(trace_path), "trace_rows": len(trace), "run_seconds": run.seconds,
    }
    if kind == "cpu":
        metrics.update(_threshold_report(agent, stream.states))
        metrics["generating_threshold"] = settings.cpu_threshold
    run.table.save_npz(os.path.join(out_dir, "transitions.npz"))
    run.table.to_csv(os.path.join(out_dir, "transitions.csv"))
    save_checkpoint(agent, os.path.join(out_dir, "dqn.pt"))
    title = f"synthetic {kind}, seed {seed}, gamma {agent.config.gamma}"
    plot_training(run.loss, run.table.reward, os.path.join(out_dir, "training.png"), title)
    plot_action_vs_input_size(stream.input_size, run.table.action, os.path.join(out_dir, "action_vs_input_size.png"),
                              title)
    plot_confusion_matrix(policies["dqn"]["confusion_matrix"], os.path.join(out_dir, "confusion_matrix.png"),
                          f"DQN greedy, last half: {policies['dqn']['accuracy']:.1%}")
    plot_accuracy_bars({name: policies[name]["accuracy"] for name in ("dqn", "dqn_taken", "lstm", "lstm_all_features",
                                                                       "threshold_d", "always_local", "always_cloud",
                                                                       "random")},
                       os.path.join(out_dir, "accuracy.png"), title)
    if kind == "cpu":
        plot_action_vs_cpu(test.cpu_availability, run.greedy_action[half:], os.path.join(out_dir, "action_vs_cpu.png"),
                           metrics["learned_threshold"], settings.cpu_threshold, title)
    write_json(os.path.join(out_dir, "metrics.json"), metrics)
    return metrics


def run_sweep(kind: str, seeds: List[int], steps: int, out_dir: str, config: DQNConfig,
              trace_path: str = BUNDLED_TRACE) -> dict:
    runs = []
    for seed in seeds:
        print(f"== {kind} seed {seed}", file=sys.stderr, flush=True)
        runs.append(run_synthetic(kind, steps, seed, os.path.join(out_dir, f"seed_{seed}"), config, trace_path,
                                  show_progress=False))

    def spread(values) -> dict:
        values = np.asarray(values, dtype=np.float64)
        return {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
                "min": float(values.min()), "max": float(values.max()), "values": values.tolist()}

    summary = {"kind": kind, "seeds": seeds, "steps": steps, "gamma": config.gamma,
               "accuracy": spread([r["accuracy"] for r in runs]),
               "accuracy_taken": spread([r["accuracy_taken"] for r in runs]),
               "lstm_accuracy": spread([r["policies"]["lstm"]["accuracy"] for r in runs]),
               "lstm_all_features_accuracy": spread([r["policies"]["lstm_all_features"]["accuracy"] for r in runs]),
               "mean_latency_s": {name: spread([r["mean_latency_s"][name] for r in runs])
                                  for name in runs[0]["mean_latency_s"]}}
    if kind == "cpu":
        summary["learned_threshold"] = spread([r["learned_threshold"] for r in runs])
    write_json(os.path.join(out_dir, "summary.json"), summary)
    return summary


def run_compare(data_path: str, out_dir: str, config: DQNConfig, train_fraction: float = 0.5,
                weights: CostWeights = CostWeights(), progress: bool = False) -> dict:
    if not 0.0 < train_fraction < 1.0:
        raise ValueError(f"train_fraction must be in (0, 1), got {train_fraction}")
    os.makedirs(out_dir, exist_ok=True)
    table = TransitionTable.from_csv(data_path) if data_path.endswith(".csv") else TransitionTable.load_npz(data_path)
    split = int(round(len(table) * train_fraction))
    if split < 1 or split >= len(table):
        raise ValueError(f"{data_path} has {len(table)} rows: too few to split at {train_fraction}")
    train, test = table.slice(0, split), table.slice(split, len(table))
    dqn = DQNPolicy(config, weights).fit(train)
    dqn_actions = dqn.choose(test)
    scores = {"dqn": evaluate(dqn_actions, test)}
    scores.update(_score_baselines(train, test, config.seed, progress))
    result = {"data": data_path, "rows": len(table), "train_rows": split, "test_rows": len(test),
              "split": "chronological: the first rows fit every policy, the rest score them",
              "dqn_config": config.to_dict(), "policies": scores,
              "accuracy": {name: score["accuracy"] for name, score in scores.items()},
              "mean_latency_s": {name: score["mean_latency_s"] for name, score in scores.items()}}
    if np.ptp(table.cpu_availability) > 0:
        result.update(_threshold_report(dqn.agent, train.states))
    write_json(os.path.join(out_dir, "comparison.json"), result)
    with open(os.path.join(out_dir, "comparison.md"), "w") as out:
        out.write(comparison_markdown(result))
    plot_accuracy_bars(result["accuracy"], os.path.join(out_dir, "accuracy.png"), os.path.basename(data_path))
    plot_confusion_matrix(scores["dqn"]["confusion_matrix"], os.path.join(out_dir, "confusion_matrix_dqn.png"))
    plot_action_vs_input_size(test.input_size, dqn_actions, os.path.join(out_dir, "action_vs_input_size.png"))
    plot_action_vs_cpu(test.cpu_availability, dqn_actions, os.path.join(out_dir, "action_vs_cpu.png"),
                       result.get("learned_threshold"))
    plot_training(dqn.online_run.loss, dqn.online_run.table.reward, os.path.join(out_dir, "training.png"),
                  "DQN online over the training rows")
    return result


def comparison_markdown(result: dict) -> str:
    lines = [f"Policies fitted on rows 0..{result['train_rows'] - 1} and scored on the {result['test_rows']} "
             f"rows after them ({result['data']}).", "",
             "| policy | accuracy | mean latency (ms) | cumulative (s) | savings vs local | savings vs cloud | "
             "regret (s) |", "|---|---|---|---|---|---|---|"]
    for name, score in result["policies"].items():
        lines.append(f"| {name} | {score['accuracy']:.1%} | {score['mean_latency_s'] * 1e3:.3f} | "
                     f"{score['cumulative_latency_s']:.3f} | {score['savings_vs_local_pct']:+.1f}% | "
                     f"{score['savings_vs_cloud_pct']:+.1f}% | {score['regret_s']:.4f} |")
    if "learned_threshold" in result:
        threshold = result["learned_threshold"]
        lines += ["", f"DQN learned CPU threshold: {threshold:.4f}" if np.isfinite(threshold) else
                  "DQN learned CPU threshold: no threshold (the greedy policy never switches in the observed range)"]
    return "\n".join(lines) + "\n"


def _config_from_args(args) -> DQNConfig:
    """DQNConfig defaults with the experiments' schedule over them, then the run's seed, then --gamma, then any
    --set field=value (parsed as JSON when it can be)."""
    values = {**DQNConfig().to_dict(), **EXPERIMENT_SCHEDULE}
    if getattr(args, "seed", None) is not None:
        values["seed"] = args.seed
    if args.gamma is not None:
        values["gamma"] = args.gamma
    for assignment in args.set or []:
        field, _, text = assignment.partition("=")
        if field not in values:
            raise ValueError(f"--set: unknown DQNConfig field {field!r}; fields: {sorted(values)}")
        try:
            values[field] = json.loads(text)
        except json.JSONDecodeError:
            values[field] = text
    try:
        return DQNConfig.from_dict(values)
    except (TypeError, ValueError) as error:
        raise ValueError(f"invalid DQN configuration: {error}") from error


def _resolve_seed(args) -> None:
    """One seed per run: --seed, or --set seed=S, or 1; the two given with different values is an
    error, never a silent override. `sweep` takes its seeds from --seeds only."""
    assignments = [text.partition("=")[2] for text in args.set or [] if text.partition("=")[0] == "seed"]
    if args.command == "sweep":
        if assignments:
            raise ValueError("sweep takes its seeds from --seeds, not --set seed=...")
        return
    if not assignments:
        args.seed = 1 if args.seed is None else args.seed
        return
    try:
        set_seed = json.loads(assignments[-1])
    except json.JSONDecodeError:
        raise ValueError(f"invalid DQN configuration: seed must be an integer, got {assignments[-1]!r}") from None
    if args.seed is not None and set_seed != args.seed:
        raise ValueError(f"--seed {args.seed} and --set seed={assignments[-1]} disagree; give one")
    if isinstance(set_seed, bool) or not isinstance(set_seed, int) or set_seed < 0:
        raise ValueError(f"invalid DQN configuration: seed must be a non-negative integer, got {set_seed!r}")
    args.seed = set_seed


def main(argv: Optional[List[str]] = None) -> int:
    """Run one command. Bad user input (a missing or invalid data, trace or config) prints
    `error: ...` on stderr and returns 2, as argparse does for bad arguments."""
    parser = argparse.ArgumentParser(prog="python -m offload_learner_py.offline.experiments", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)

    def add_common(sub):
        sub.add_argument("--out", required=True, help="output directory")
        sub.add_argument("--gamma", type=float, default=None, help="discount (default 0: contextual bandit)")
        sub.add_argument("--set", action="append", metavar="FIELD=VALUE", help="override any DQNConfig field")
        sub.add_argument("--threads", type=bounded_int("--threads", 1, MAX_COUNT), default=1,
                         help="torch threads; 1 is fastest for these small networks")

    synthetic = commands.add_parser("synthetic", help="train online on one synthetic dataset")
    synthetic.add_argument("--kind", choices=SYNTHETIC_KINDS, required=True)
    synthetic.add_argument("--steps", type=bounded_int("--steps", 1, MAX_COUNT), default=1000)
    synthetic.add_argument("--seed", type=bounded_int("--seed", 0, MAX_COUNT), default=None, help="seed of the data and the DQN "
                           "(default 1, or --set seed=S)")
    synthetic.add_argument("--trace", default=BUNDLED_TRACE, help="planning trace .npz (default: bundled)")
    add_common(synthetic)

    sweep = commands.add_parser("sweep", help="`synthetic` over several seeds, with mean and spread")
    sweep.add_argument("--kind", choices=SYNTHETIC_KINDS, required=True)
    sweep.add_argument("--seeds", type=bounded_int("--seeds", 0, MAX_COUNT), nargs="+", required=True)
    sweep.add_argument("--steps", type=bounded_int("--steps", 1, MAX_COUNT), default=1000)
    sweep.add_argument("--trace", default=BUNDLED_TRACE)
    add_common(sweep)

    compare = commands.add_parser("compare", help="every policy on one transition table")
    compare.add_argument("--data", required=True, help="transition table (.npz or .csv)")
    compare.add_argument("--train-fraction", type=bounded_float("--train-fraction", 0.0, 1.0, low_open=True, high_open=True),
                         default=0.5)
    compare.add_argument("--seed", type=bounded_int("--seed", 0, MAX_COUNT), default=None, help="seed of the DQN and the baselines "
                         "(default 1, or --set seed=S)")
    add_common(compare)

    generate = commands.add_parser("generate", help="write a synthetic transition table (.npz, and .csv beside it)")
    generate.add_argument("--kind", choices=SYNTHETIC_KINDS, required=True)
    generate.add_argument("--steps", type=bounded_int("--steps", 1, MAX_COUNT), default=1000)
    generate.add_argument("--seed", type=bounded_int("--seed", 0, MAX_COUNT), default=1)
    generate.add_argument("--trace", default=BUNDLED_TRACE)
    generate.add_argument("--out", required=True, help="output .npz (the .csv is written beside it)")

    args = parser.parse_args(argv)
    try:
        return _run(args)
    except (ValueError, OSError) as error:  # IncompatibleCheckpointError is a ValueError
        print(f"error: {error}", file=sys.stderr)
        return 2


def _run(args) -> int:
    # Every value is checked, and the output made sure to be writable, before any work starts.
    if args.command == "generate":
        if not args.out.endswith(".npz"):
            raise ValueError(f"--out must end in .npz (the .csv is written beside it), got {args.out}")
        csv_path = args.out[:-len(".npz")] + ".csv"
        require_writable_file(args.out)
        require_writable_file(csv_path)
        table = generate_synthetic(args.kind, PlanningTrace.load_npz(args.trace), args.steps, args.seed)
        table.save_npz(args.out)
        table.to_csv(csv_path)
        print(f"wrote {args.out} and {csv_path}: {len(table)} steps of synthetic {args.kind}")
        return 0
    _resolve_seed(args)
    config = _config_from_args(args)
    require_writable_dir(args.out)
    torch.set_num_threads(args.threads)
    if args.command == "synthetic":
        metrics = run_synthetic(args.kind, args.steps, args.seed, args.out, config, args.trace)
        summary = {key: metrics[key] for key in ("accuracy", "accuracy_taken", "learned_threshold") if key in metrics}
        summary["lstm_accuracy"] = metrics["policies"]["lstm"]["accuracy"]
        print(json.dumps(summary))
    elif args.command == "sweep":
        summary = run_sweep(args.kind, args.seeds, args.steps, args.out, config, args.trace)
        brief = {key: {k: summary[key][k] for k in ("mean", "std", "min", "max")}
                 for key in ("accuracy", "accuracy_taken", "lstm_accuracy", "learned_threshold") if key in summary}
        print(json.dumps(brief))
    else:
        result = run_compare(args.data, args.out, config, args.train_fraction, progress=True)
        print(comparison_markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
