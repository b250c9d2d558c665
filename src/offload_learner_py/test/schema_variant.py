"""Run by test_state_schema_change.py in a fresh interpreter, on a copy of the package whose state schema was
changed: every field moved, bounds changed and a field added (`rate`, logged, with a value for the records
made before it) to the code's own (input_size, cpu_availability, round_trip_s, local_plan_rate). Checks that each consumer follows the changed schema.

    python schema_variant.py PACKAGE_PARENT PAPER_CHECKPOINT BAG_DIR
"""
import math
import os
import sys
from types import SimpleNamespace

import numpy as np

parent, paper_checkpoint, bag_dir = sys.argv[1:4]
sys.path.insert(0, parent)

import offload_learner_py  # noqa: E402
from offload_learner_py.core.state import STATE_FIELDS, STATE_SCHEMA, State  # noqa: E402

assert offload_learner_py.__file__.startswith(parent), offload_learner_py.__file__
ORDER = ("rate", "round_trip_s", "input_size", "cpu_availability", "local_plan_rate")
CODE_ORDER = ("input_size", "cpu_availability", "round_trip_s", "local_plan_rate")   # the schema it was changed from
assert STATE_FIELDS == ORDER, STATE_FIELDS
RATE, B, D, U, P = range(5)
check = []


def section(name):
    check.append(name)


def refused(call, *fragments, error=ValueError):
    try:
        call()
    except error as caught:
        assert all(f in str(caught) for f in fragments), f"{fragments} not in: {caught}"
        return
    raise AssertionError(f"not refused: {fragments}")


def good(**override):
    values = {"rate": 4.0, "round_trip_s": 0.03, "input_size": 0.5, "cpu_availability": 0.6, "local_plan_rate": 500.0}
    values.update(override)
    return values


# --- State: the fields, their order and their bounds ---------------------------------------------------
section("state")
state = State(**good())
assert tuple(State.__dataclass_fields__) == ORDER and state.as_tuple() == (4.0, 0.03, 0.5, 0.6, 500.0)
assert State(4.0, 0.03, 0.5, 0.6, 500.0) == state
refused(lambda: State(**good(rate=1000.5)), "rate must be in [0, 1000], got 1000.5")
refused(lambda: State(**good(round_trip_s=10.5)), "round_trip_s must be in [0, 10], got 10.5")
State(**good(rate=1000.0, round_trip_s=10.0))

# --- the transition table: columns, checks, .npz and CSV -----------------------------------------------
section("table")
from offload_learner_py.data.dataset import COLUMNS, TransitionTable  # noqa: E402

assert COLUMNS == ("t", *ORDER, "local_s", "cloud_s", "action", "action_propensity", "reward"), COLUMNS
n = 40
rng = np.random.default_rng(5)
columns = {"rate": rng.uniform(1, 100, n), "round_trip_s": rng.uniform(0.01, 0.1, n),
           "input_size": 10 ** rng.uniform(-3, 0, n), "cpu_availability": rng.uniform(0.2, 1.0, n),
           "local_plan_rate": 10 ** rng.uniform(1, 3, n)}
local_s = 0.01 + 0.1 * columns["input_size"] / columns["cpu_availability"]
cloud_s = np.where(columns["cpu_availability"] < 0.6, 0.5, 2.0) * local_s
outcomes = dict(t=np.arange(n), local_s=local_s, cloud_s=cloud_s, action=np.zeros(n, np.int64),
                action_propensity=np.ones(n), reward=np.zeros(n))
table = TransitionTable(**columns, **outcomes)
assert np.array_equal(table.states, np.stack([columns[name] for name in ORDER], axis=1))
refused(lambda: TransitionTable(**{**columns, "rate": np.full(n, 2000.0)}, **outcomes), "rate must be in [0, 1000]")
refused(lambda: TransitionTable(**{**columns, "round_trip_s": np.full(n, 11.0)}, **outcomes),
        "round_trip_s must be in [0, 10]")
table.save_npz(os.path.join(bag_dir, "t.npz"))
table.to_csv(os.path.join(bag_dir, "t.csv"))
with open(os.path.join(bag_dir, "t.csv")) as csv_file:
    assert csv_file.readline().strip() == ",".join(COLUMNS)
for loaded in (TransitionTable.load_npz(os.path.join(bag_dir, "t.npz")),
               TransitionTable.from_csv(os.path.join(bag_dir, "t.csv"))):
    assert np.allclose(loaded.states, table.states)

# --- normalisation, the network's input, the fast decision, checkpoints --------------------------------
section("normalisation")
from offload_learner_py.core.checkpoint import IncompatibleCheckpointError, load_checkpoint, save_checkpoint  # noqa
from offload_learner_py.core.dqn import DQNAgent  # noqa: E402
from offload_learner_py.core.normalisation import StateNormalisation  # noqa: E402

norm = StateNormalisation.fit(table.states)
features = table.states.copy()
features[:, D] = np.log(features[:, D] + 1e-6)
features[:, RATE] = np.log(features[:, RATE] + 1e-3)
features[:, P] = np.log(features[:, P] + 0.1)
assert np.allclose(norm.mean, features.mean(axis=0)) and np.allclose(norm.scale, features.std(axis=0))
assert norm.to_dict()["fields"] == list(ORDER)
agent = DQNAgent(normalisation=norm)
assert agent.q_network.layers[0].in_features == 5 and agent.memory.states.shape[1] == 5
for s in table.states[:2]:
    assert agent.observe(s, 0, 0.0, s) is None
fast = agent.fast_decision()
for s in table.states[:10]:
    assert np.allclose(fast.decide(*s)[1:], agent.q_values(s), atol=1e-5)
save_checkpoint(agent, os.path.join(bag_dir, "variant.pt"))
assert load_checkpoint(os.path.join(bag_dir, "variant.pt")).normalisation == norm
refused(lambda: load_checkpoint(paper_checkpoint), f"normalisation is of the state ({', '.join(CODE_ORDER)}), this "
        f"code's state is ({', '.join(ORDER)})", error=IncompatibleCheckpointError)

# --- the Q-function read by field: learned threshold in u_t, offload point in d_t ------------------------
section("evaluation")
from offload_learner_py.core.evaluation import learned_cpu_threshold  # noqa: E402
from offload_learner_py.offline.summary import FEATURES, learned_offload_input_size, oracle_share_by_tercile  # noqa

threshold = learned_cpu_threshold(lambda s: np.stack([0 * s[:, U], 0.6 - s[:, U]], axis=1), table.states)
assert abs(threshold - 0.6) < 1e-3, threshold
point = learned_offload_input_size(lambda s: np.stack([0 * s[:, D], s[:, D] - 0.1], axis=1), table.states)
assert abs(point - 0.1) < 2e-3, point
assert FEATURES == (("rate", "r_t"), ("round_trip_s", "b_t"), ("input_size", "d_t"), ("cpu_availability", "u_t"),
                    ("local_plan_rate", "p_t"))
assert list(oracle_share_by_tercile(table)) == ["r_t", "b_t", "d_t", "u_t", "p_t"]

section("baselines")
from offload_learner_py.core.lstm_baseline import FEATURE_COLUMNS, LSTMConfig, LSTMPolicy  # noqa: E402
from offload_learner_py.offline import off_policy  # noqa: E402

assert FEATURE_COLUMNS == ORDER
lstm_features = LSTMPolicy(LSTMConfig(features=("rate", "cpu_availability")))._features(table)
assert np.allclose(lstm_features, np.stack([np.log(columns["rate"] + 1e-3), columns["cpu_availability"]], axis=1))
assert off_policy._features(table.states).shape == (n, 1 + 5 + 15)

# --- records: the request log, its bounds, the table rows, a record from before a field -----------------
section("records")
from offload_learner_py.data import records  # noqa: E402


def decision(request_id, **state_values):
    return SimpleNamespace(request_id=request_id, **state_values, action=0, action_propensity=1.0, probe=True)


def outcome(request_id):
    return SimpleNamespace(request_id=request_id, local_s=0.1, cloud_s=0.2)


assert records.DECISION_FIELDS[1:6] == ORDER and records.DECISION_DEFAULTS["rate"] == 2.0
log = records.pair_records([decision(1, **good()), decision(2, input_size=0.5, cpu_availability=0.6,
                                                            round_trip_s=0.03)], [outcome(1), outcome(2)])
assert log["rate"].tolist() == [4.0, 2.0]           # a decision without the field: the schema's `missing`
assert log["local_plan_rate"].tolist() == [500.0, 0.0]
rows = [[4.0, 0.03, 0.5, 0.6, 500.0], [2.0, 0.03, 0.5, 0.6, 0.0]]
assert records.transition_table(log).states.tolist() == rows
assert off_policy.LoggedSteps.from_log(log).states.tolist() == rows
for bad, why in ((good(rate=150.0), "rate 150.0 outside [0, 100]"), (good(input_size=60.0), "input_size 60.0 "
                 "outside [0, 50]"), (good(round_trip_s=6.0), "round_trip_s 6.0 outside [0, 5]")):
    refused(lambda: records.pair_records([decision(3, **bad)], [outcome(3)]), why, error=records.RecordMismatchError)

# --- bags: decoded by the schema's names, an older definition without the field -------------------------
section("bags")
from offload_demos.bag_writer import installed_definitions, probe_request, typestore_for, write_requests  # noqa
from offload_learner_py.core.reward import reward  # noqa: E402
from offload_learner_py.data.bags import read_bags  # noqa: E402

paper_decision, outcome_msg = installed_definitions()
assert "float64 rate" not in paper_decision
requests = []
for i in range(6):
    d, o = probe_request(100 + i, 0.5, 0.6, 0.03, 0.1, 0.2, 0, 1.0, reward(0, 0.1, 0.2))
    requests.append(({**d, "rate": 10.0 + i}, o))
new_bag = write_requests(os.path.join(bag_dir, "new.bag"), requests,
                         store=typestore_for(paper_decision.rstrip("\n") + "\nfloat64 rate\n", outcome_msg))
old_bag = write_requests(os.path.join(bag_dir, "old.bag"), requests, store=typestore_for(paper_decision, outcome_msg))
for path, rates in ((new_bag, [10.0 + i for i in range(6)]), (old_bag, [2.0] * 6)):
    data = read_bags([path], workers=1)
    assert data.report.bags[0].ok and data.report.bags[0].invalid == 0, data.report.format()
    assert data.transition_table().rate.tolist() == rates

# --- the learner's decision message: one field per schema field ------------------------------------------
section("decision message")
from offload_learner_py.nodes import learner_io  # noqa: E402

learner_io.OffloadDecision = lambda **fields: SimpleNamespace(**fields)   # the real one has no `rate`
learner_io.stamped = lambda msg: msg
routing = SimpleNamespace(state=state, decision=SimpleNamespace(action=1, propensity=0.9, q_local=0.1, q_cloud=0.2,
                                                                 model_version=""),
                          request_id=7, probe=False, mode="deployed", action=1, breaker="closed", deadline_s=math.nan)
msg = learner_io.decision_msg(routing, "dqn", 3)
assert {name: getattr(msg, name) for name in ORDER} == state.as_dict()

print("checked:", ", ".join(check))
