"""The learner's decision and outcome records (OffloadDecision / OffloadOutcome messages, or anything
with the same fields) turned back into the one transition table. No ROS import: the records may come
from rosbag, from the rosbags library or from a test."""
from dataclasses import dataclass
from typing import Dict, Iterable

import numpy as np

from offload_learner_py.data.dataset import TransitionTable

NO_PATH_DELIVERED = 255
# Fields added with the two modes and robot cost accounting, and their value in records made before them
# ("routed" defaults to the decision's action).
OPTIONAL_DECISION_FIELDS = {"mode": "", "routed": None, "breaker": "", "deadline_s": float("nan")}
OPTIONAL_OUTCOME_FIELDS = {"hedged": False, "transitions": 0, "imputed": NO_PATH_DELIVERED,
                           "robot_cpu_s": float("nan"), "bridge_cpu_s": float("nan"), "link_bytes_sent": 0,
                           "link_bytes_received": 0}
DECISION_FIELDS = ("request_id", "input_size", "cpu_availability", "round_trip_s", "action",
                   "action_propensity", "q_local", "q_cloud", "policy", "model_steps", "probe",
                   *OPTIONAL_DECISION_FIELDS)
OUTCOME_FIELDS = ("request_id", "action", "delivered", "local_measured", "local_s", "local_status",
                  "cloud_measured", "cloud_s", "cloud_status", "cloud_timeout", "reward_valid", "reward",
                  "loss_valid", "loss", "delivered_s", *OPTIONAL_OUTCOME_FIELDS)


class RecordMismatchError(ValueError):
    """Decisions and outcomes disagree (an outcome without a decision, or a different action)."""


@dataclass
class RequestLog:
    """Every request of a run, in request-id order: the decision fields and the outcome fields as
    numpy columns (outcome columns hold NaN / 0 where a decision has no outcome yet)."""
    columns: Dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.columns["request_id"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]


def pair_records(decisions: Iterable, outcomes: Iterable) -> RequestLog:
    """Pair by request id. Each outcome must have exactly one decision with the same action; a
    decision without an outcome (the run stopped mid-request) is kept with `has_outcome` false."""
    by_id = {}
    for decision in decisions:
        request_id = int(decision.request_id)
        if request_id in by_id:
            raise RecordMismatchError(f"two decisions for request {request_id}")
        by_id[request_id] = (decision, None)
    for outcome in outcomes:
        request_id = int(outcome.request_id)
        if request_id not in by_id:
            raise RecordMismatchError(f"outcome for request {request_id} has no decision")
        decision, previous = by_id[request_id]
        if previous is not None:
            raise RecordMismatchError(f"two outcomes for request {request_id}")
        if int(outcome.action) != int(decision.action):
            raise RecordMismatchError(f"request {request_id}: decision action {decision.action}, outcome action "
                                      f"{outcome.action}")
        by_id[request_id] = (decision, outcome)
    ids = sorted(by_id)
    columns = {name: [] for name in DECISION_FIELDS}
    columns.update({f"outcome_{name}": [] for name in OUTCOME_FIELDS if name not in ("request_id", "action")})
    columns["has_outcome"] = []
    for request_id in ids:
        decision, outcome = by_id[request_id]
        for name in DECISION_FIELDS:
            default = decision.action if name == "routed" else OPTIONAL_DECISION_FIELDS.get(name)
            columns[name].append(getattr(decision, name, default) if name in OPTIONAL_DECISION_FIELDS
                                 else getattr(decision, name))
        columns["has_outcome"].append(outcome is not None)
        for name in OUTCOME_FIELDS:
            if name in ("request_id", "action"):
                continue
            missing = OPTIONAL_OUTCOME_FIELDS.get(name, float("nan") if name.endswith("_s") or name in ("reward", "loss")
                                                  else 0)
            columns[f"outcome_{name}"].append(getattr(outcome, name, missing) if outcome is not None else missing)
    arrays = {}
    for name, values in columns.items():
        arrays[name] = np.array(values, dtype=object if name in ("policy", "mode", "breaker") else None)
    if not ids:
        arrays = {name: np.zeros(0) for name in columns}
    return RequestLog(arrays)


def transition_table(log: RequestLog, metadata: Dict = None) -> TransitionTable:
    """The transition-table rows of a run: every request whose reward is known (both latencies
    measured, the request plannable), t being its request id."""
    if len(log) == 0:
        keep = np.zeros(0, dtype=bool)
    else:
        keep = log["has_outcome"].astype(bool) & log["outcome_reward_valid"].astype(bool)
    pick = lambda name: np.asarray(log[name])[keep] if len(log) else np.zeros(0)  # noqa: E731
    rewards = pick("outcome_reward").astype(np.float64)
    if not np.all(np.isfinite(rewards)):
        raise RecordMismatchError("an outcome flags its reward valid but holds a non-finite reward")
    return TransitionTable(t=pick("request_id").astype(np.int64), input_size=pick("input_size"),
                           cpu_availability=pick("cpu_availability"), round_trip_s=pick("round_trip_s"),
                           local_s=pick("outcome_local_s"), cloud_s=pick("outcome_cloud_s"),
                           action=pick("action").astype(np.int64), action_propensity=pick("action_propensity"),
                           reward=rewards, metadata=dict(metadata or {}))

