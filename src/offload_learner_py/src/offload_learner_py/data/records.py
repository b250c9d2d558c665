"""The learner's decision and outcome records (OffloadDecision / OffloadOutcome messages, or anything with
the same fields) paired by request id into the one request log, and that log turned into the transition
table. One pairing serves every source: the bag reader (tolerant: what real bags hold is counted and
skipped) and live messages or tests (`pair_records`, strict: any disagreement is an error). No ROS import.
"""
import math
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional, Tuple

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.reward import CostWeights, reward
from offload_learner_py.core.state import MAX_LATENCY_S, STATE_FIELDS, STATE_SCHEMA
from offload_learner_py.data.dataset import TransitionTable

NO_PATH_DELIVERED = 255   # `delivered` when neither side produced a path
NO_VALUE = object()       # a field the record lacks, derived from the others (see _complete)
# Physical bounds of a row: beyond them a value is damage or hostility, and one such row would own every
# figure (an IPS weight of 1e300, a mean latency of 1e308 s, a NaN network). Such rows are counted skips.
# The state's are the schema's (each field's [low, recorded_max]); MAX_LATENCY_S bounds l_local and l_cloud.
MIN_PROPENSITY = 1e-3       # importance weights stay at most 1000

# Per field: the value when a record (an older message definition) lacks it; None: the field is required.
# The state's fields are the schema's, named as in OffloadDecision, with the schema's `missing` value.
DECISION_DEFAULTS = {"request_id": None, **{f.name: f.missing for f in STATE_SCHEMA},
                     "action": None, "action_propensity": None, "q_local": math.nan, "q_cloud": math.nan,
                     "policy": "", "model_steps": 0, "probe": NO_VALUE, "mode": "", "routed": NO_VALUE, "breaker": "",
                     "deadline_s": math.nan, "model_version": ""}
OUTCOME_DEFAULTS = {"request_id": None, "action": NO_VALUE, "delivered": NO_PATH_DELIVERED,
                    "local_measured": NO_VALUE, "local_s": None, "local_status": 0, "cloud_measured": NO_VALUE,
                    "cloud_s": None, "cloud_status": 0, "cloud_timeout": False, "reward_valid": NO_VALUE,
                    "reward": NO_VALUE, "loss_valid": False, "loss": math.nan, "delivered_s": math.nan,
                    "hedged": False, "transitions": 0, "imputed": NO_PATH_DELIVERED, "robot_cpu_s": math.nan,
                    "bridge_cpu_s": math.nan, "learner_cpu_s": math.nan, "link_bytes_sent": 0,
                    "link_bytes_received": 0}
DECISION_FIELDS = tuple(DECISION_DEFAULTS)
OUTCOME_FIELDS = tuple(OUTCOME_DEFAULTS)
_TEXT = ("policy", "mode", "breaker", "model_version")
_FLOAT = (*STATE_FIELDS, "action_propensity", "q_local", "q_cloud", "reward", "loss")


class RecordMismatchError(ValueError):
    """Decisions and outcomes disagree (an outcome without a decision, or a different action)."""


@dataclass
class RequestLog:
    """Every request of a run, in time order: the decision fields and the outcome fields (`outcome_<name>`)
    as numpy columns, `has_outcome` (false for a decision whose outcome never came, kept only by strict
    pairing) and `stamp_ns`."""
    columns: Dict[str, np.ndarray]

    def __len__(self) -> int:
        return len(self.columns["request_id"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]


@dataclass
class PairingCounts:
    """What pairing found and kept (a bag's report carries these)."""
    decisions: int = 0
    outcomes: int = 0
    requests: int = 0                 # decision + outcome pairs kept
    probe_steps: int = 0
    rewarded_steps: int = 0           # both latencies: rows of the transition table
    one_latency_steps: int = 0        # kept for off-policy evaluation only
    dropped_no_outcome: int = 0
    orphan_outcomes: int = 0
    duplicate_decisions: int = 0
    duplicate_outcomes: int = 0
    invalid: int = 0                  # pairs dropped for a value the table forbids
    invalid_examples: List[str] = field(default_factory=list)

    def skip(self, why: str) -> None:
        self.invalid += 1
        self.note(why)

    def note(self, example: str) -> None:
        if len(self.invalid_examples) < 5:
            self.invalid_examples.append(example)


def _finite(value) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value)


def _complete(decision: Dict, outcome: Dict, weights: CostWeights) -> Optional[str]:
    """Fill what an older record lacked and check the pair against the table's rules. Returns why the pair
    is invalid, or None."""
    if outcome["action"] is NO_VALUE:
        outcome["action"] = decision["action"]
    if decision["routed"] is NO_VALUE:
        decision["routed"] = decision["action"]
    if int(outcome["action"]) != int(decision["action"]):
        return f"decision action {decision['action']}, outcome action {outcome['action']}"
    if decision["action"] not in (LOCAL, CLOUD):
        return f"action {decision['action']} is neither local nor cloud"
    for f in STATE_SCHEMA:
        value = decision[f.name]
        if not (_finite(value) and f.low <= value <= f.recorded_high):
            return f"{f.name} {value} outside [{f.low:g}, {f.recorded_high:g}]"
    propensity = decision["action_propensity"]
    if not (_finite(propensity) and MIN_PROPENSITY <= propensity <= 1.0):
        return f"action_propensity {propensity} outside [{MIN_PROPENSITY:g}, 1]"
    for side in ("local", "cloud"):
        if outcome[f"{side}_measured"] is NO_VALUE:
            value = outcome[f"{side}_s"]
            outcome[f"{side}_measured"] = bool(_finite(value) and value > 0)
    if decision["probe"] is NO_VALUE:
        decision["probe"] = bool(outcome["local_measured"] and outcome["cloud_measured"])
    # The side the router called first is measured, except on a probe, where the side that lost the race may
    # have been dropped before it started (a newer request needed it), and on a hedged request, where the other
    # side answered first and the first was cancelled; either still measured one side.
    routed, other = ("cloud", "local") if decision["routed"] == CLOUD else ("local", "cloud")
    if decision["probe"]:
        if not (outcome["local_measured"] or outcome["cloud_measured"]):
            return "a probe with no measured latency"
    elif not outcome[f"{routed}_measured"] and not (outcome["hedged"] and outcome[f"{other}_measured"]):
        return f"the routed side ({routed}) has no measured latency"
    for side in ("local", "cloud"):
        value = outcome[f"{side}_s"]
        if outcome[f"{side}_measured"] and not (_finite(value) and 0 < value <= MAX_LATENCY_S):
            return f"{side}_s {value} outside (0, {MAX_LATENCY_S:g}]"
    for side in ("local", "cloud"):
        if not outcome[f"{side}_measured"]:
            outcome[f"{side}_s"] = math.nan    # not measured: no number stands in for it
    both = outcome["local_measured"] and outcome["cloud_measured"]
    if outcome["reward"] is NO_VALUE:     # a record without the reward: eq. 10 from both latencies
        outcome["reward"] = reward(int(decision["action"]), outcome["local_s"], outcome["cloud_s"], weights) \
            if both else math.nan
    if outcome["reward_valid"] is NO_VALUE:
        outcome["reward_valid"] = bool(both and _finite(outcome["reward"]))
    if outcome["reward_valid"]:
        if not both:
            return "reward marked valid without both latencies"
        if not (_finite(outcome["reward"]) and -1.0 <= outcome["reward"] <= 1.0):
            return f"reward {outcome['reward']}"
    return None


def _unanswered(decision: Dict) -> Dict:
    """The outcome columns of a decision whose outcome never came: nothing measured, nothing delivered."""
    values = {name: (math.nan if name.endswith("_s") or name in _FLOAT else 0) for name in OUTCOME_FIELDS}
    values.update(delivered=NO_PATH_DELIVERED, imputed=NO_PATH_DELIVERED)
    if decision["routed"] is NO_VALUE:
        decision["routed"] = decision["action"]
    if decision["probe"] is NO_VALUE:
        decision["probe"] = False
    return values


def _columns(rows: List[Tuple[Dict, Optional[Dict], int]]) -> Dict[str, np.ndarray]:
    columns = {name: [decision[name] for decision, _, _ in rows] for name in DECISION_FIELDS}
    for name in OUTCOME_FIELDS:
        if name not in ("request_id", "action"):
            columns[f"outcome_{name}"] = [outcome[name] for _, outcome, _ in rows]
    arrays = {}
    for name, values in columns.items():
        if name in _TEXT:
            arrays[name] = np.array([str(v) for v in values], dtype=object)
        elif name in ("request_id", "model_steps"):
            arrays[name] = np.array(values, dtype=np.uint64).astype(np.int64) if values else np.zeros(0, np.int64)
        else:
            plain = name[len("outcome_"):] if name.startswith("outcome_") else name
            arrays[name] = np.array(values, dtype=np.float64 if plain.endswith("_s") or plain in _FLOAT
                                    else np.int64)
    return arrays


class Pairing:
    """Decisions and outcomes in any order, paired by request id.

    Tolerant (a bag): duplicates, orphans, decisions without an outcome and pairs that break the table's
    rules are counted in `counts` and dropped. Strict (`strict=True`): each of those is a
    RecordMismatchError, except a decision whose outcome has not come yet, which is kept with
    `has_outcome` false (a run stopped mid-request)."""

    def __init__(self, counts: Optional[PairingCounts] = None, weights: CostWeights = CostWeights(),
                 strict: bool = False):
        self.counts = counts if counts is not None else PairingCounts()
        self.weights, self.strict = weights, strict
        self._decisions: Dict[int, Tuple[Dict, int]] = {}
        self._outcomes: Dict[int, Dict] = {}

    def _refuse(self, why: str) -> None:
        if self.strict:
            raise RecordMismatchError(why)

    def decision(self, values: Dict, stamp_ns: int = 0) -> None:
        self._keep(self._decisions, values, (values, stamp_ns), "decision")

    def outcome(self, values: Dict) -> None:
        self._keep(self._outcomes, values, values, "outcome")

    def _keep(self, store: Dict, values: Dict, kept, kind: str) -> None:
        """The first record of each request id; a second one is a duplicate."""
        setattr(self.counts, f"{kind}s", getattr(self.counts, f"{kind}s") + 1)
        request_id = int(values["request_id"])
        if request_id in store:
            self._refuse(f"two {kind}s for request {request_id}")
            setattr(self.counts, f"duplicate_{kind}s", getattr(self.counts, f"duplicate_{kind}s") + 1)
            return
        store[request_id] = kept

    def log(self) -> RequestLog:
        counts, rows, answered = self.counts, [], []
        outcomes = dict(self._outcomes)
        if self.strict:
            orphans = sorted(set(outcomes) - set(self._decisions))
            if orphans:
                raise RecordMismatchError(f"outcome for request {orphans[0]} has no decision")
        for request_id, (decision, stamp) in self._decisions.items():
            outcome = outcomes.pop(request_id, None)
            if outcome is None:
                if self.strict:
                    rows.append((decision, _unanswered(decision), stamp))
                    answered.append(False)
                else:
                    counts.dropped_no_outcome += 1
                continue
            why = _complete(decision, outcome, self.weights)
            if why is not None:
                self._refuse(f"request {request_id}: {why}")
                counts.skip(f"request {request_id}: {why}")
                continue
            rows.append((decision, outcome, stamp))
            answered.append(True)
        counts.orphan_outcomes = len(outcomes)
        order = sorted(range(len(rows)), key=lambda k: (rows[k][2], rows[k][0]["request_id"]))
        columns = _columns([rows[k] for k in order])
        columns["has_outcome"] = np.array([answered[k] for k in order], dtype=bool)
        columns["stamp_ns"] = np.array([rows[k][2] for k in order], dtype=np.int64)
        has = columns["has_outcome"]
        counts.requests = int(has.sum())
        counts.probe_steps = int(np.sum(columns["probe"].astype(bool) & has)) if rows else 0
        counts.rewarded_steps = int(np.sum(columns["outcome_reward_valid"].astype(bool) & has)) if rows else 0
        counts.one_latency_steps = counts.requests - counts.rewarded_steps
        return RequestLog(columns)


def _as_dict(record, defaults: Dict) -> Dict:
    """A record's fields (an attribute object: a ROS message, a namespace) with the defaults of those it lacks."""
    values = {}
    for name, default in defaults.items():
        if default is None:
            values[name] = getattr(record, name)       # required: an AttributeError names it
        else:
            values[name] = getattr(record, name, default)
    return values


def pair_records(decisions: Iterable, outcomes: Iterable, weights: CostWeights = CostWeights()) -> RequestLog:
    """Strict pairing of attribute records (live messages, tests): see Pairing."""
    pairing = Pairing(weights=weights, strict=True)
    for decision in decisions:
        pairing.decision(_as_dict(decision, DECISION_DEFAULTS))
    for outcome in outcomes:
        pairing.outcome(_as_dict(outcome, OUTCOME_DEFAULTS))
    return pairing.log()


def transition_table(log: RequestLog, metadata: Dict = None) -> TransitionTable:
    """The transition-table rows of a run: every request whose reward is known (both latencies
    measured, the request plannable), t being its request id."""
    keep = rewarded_rows(log)
    pick = lambda name: np.asarray(log[name])[keep] if len(log) else np.zeros(0)  # noqa: E731
    rewards = pick("outcome_reward").astype(np.float64)
    if not np.all(np.isfinite(rewards)):
        raise RecordMismatchError("an outcome flags its reward valid but holds a non-finite reward")
    return TransitionTable(t=pick("request_id").astype(np.int64), **{name: pick(name) for name in STATE_FIELDS},
                           local_s=pick("outcome_local_s"), cloud_s=pick("outcome_cloud_s"),
                           action=pick("action").astype(np.int64), action_propensity=pick("action_propensity"),
                           reward=rewards, metadata=dict(metadata or {}))


def cloud_answered(log: RequestLog) -> np.ndarray:
    """Per transition-table row (`transition_table`'s rows, in its order): whether its cloud side answered with a
    path, so l_cloud is the round trip plus the cloud's work rather than a timeout or a failure's cost. Read from
    the outcome's own status and timeout flag, so a run with any cloud timeout is told apart alike."""
    from offload_planner_cpp import PlanStatus   # the core's status codes (a binding, no ROS)

    keep = rewarded_rows(log)
    if not keep.any():
        return np.zeros(0, dtype=bool)
    status = np.asarray(log["outcome_cloud_status"])[keep]
    return (status == int(PlanStatus.OK)) & ~np.asarray(log["outcome_cloud_timeout"])[keep].astype(bool)


def rewarded_rows(log: RequestLog) -> np.ndarray:
    """The log rows that are transition-table rows (a reward from two measured latencies), as a mask."""
    if len(log) == 0:
        return np.zeros(0, dtype=bool)
    return log["has_outcome"].astype(bool) & log["outcome_reward_valid"].astype(bool)
