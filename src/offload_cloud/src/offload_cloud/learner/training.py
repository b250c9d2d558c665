"""One training round of the fleet learner: each robot's recent rows from the pool, the DQN trained (warm-started
from the version in use) with offload_learner_py.offline.retrain's training, the candidate gated on each
contributing robot's most recent rows (held out of its training), and the round recorded in the store. A version
in use that this code cannot load (a model of another state schema: trained before p_t was added) is neither
warm-started nor compared with: the round trains from scratch and judges as when no version is in use, so the
first candidate that passes replaces it (the robots refuse it anyway, keeping the model they have).

Per robot the window is its last `window_rows` requests (bags read newest first only as far as needed is not
attempted: a robot's pool directory is bounded by its disk share, and it is read whole). The window's first
1 - holdout of requests train (the rows with both latencies: the transition table), the rest judge (every logged
request, probe or not: off-policy evaluation). A robot with fewer than `min_robot_rows` requests does not
contribute. When no version is in use yet, the candidate is judged against what each robot logged: its greedy
action from the Q-values it recorded, else the action it took. A robot whose rows cannot judge the candidate
abstains (published_by)."""
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Dict, Optional

import numpy as np
import torch

from offload_cloud.learner.gate import gate
from offload_cloud.learner.pool import ExperiencePool
from offload_cloud.learner.store import ModelStore
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent, greedy_actions
from offload_learner_py.core.model_file import ModelFileError, agent_model_bytes, load_model, model_version
from offload_learner_py.data.bags import read_bags
from offload_learner_py.data.dataset import COLUMNS, TransitionTable
from offload_learner_py.data.records import RequestLog, cloud_answered, transition_table
from offload_learner_py.offline.off_policy_steps import LoggedSteps
from offload_learner_py.offline.retrain import DEFAULT_EPOCHS, gradient_steps_for, train_offline

LOG = logging.getLogger("offload_cloud.learner")


@dataclass
class TrainingConfig:
    window_rows: int = 2000
    holdout: float = 0.3
    min_robot_rows: int = 20
    margin_s: float = 0.0
    epochs: float = DEFAULT_EPOCHS
    dqn: Dict = field(default_factory=dict)     # DQNConfig overrides (--set)


def warm_agent(data: bytes, config: DQNConfig) -> DQNAgent:
    """A DQNAgent holding a model file's network and normalisation (its layer widths replace the config's)."""
    fast, normalisation = load_model(data)
    widths = tuple(int(w.shape[1]) for w in fast.weights[:-1])
    agent = DQNAgent(DQNConfig.from_dict({**config.to_dict(), "hidden_sizes": list(widths)}), normalisation)
    linears = [m for m in agent.q_network.layers if isinstance(m, torch.nn.Linear)]
    with torch.no_grad():
        for layer, w, b in zip(linears, fast.weights, fast.biases):
            layer.weight.copy_(torch.from_numpy(np.ascontiguousarray(w.T)))
            layer.bias.copy_(torch.from_numpy(b))
    agent.target_network.load_state_dict(agent.q_network.state_dict())
    return agent


def agent_in_use(data: Optional[bytes], config: DQNConfig) -> Optional[DQNAgent]:
    """warm_agent of the version in use; None when there is none or this code cannot load it (said in the log)."""
    if not data:
        return None
    try:
        return warm_agent(data, config)
    except ModelFileError as error:
        LOG.warning("the version in use cannot be loaded here (%s): this round trains from scratch", error)
        return None


def _rows(log: RequestLog, rows: np.ndarray) -> RequestLog:
    return RequestLog({name: values[rows] for name, values in log.columns.items()})


def logged_actions(log: RequestLog, rows: np.ndarray) -> np.ndarray:
    q_local, q_cloud = log["q_local"][rows], log["q_cloud"][rows]
    known = np.isfinite(q_local) & np.isfinite(q_cloud)
    taken = log["routed" if "routed" in log.columns else "action"][rows].astype(np.int64)
    return np.where(known, greedy_actions(np.stack([q_local, q_cloud], axis=-1)), taken)


def training_round(pool: ExperiencePool, store: ModelStore, config: TrainingConfig) -> Optional[dict]:
    """Trains, gates and records one round; the history entry, or None when no robot has enough rows."""
    started = time.monotonic()
    dqn = DQNConfig.from_dict(config.dqn)
    current = store.state()["current"]
    current_data = store.get(current) if current else None
    tables, answered, judged, used = [], [], {}, {}
    for robot in pool.robots():
        data = read_bags(pool.bag_paths(robot), workers=1)
        log = data.log
        if len(log) < config.min_robot_rows:
            continue
        window = np.arange(max(0, len(log) - config.window_rows), len(log))
        cut = int(round(len(window) * (1.0 - config.holdout)))
        train_log = _rows(log, window[:cut])
        table = transition_table(train_log)
        steps = LoggedSteps.from_log(log, window[cut:])
        if len(table) == 0 or len(steps) == 0:
            continue
        tables.append(table)
        answered.append(cloud_answered(train_log))
        used[robot] = len(table)
        judged[robot] = (steps, logged_actions(log, window[cut:]) if len(steps) == len(window) - cut else None)
    if not tables or sum(used.values()) < 2:
        return None
    table = TransitionTable(**{name: np.concatenate([getattr(t, name) for t in tables]) for name in COLUMNS})
    base = agent_in_use(current_data, dqn)
    steps_count = gradient_steps_for(len(table), dqn, config.epochs)
    result = train_offline(table, base.config if base else dqn, steps_count, agent=base,
                           cloud_answered=np.concatenate(answered))
    data = agent_model_bytes(result.agent)
    version = model_version(data)
    reference = agent_in_use(current_data, dqn) if base is not None else None
    figures = {}
    for robot, (steps, logged) in judged.items():
        new = result.agent.greedy_actions(steps.states)
        old = reference.greedy_actions(steps.states) if reference else logged
        if old is None:   # rows left out by LoggedSteps (nothing known of them): judge on the taken side
            old = steps.action
        ok, difference = gate(steps, new, old, config.margin_s)
        figures[robot] = {"accepted": ok, "judged": difference.available, "rows": len(steps),
                          "difference_s": _finite(difference.value), "low_s": _finite(difference.low),
                          "high_s": _finite(difference.high), "disagree": int(np.sum(new != old)),
                          "reason": difference.reason}
    passed = published_by(figures)
    entry = {"version": version, "parent": current, "rows": used, "gate": figures, "gate_passed": passed,
             "gradient_steps": steps_count, "train_s": round(time.monotonic() - started, 3)}
    if version == current:
        entry["gate_passed"], passed = False, False   # nothing new to publish
    entry["published"] = store.record_round(entry, data if passed else None)
    LOG.info("training round: %d rows from %d robots, %d steps in %.2f s, candidate %s %s", len(table), len(used),
             steps_count, entry["train_s"], version[:12], "published" if entry["published"] else "refused by the gate")
    return entry


def published_by(figures: Dict[str, dict]) -> bool:
    """Whether a candidate passes the gate: every robot whose rows can judge it (an estimate, not "n/a") says it
    is not worse, and at least one can. A robot whose rows cannot (a deployed robot logs few probes, and a
    greedy logger never takes the side a changed decision needs) abstains rather than vetoes: else one such
    robot in the fleet would keep every version from every robot. Where it abstained, its own guard judges the
    version live (online/model_guard.py) and rolls it back when it is worse beyond noise."""
    judging = [figure for figure in figures.values() if figure["judged"]]
    return bool(judging) and all(figure["accepted"] for figure in judging)


def _finite(value: float) -> Optional[float]:
    return float(value) if math.isfinite(value) else None
