"""Retrain the DQN offline from recorded bags.

    python -m offload_learner_py.offline.retrain BAGS... --out DIR [--seed S] [--steps N] [--baselines]

Reads the bags (files, globs, directories), keeps the requests with both latencies (the transition
table), splits them in time (the first 80 % to train, the last 20 % held out), trains the Q-network
of Algorithm 1 on the training rows and scores it on the held-out rows beside the online policy
that wrote the bags. Both latencies are known on every training row, so each row teaches the reward
(eq. 10) of both actions, not only the one taken (`--taken-only` keeps the logged action alone).
Off-policy estimates on the held-out requests, probe or not (probes scored directly, the others by SNIPS,
DR and IPS), stand beside the probe-step figures.

DIR receives checkpoint.pt (load it with the learner node's ~model), transitions.npz, evaluation.json,
evaluation.md and read_report.json. The same bags, --seed and --steps give the same checkpoint.
"""
import argparse
import json
import math
import os
import sys
from dataclasses import dataclass
from typing import Dict, List, Optional

import numpy as np
import torch

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.data.bags import BagData, read_bags
from offload_learner_py.core.checkpoint import save_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.data.records import cloud_answered, rewarded_rows
from offload_learner_py.core.dqn import DQNAgent, greedy_actions
from offload_learner_py.core.evaluation import evaluate
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.offline.output import code_block, prepare_out_dir, terminal_text
from offload_learner_py.offline.off_policy import LoggedSteps, evaluate_policy, format_results, to_jsonable
from offload_learner_py.core.replay import ReplayMemory
from offload_learner_py.core.reward import DEFAULT_CLOUD_TIMEOUT_S, CostWeights, rewards
from offload_learner_py.core.round_trip import table_variants

DEFAULT_EPOCHS = 50
MIN_ROWS = 10


@dataclass
class OfflineResult:
    agent: DQNAgent
    losses: np.ndarray       # one per gradient step


def gradient_steps_for(rows: int, config: DQNConfig, epochs: float = DEFAULT_EPOCHS, taken_only: bool = False) -> int:
    """Minibatch steps for `epochs` passes over the replay (two transitions per row unless taken_only).
    A fixed count over-fits small bags: on a 400-request demo bag, 300 epochs lost 3-5 points of
    held-out accuracy against 30-100."""
    transitions = rows * (1 if taken_only else 2)
    return max(1, int(math.ceil(epochs * transitions / config.batch_size)))


def train_offline(train: TransitionTable, config: DQNConfig, gradient_steps: Optional[int] = None,
                  weights: CostWeights = CostWeights(), taken_only: bool = False,
                  progress: bool = False, agent: Optional[DQNAgent] = None,
                  cloud_answered: Optional[np.ndarray] = None) -> OfflineResult:
    """The Q-network trained on a fixed table: the normalisation fitted on the training states and
    frozen, every transition in replay at once, `gradient_steps` minibatch steps of Algorithm 1's
    loss (target copies every K steps when gamma > 0). The agent's step counter is set past the
    warm-up, so a node that loads the checkpoint acts on it at once. With `agent` (a warm start, e.g. the fleet
    learner's version in use) that network is trained further with its own normalisation. Unless taken_only, the
    replay also holds config.round_trip_variants round-trip variants of each row whose cloud side answered
    (core/round_trip.py; the gradient steps are counted on the rows alone): `cloud_answered` per row, as
    data/records.cloud_answered reads it from the outcomes; without it, a row whose l_cloud is under the paper's
    5 s timeout (a table of no run: a CSV, synthetic data)."""
    if len(train) == 0:
        raise ValueError("no training rows")
    if gradient_steps is None:
        gradient_steps = gradient_steps_for(len(train), config, taken_only=taken_only)
    if agent is None:
        agent = DQNAgent(config, StateNormalisation.fit(train.states, config.log_input_size))
    states = train.states
    next_states = np.concatenate([states[1:], states[-1:]])
    if taken_only:
        actions = train.action
        step_rewards = rewards(actions, train.local_s, train.cloud_s, weights)
        state_rows, next_rows = states, next_states
    else:
        actions = np.concatenate([np.full(len(train), LOCAL), np.full(len(train), CLOUD)])
        step_rewards = np.concatenate([rewards(np.full(len(train), a), train.local_s, train.cloud_s, weights)
                                       for a in (LOCAL, CLOUD)])
        state_rows, next_rows = np.concatenate([states, states]), np.concatenate([next_states, next_states])
        answered = train.cloud_s < DEFAULT_CLOUD_TIMEOUT_S if cloud_answered is None else \
            np.asarray(cloud_answered, dtype=bool)
        if len(answered) != len(train):
            raise ValueError(f"cloud_answered has {len(answered)} rows for a table of {len(train)}")
        moved, local_s, cloud_s = table_variants(states[answered], train.local_s[answered], train.cloud_s[answered],
                                                 config.round_trip_variants, np.random.default_rng(config.seed))
        actions = np.concatenate([actions, np.full(len(moved), CLOUD)])
        step_rewards = np.concatenate([step_rewards, rewards(np.full(len(moved), CLOUD), local_s, cloud_s, weights)])
        state_rows, next_rows = np.concatenate([state_rows, moved]), np.concatenate([next_rows, moved])
    agent.memory = ReplayMemory(max(len(actions), config.batch_size))
    for state, action, value, next_state in zip(state_rows, actions, step_rewards, next_rows):
        agent.memory.add(state, int(action), float(value), next_state)
    plain_optimizer = agent.optimizer
    agent.optimizer = _fused_like(plain_optimizer, agent.q_network.parameters())
    losses = np.zeros(gradient_steps)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=gradient_steps, desc="training", unit="step", file=sys.stderr, mininterval=0.5)
    for step in range(gradient_steps):
        losses[step] = agent.train_step()
        if (step + 1) % config.target_update_interval == 0:
            agent.target_network.load_state_dict(agent.q_network.state_dict())
        if bar is not None:
            bar.update(1)
            if step % 100 == 99:
                bar.set_postfix(loss=f"{losses[max(0, step - 99):step + 1].mean():.4f}", refresh=False)
    if bar is not None:
        bar.close()
    agent.optimizer = _back_to_plain(agent.optimizer, plain_optimizer)
    agent.target_network.load_state_dict(agent.q_network.state_dict())
    agent.memory = ReplayMemory(config.replay_capacity)   # online learning after loading starts afresh
    agent.steps = max(len(train), config.learning_starts)
    return OfflineResult(agent, losses)


def _fused_like(optimizer, parameters):
    """The same AdamW with torch's fused CPU kernel: about a third faster per step here. The node keeps
    the plain optimizer; _back_to_plain hands the moments over."""
    group = optimizer.param_groups[0]
    try:
        return torch.optim.AdamW(parameters, lr=group["lr"], weight_decay=group["weight_decay"], fused=True)
    except (RuntimeError, TypeError, ValueError):   # a torch build without the fused CPU kernel
        return optimizer


def _back_to_plain(fused, plain):
    if fused is plain:
        return plain
    state = fused.state_dict()
    for group in state["param_groups"]:
        group["fused"] = None
    plain.load_state_dict(state)
    return plain


def logged_reward_mismatch(table: TransitionTable, weights: CostWeights) -> float:
    """Largest difference between the rewards the robot logged and eq. 10 with `weights`: the bags
    do not record alpha, so this is how a retraining with another alpha is caught."""
    if len(table) == 0:
        return 0.0
    return float(np.max(np.abs(rewards(table.action, table.local_s, table.cloud_s, weights) - table.reward)))


def recorded_weights(data: BagData) -> CostWeights:
    """alpha and beta as the learner recorded them in the bags (its latched config); the paper's 0.5 for
    bags from before the config was recorded. Sessions with different weights cannot share one reward."""
    recorded = [alpha for alpha in data.report.recorded("alpha") if alpha is not None and math.isfinite(alpha)]
    if len(recorded) > 1:
        raise ValueError(f"the bags were recorded with different alphas {sorted(recorded)}: pass --alpha, or "
                         "retrain from bags of one setting")
    alpha = recorded[0] if recorded else 0.5
    return CostWeights(alpha, 1.0 - alpha)


def chronological_split(n: int, test_fraction: float) -> int:
    """Rows [0, cut) train, [cut, n) test; both non-empty when n >= 2."""
    if not 0.0 < test_fraction < 1.0:
        raise ValueError(f"test fraction must be in (0, 1), got {test_fraction}")
    return min(max(1, int(round(n * (1.0 - test_fraction)))), n - 1)


def online_greedy(data: BagData) -> np.ndarray:
    """The online policy's greedy action on each table row, from the Q-values it logged (NaN-free
    rows only; -1 where the policy logged none)."""
    rows = rewarded_rows(data.log)
    q_local, q_cloud = data.log["q_local"][rows], data.log["q_cloud"][rows]
    known = np.isfinite(q_local) & np.isfinite(q_cloud)
    return np.where(known, greedy_actions(np.stack([q_local, q_cloud], axis=-1)), -1)


def retrain(data: BagData, out_dir: str, config: DQNConfig, gradient_steps: Optional[int] = None,
            test_fraction: float = 0.2, baselines: bool = False, weights: CostWeights = CostWeights(),
            taken_only: bool = False, progress: bool = False) -> Dict:
    """Train, evaluate and write DIR; returns the evaluation."""
    table = data.transition_table()
    if len(table) < MIN_ROWS:
        raise ValueError(f"only {len(table)} requests with both latencies in the bags; retraining needs at least "
                         f"{MIN_ROWS} (record with a probe rate above 0)")
    os.makedirs(out_dir, exist_ok=True)
    mismatch = logged_reward_mismatch(table, weights)
    if mismatch > 1e-6:
        print(f"warning: the logged rewards differ from eq. 10 with alpha {weights.alpha} by up to {mismatch:.3g}: "
              f"the robot ran with another alpha (pass --alpha)", file=sys.stderr)
    cut = chronological_split(len(table), test_fraction)
    train, test = table.slice(0, cut), table.slice(cut, len(table))
    if gradient_steps is None:
        gradient_steps = gradient_steps_for(len(train), config, taken_only=taken_only)
    result = train_offline(train, config, gradient_steps, weights, taken_only, progress,
                           cloud_answered=cloud_answered(data.log)[:cut])
    agent = result.agent
    checkpoint = os.path.join(out_dir, "checkpoint.pt")
    save_checkpoint(agent, checkpoint)
    table.save_npz(os.path.join(out_dir, "transitions.npz"))
    retrained = agent.greedy_actions(test.states)
    evaluation = {"rows": len(table), "train_rows": len(train), "test_rows": len(test),
                  "test_from_request": int(test.t[0]), "gradient_steps": gradient_steps, "seed": config.seed,
                  "taken_only": taken_only, "final_loss": float(result.losses[-100:].mean()) if gradient_steps else None,
                  "checkpoint": checkpoint, "retrained": evaluate(retrained, test),
                  "online_taken": evaluate(test.action, test)}
    greedy = online_greedy(data)[cut:]
    if np.all(greedy >= 0) and len(greedy):
        evaluation["online_greedy"] = evaluate(greedy, test)
    if baselines:
        from offload_learner_py.offline.experiments import baseline_policies

        evaluation["baselines"] = {policy.name: evaluate(policy.fit(train).choose(test), test)
                                   for policy in baseline_policies(config.seed, progress)}
    # Off-policy: every held-out request (one latency or two) from the first held-out one on.
    log_rows = np.flatnonzero(rewarded_rows(data.log))
    first_test_log_row = log_rows[cut]
    steps = LoggedSteps.from_log(data.log, np.arange(first_test_log_row, len(data.log)))
    predicted = steps.latency_model()
    candidates = {"retrained": agent.greedy_actions(steps.states), "always_local": np.full(len(steps), LOCAL),
                  "always_cloud": np.full(len(steps), CLOUD)}
    ope = {name: evaluate_policy(steps, actions, predicted) for name, actions in candidates.items()}
    evaluation["off_policy"] = {name: to_jsonable(value) for name, value in ope.items()}
    evaluation["off_policy_table"] = format_results(ope)
    with open(os.path.join(out_dir, "evaluation.json"), "w") as out:
        json.dump(evaluation, out, indent=2, default=float)
    with open(os.path.join(out_dir, "read_report.json"), "w") as out:
        json.dump(data.report.to_dict(), out, indent=2)
    with open(os.path.join(out_dir, "evaluation.md"), "w") as out:
        out.write(format_evaluation(evaluation, data.report.format()))
    return evaluation


def format_evaluation(evaluation: Dict, read_report: str = "") -> str:
    lines = ["# Offline retraining", "",
             f"{evaluation['rows']} requests with both latencies: the first {evaluation['train_rows']} train, the "
             f"last {evaluation['test_rows']} (from request {evaluation['test_from_request']}) are held out. "
             f"{evaluation['gradient_steps']} gradient steps, seed {evaluation['seed']}.", "",
             "| policy on the held-out rows | accuracy (%) | mean latency (ms) | cloud share (%) |", "|---|---|---|---|"]
    rows = [("retrained DQN (greedy)", evaluation["retrained"]), ("online policy, actions taken", evaluation["online_taken"])]
    if "online_greedy" in evaluation:
        rows.append(("online policy, greedy", evaluation["online_greedy"]))
    rows += [(name, score) for name, score in evaluation.get("baselines", {}).items()]
    for name, score in rows:
        lines.append(f"| {name} | {100 * score['accuracy']:.1f} | {1000 * score['mean_latency_s']:.2f} | "
                     f"{100 * score['cloud_share']:.1f} |")
    lines += ["", "Off-policy estimates on the held-out requests (95 % intervals):", "", "```",
              evaluation["off_policy_table"], "```"]
    if read_report:
        lines += ["", "Bags read:", "", "```", code_block(read_report), "```"]
    return "\n".join(lines) + "\n"


def parse_overrides(pairs: List[str]) -> Dict:
    overrides = {}
    for pair in pairs:
        name, separator, text = pair.partition("=")
        if not separator:
            raise ValueError(f"--set takes FIELD=VALUE, got {pair!r}")
        try:
            overrides[name] = json.loads(text)
        except json.JSONDecodeError:
            overrides[name] = text
    return overrides


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bags", nargs="+", help="bag files, globs or directories (.bag, .bag.active)")
    parser.add_argument("--out", required=True, help="output directory")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--steps", type=int, default=None,
                        help=f"gradient steps (default: {DEFAULT_EPOCHS} passes over the training transitions)")
    parser.add_argument("--test-fraction", type=float, default=0.2)
    parser.add_argument("--baselines", action="store_true", help="also fit and score every baseline policy")
    parser.add_argument("--taken-only", action="store_true", help="learn from the logged action only")
    parser.add_argument("--alpha", type=float, default=None,
                        help="weight of local time in eq. 10 (beta = 1 - alpha); default: the alpha the bags' "
                             "learner config recorded, else 0.5")
    parser.add_argument("--gamma", type=float, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="any DQNConfig field")
    parser.add_argument("--workers", type=int, default=None, help="bag reader processes (default: CPU count)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--force", action="store_true", help="overwrite earlier results in --out")
    args = parser.parse_args(argv)
    try:
        prepare_out_dir(args.out, args.force)
        overrides = parse_overrides(args.set)
        if args.gamma is not None:
            overrides["gamma"] = args.gamma
        config = DQNConfig.from_dict({"seed": args.seed, **overrides})
        weights = CostWeights(args.alpha, 1.0 - args.alpha) if args.alpha is not None else None
        if args.steps is not None and args.steps < 1:
            raise ValueError(f"--steps must be at least 1, got {args.steps}")
        chronological_split(2, args.test_fraction)
    except (ValueError, TypeError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)   # tiny network: one thread is fastest, and the result does not depend on cores
    data = read_bags(args.bags, workers=args.workers)
    print(terminal_text(data.report.format()), file=sys.stderr)
    if weights is None:
        try:
            weights = recorded_weights(data)
        except ValueError as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
    try:
        evaluation = retrain(data, args.out, config, args.steps, args.test_fraction, args.baselines, weights,
                             args.taken_only, progress=not args.quiet)
    except ValueError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(format_evaluation(evaluation))
    print(f"checkpoint: {evaluation['checkpoint']}  (learner node: _model:={evaluation['checkpoint']})")
    return 0 if not data.report.failed else 1


if __name__ == "__main__":
    sys.exit(main())
