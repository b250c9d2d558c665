"""The paper's section V from one's own bags.

    python -m offload_learner_py.offline.report BAGS... --out DIR [--model CHECKPOINT] [--seed S]

Writes DIR/report.md (figures beside it in DIR/figures/), DIR/report.html (one self-contained page,
the PNGs inlined) and DIR/report.json: loss and cumulative reward per step (Fig. 6), action against
input size with the learned offload point (Fig. 7), action against CPU availability with the learned
threshold (Fig. 11), the confusion matrix (Fig. 12), DQN against LSTM accuracy trained on the first
500 and on all steps with an 80:20 split (Fig. 13), and the latency table, each beside the paper's
published numbers. The learned offload point and threshold are read from --model (the run's own
checkpoint) or, without it, from a DQN trained offline on every probe step of the bags.

`report(bags, out_dir)` does the same from Python; `report_run(run_dir)` writes RUN_DIR/report from a
`make demo` run directory (its bag and checkpoint).
"""
import argparse
import base64
import html
import json
import math
import os
import re
import sys
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch

from offload_learner_py.offline import plots
from offload_learner_py.data.bags import BagData, read_bags
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.evaluation import accuracy, confusion_matrix, evaluate, learned_cpu_threshold
from offload_learner_py.core.lstm_baseline import LSTMConfig, LSTMPolicy
from offload_learner_py.offline.output import OutputDirError, code_block, prepare_out_dir, terminal_text
from offload_learner_py.offline.off_policy import LoggedSteps, evaluate_policy, format_results
from offload_learner_py.offline.retrain import chronological_split, train_offline
from offload_learner_py.offline.summary import learned_offload_input_size

# Section V of the paper (real data unless said otherwise).
PAPER = {
    "accuracy_pct": 84.0,
    "mean_latency_ms": {"chosen": 71.28, "local": 88.38, "cloud": 73.46},
    "cumulative_latency_s": {"chosen": 140.88, "local": 175.81, "cloud": 146.09},
    "savings_pct": {"vs_local": 23.0, "vs_cloud": 3.0},    # as stated in the text
    "offload_input_size": 1.1,
    "cpu_threshold": 0.61,           # synthetic CPU dataset (eq. 15), generated with 0.6
    "cpu_accuracy_pct": 94.0,        # the same dataset, Fig. 12
    "fig13": {"DQN, first 500": 81.62, "LSTM, first 500": 72.08, "DQN, all": 83.32, "LSTM, all": 74.12},
    "steps": 1000,
}
MIN_ROWS = 10


def _pct(value: float) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{100 * value:.1f}"


def _fit_pair(rows: TransitionTable, seed: int, gradient_steps: Optional[int], lstm_epochs: int) -> Dict[str, float]:
    """DQN and LSTM fitted on the first 80 % of rows, accuracy on the last 20 %."""
    cut = chronological_split(len(rows), 0.2)
    train, test = rows.slice(0, cut), rows.slice(cut, len(rows))
    agent = train_offline(train, DQNConfig(seed=seed), gradient_steps).agent
    lstm = LSTMPolicy(LSTMConfig(seed=seed, epochs=lstm_epochs)).fit(train)
    return {"dqn": accuracy(agent.greedy_actions(test.states), test), "lstm": accuracy(lstm.choose(test), test),
            "train_rows": len(train), "test_rows": len(test)}


def report(bags: Sequence[str] = (), out_dir: str = "report", model: Optional[str] = None, seed: int = 1,
           gradient_steps: Optional[int] = None, lstm_epochs: int = 60, workers: Optional[int] = None,
           data: Optional[BagData] = None, progress: bool = False) -> str:
    """Write the report for the bags (or already read `data`) into out_dir; returns report.md's path."""
    if data is None:
        data = read_bags(list(bags), workers=workers)
    figures = os.path.join(out_dir, "figures")
    os.makedirs(figures, exist_ok=True)
    log, table = data.log, data.transition_table()
    numbers: Dict = {"requests": len(log), "probe_rows": len(table), "paper": PAPER,
                     "read_report": data.report.to_dict()}
    sections: List[Dict] = []
    if len(table) < MIN_ROWS:
        sections.append({"title": "Not enough data", "text": f"{len(table)} requests with both latencies were read; "
                         f"the figures need at least {MIN_ROWS} (record with a probe rate above 0)."})
        return _write(out_dir, sections, numbers, data.report.format())

    stages = _Stages(progress, ["Q-function", "figures 6-12", "Fig. 13 on the first 500 steps",
                                "Fig. 13 on all steps", "latency table and off-policy estimates"])
    # Q-function behind the learned offload point and threshold
    stages.next()
    if model:
        from offload_learner_py.core.checkpoint import load_checkpoint

        agent = load_checkpoint(model)
        q_source = f"the checkpoint {model}"
    else:
        fitted = train_offline(table, DQNConfig(seed=seed), gradient_steps, progress=progress)
        agent = fitted.agent
        q_source = f"a DQN trained offline on all {len(table)} probe steps ({len(fitted.losses)} gradient steps)"
    states = table.states
    offload_point = learned_offload_input_size(agent.q_values, states)
    threshold = learned_cpu_threshold(agent.q_values, states)
    numbers.update(offload_input_size=offload_point, cpu_threshold=threshold, q_source=q_source)

    # Fig. 6: loss and cumulative reward of the online run, per request
    stages.next()
    loss = np.where(log["outcome_loss_valid"].astype(bool), log["outcome_loss"], np.nan)
    step_reward = np.where(log["outcome_reward_valid"].astype(bool), log["outcome_reward"], 0.0)
    path6 = plots.plot_training(loss, step_reward, os.path.join(figures, "fig6_loss_reward.png"),
                                title="online learning: loss and cumulative reward per request")
    numbers["cumulative_reward"] = float(np.sum(step_reward))
    finite_loss = loss[np.isfinite(loss)]
    numbers["final_loss"] = float(finite_loss[-50:].mean()) if len(finite_loss) else None
    sections.append({"title": "Fig. 6: loss and cumulative reward", "image": path6,
                     "ours": f"{len(log)} requests, {int(np.isfinite(loss).sum())} gradient steps logged; cumulative "
                             f"reward {numbers['cumulative_reward']:.2f}; mean loss of the last 50 logged steps "
                             f"{numbers['final_loss'] if numbers['final_loss'] is not None else float('nan'):.4g}.",
                     "paper": "Real data, 1000 steps: the average loss converges and the cumulative reward rises "
                              "steadily from about t = 400."})

    # Fig. 7 and 11: the actions taken against d_t and u_t
    path7 = plots.plot_action_vs_input_size(log["input_size"], log["action"],
                                            os.path.join(figures, "fig7_action_vs_input_size.png"),
                                            offload_point=offload_point)
    sections.append({"title": "Fig. 7: action against input size", "image": path7,
                     "ours": f"Learned offload point: greedy policy offloads above d_t = {offload_point:.3g} (u_t, "
                             f"b_t at their medians; from {q_source})." if math.isfinite(offload_point) else
                             f"The greedy policy does not switch from local to cloud as d_t grows ({q_source}).",
                     "paper": f"Cloud preferred for normalised d_t > {PAPER['offload_input_size']}."})
    path11 = plots.plot_action_vs_cpu(log["cpu_availability"], log["action"],
                                      os.path.join(figures, "fig11_action_vs_cpu.png"), learned_threshold=threshold)
    sections.append({"title": "Fig. 11: action against CPU availability", "image": path11,
                     "ours": f"Learned threshold: cloud below u_t = {threshold:.3f} (d_t, b_t at their medians)."
                     if math.isfinite(threshold) else "The greedy policy has no cloud-below/local-above switch in u_t "
                                                      "over the observed range.",
                     "paper": f"Synthetic CPU dataset generated with 0.6: learned threshold {PAPER['cpu_threshold']}."})

    # Fig. 12: the online policy's actions on probe steps against the oracle
    matrix = confusion_matrix(table.action, table)
    path12 = plots.plot_confusion_matrix(matrix, os.path.join(figures, "fig12_confusion.png"),
                                         title=f"actions taken on probe steps: accuracy "
                                               f"{_pct(accuracy(table.action, table))}%")
    numbers["confusion_matrix"] = matrix.tolist()
    numbers["accuracy_taken"] = accuracy(table.action, table)
    half = len(table) // 2
    numbers["accuracy_taken_second_half"] = accuracy(table.action[half:], table.slice(half, len(table)))
    sections.append({"title": "Fig. 12: confusion matrix", "image": path12,
                     "ours": f"Actions taken (exploration included) on {len(table)} probe steps: accuracy "
                             f"{_pct(numbers['accuracy_taken'])} % (second half {_pct(numbers['accuracy_taken_second_half'])} %). "
                             f"Rows: oracle local / cloud; columns: chosen local / cloud: {matrix.tolist()}.",
                     "paper": f"Real data: {PAPER['accuracy_pct']:.0f} % over the whole run; synthetic CPU data: "
                              f"{PAPER['cpu_accuracy_pct']:.0f} %."})

    # Fig. 13: DQN against LSTM, first 500 steps and all steps, 80:20
    first = table.slice(0, min(500, len(table)))
    fig13 = {}
    for label, rows in (("first 500", first), ("all", table)):
        stages.next()
        scores = _fit_pair(rows, seed, gradient_steps, lstm_epochs)
        fig13[f"DQN, {label}"], fig13[f"LSTM, {label}"] = scores["dqn"], scores["lstm"]
    numbers["fig13"] = fig13
    path13 = plots.plot_accuracy_bars(fig13, os.path.join(figures, "fig13_dqn_vs_lstm.png"),
                                      title="accuracy on the last 20 % (fitted on the first 80 %)")
    rows13 = "; ".join(f"{name} {_pct(value)} % (paper {PAPER['fig13'][name]})" for name, value in fig13.items())
    small = len(table) - chronological_split(len(table), 0.2) < 30
    sections.append({"title": "Fig. 13: DQN against LSTM", "image": path13,
                     "ours": rows13 + (f". Only {len(table)} probe steps: 'first 500' is all of them, so its bars "
                                       "repeat the 'all' bars." if len(table) <= 500 else ".")
                     + (" Warning: the held-out 20 % is under 30 steps, so these accuracies move by several points "
                        "with one step." if small else ""),
                     "paper": "LSTM (hidden 4, batch 50, 8 steps) predicting execution time from the input size; "
                              "DQN 81.62 / 83.32 %, LSTM 72.08 / 74.12 % (first 500 / all 1000 steps)."})

    # The latency table
    stages.next()
    scores = evaluate(table.action, table)
    n = len(table)
    latency = {"chosen": scores["mean_latency_s"], "local": scores["mean_latency_always_local_s"],
               "cloud": scores["mean_latency_always_cloud_s"]}
    numbers["latency"] = {"mean_ms": {k: 1000 * v for k, v in latency.items()},
                          "cumulative_s": {k: v * n for k, v in latency.items()},
                          "savings_vs_local_pct": scores["savings_vs_local_pct"],
                          "savings_vs_cloud_pct": scores["savings_vs_cloud_pct"]}
    rows = ["| | ours: mean (ms) | ours: cumulative (s) | paper: mean (ms) | paper: cumulative (s) |",
            "|---|---|---|---|---|"]
    for key, name in (("chosen", "chosen by the policy"), ("local", "always local"), ("cloud", "always cloud")):
        rows.append(f"| {name} | {1000 * latency[key]:.2f} | {latency[key] * n:.2f} | "
                    f"{PAPER['mean_latency_ms'][key]} | {PAPER['cumulative_latency_s'][key]} |")
    rows.append(f"| savings vs local (%) | {scores['savings_vs_local_pct']:.1f} | | {PAPER['savings_pct']['vs_local']:.0f} "
                f"(text; 19.3 from its means) | |")
    rows.append(f"| savings vs cloud (%) | {scores['savings_vs_cloud_pct']:.1f} | | {PAPER['savings_pct']['vs_cloud']:.0f} | |")
    sections.append({"title": "Latency table", "table": "\n".join(rows),
                     "ours": f"Over the {n} probe steps (both latencies measured), actions as taken online. "
                             "Absolute latencies differ from the paper's by design: its local plans were small "
                             "(88 ms mean) on a whole robot CPU with a constant 30 ms link, while this system's "
                             "depend on the map and goal distances, the robot's CPU budget and its workload, and "
                             "the link profile (the demo: the warehouse's known free space, a 0.5-core budget with a "
                             "varying workload, an 8-120 ms edge or 20-400 ms WAN round-trip trace). Compare the rows with each other, not with the paper's.",
                     "paper": f"{PAPER['steps']} steps of real data."})

    # Off-policy estimates: what a deployed robot's bags say about other policies
    steps = LoggedSteps.from_log(log)
    predicted = steps.latency_model()
    candidates = {"greedy DQN": agent.greedy_actions(steps.states), "always local": np.full(len(steps), 0),
                  "always cloud": np.full(len(steps), 1)}
    ope = {name: evaluate_policy(steps, actions, predicted) for name, actions in candidates.items()}
    numbers["off_policy"] = {name: {key: (value.__dict__ if hasattr(value, "__dict__") else value)
                                    for key, value in result.items()} for name, result in ope.items()}
    sections.append({"title": "Off-policy estimates", "code": format_results(ope),
                     "ours": "Mean latency of each policy on these requests: probes (both sides measured) scored "
                             "directly, the other requests by SNIPS, DR or IPS from the logged propensities; "
                             "beside it the latency and accuracy on the probes alone; 95 % intervals, n/a where the "
                             "logs cannot say.",
                     "paper": "Not in the paper (it measured both sides at every step)."})
    stages.close()
    return _write(out_dir, sections, numbers, data.report.format())


class _Stages:
    """One progress bar over the report's steps (with an ETA), on stderr, when asked for."""

    def __init__(self, enabled: bool, names: List[str]):
        self.names, self.index = names, -1
        self.bar = None
        if enabled:
            from tqdm import tqdm
            self.bar = tqdm(total=len(names), desc="report", unit="step", file=sys.stderr)

    def next(self) -> None:
        """The previous step is done; the next one starts."""
        if self.bar is None:
            return
        if self.index >= 0:
            self.bar.update(1)
        self.index += 1
        self.bar.set_description(f"report: {self.names[min(self.index, len(self.names) - 1)]}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.update(self.bar.total - self.bar.n)
            self.bar.close()


def report_run(run_dir: str, **options) -> str:
    """The report of a `make demo` run directory, into RUN_DIR/report: its offload.bag (or the
    .bag.active a stopped recorder left) and, when present, its checkpoint.pt for the learned offload
    point and threshold."""
    bag = os.path.join(run_dir, "offload.bag")
    if not os.path.exists(bag) and os.path.exists(bag + ".active"):
        bag += ".active"
    checkpoint = os.path.join(run_dir, "checkpoint.pt")
    options.setdefault("model", checkpoint if os.path.exists(checkpoint) else None)
    return report([bag], os.path.join(run_dir, "report"), **options)


def _write(out_dir: str, sections: List[Dict], numbers: Dict, read_report: str) -> str:
    md = ["# Offloading report: the paper's section V from these bags", "",
          f"{numbers['requests']} requests read, {numbers['probe_rows']} with both latencies.", ""]
    page = []
    for section in sections:
        md += [f"## {section['title']}", ""]
        page.append(f"<h2>{html.escape(section['title'])}</h2>")
        if "image" in section:
            relative = os.path.relpath(section["image"], out_dir)
            md += [f"![{section['title']}]({relative})", ""]
            with open(section["image"], "rb") as image:
                encoded = base64.b64encode(image.read()).decode("ascii")
            page.append(f'<img alt="{html.escape(section["title"])}" src="data:image/png;base64,{encoded}">')
        if "table" in section:
            md += [section["table"], ""]
            page.append(_html_table(section["table"]))
        if "code" in section:
            md += ["```", code_block(section["code"]), "```", ""]
            page.append(f"<pre>{html.escape(section['code'])}</pre>")
        for key, label in (("ours", "Ours"), ("paper", "Paper"), ("text", "")):
            if key in section:
                md += [f"**{label}:** {section[key]}" if label else section[key], ""]
                page.append(f"<p>{'<b>' + label + ':</b> ' if label else ''}{html.escape(section[key])}</p>")
    md += ["## Bags read", "", "```", code_block(read_report), "```", ""]
    page.append(f"<h2>Bags read</h2><pre>{html.escape(read_report)}</pre>")
    path = os.path.join(out_dir, "report.md")
    with open(path, "w") as out:
        out.write("\n".join(md))
    with open(os.path.join(out_dir, "report.html"), "w") as out:
        out.write("<!DOCTYPE html><html><head><meta charset='utf-8'><title>Offloading report</title><style>"
                  "body{font-family:sans-serif;max-width:60em;margin:auto}img{max-width:100%}"
                  "table{border-collapse:collapse}td,th{border:1px solid #999;padding:0.2em 0.5em}"
                  # wide blocks (the off-policy table, the bags read) wrap instead of overflowing the page
                  "pre{white-space:pre-wrap;overflow-wrap:anywhere}</style></head>"
                  "<body><h1>Offloading report: the paper's section V from these bags</h1>"
                  f"<p>{numbers['requests']} requests read, {numbers['probe_rows']} with both latencies.</p>"
                  + "\n".join(page) + "</body></html>\n")
    with open(os.path.join(out_dir, "report.json"), "w") as out:
        json.dump(numbers, out, indent=2, default=_json_default)
    return path


def _json_default(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON: {type(value).__name__}")


def _html_table(markdown: str) -> str:
    lines = [line for line in markdown.splitlines() if not re.fullmatch(r"\|[-|]+\|", line)]
    cells = [[html.escape(cell.strip()) for cell in line.strip("|").split("|")] for line in lines]
    head = "".join(f"<th>{cell}</th>" for cell in cells[0])
    body = "".join("<tr>" + "".join(f"<td>{cell}</td>" for cell in row) + "</tr>" for row in cells[1:])
    return f"<table><tr>{head}</tr>{body}</table>"


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bags", nargs="+", help="bag files, globs or directories")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--model", help="checkpoint whose Q-function gives the offload point and threshold")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--steps", type=int, default=None,
                        help="gradient steps of each offline DQN fit (default: 50 passes over its transitions)")
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--quiet", action="store_true")
    parser.add_argument("--force", action="store_true", help="overwrite an earlier report in --out")
    args = parser.parse_args(argv)
    try:
        prepare_out_dir(args.out, args.force)
    except OutputDirError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)   # tiny networks: one thread is fastest
    data = read_bags(args.bags, workers=args.workers)
    print(terminal_text(data.report.format()), file=sys.stderr)
    try:
        path = report(out_dir=args.out, model=args.model, seed=args.seed, gradient_steps=args.steps, data=data,
                      progress=not args.quiet)
    except ValueError as error:   # an unreadable checkpoint
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"report: {path} and {os.path.join(args.out, 'report.html')}")
    if data.report.failed:
        return 1   # a bag that could not be read is not a documented skip
    return 0 if len(data.transition_table()) >= MIN_ROWS else 2


if __name__ == "__main__":
    sys.exit(main())
