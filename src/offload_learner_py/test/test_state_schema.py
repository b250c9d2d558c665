"""core/state.py's schema is the one list of the state's fields: State, the transition table, the decision
records and messages, normalisation and the reports follow it. Every test here runs over the schema's fields,
so a field added to it is covered without a new test; test_state_schema_change.py changes the schema (order,
bounds, a field more) and checks that the consumers follow."""
import math
import re
from types import SimpleNamespace

import numpy as np
import pytest

from recordtools import decision, outcome
from statetools import PLAN_RATE
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.state import STATE_FIELDS, STATE_SCHEMA, STATE_SIZE, State, StateField, StateSchema
from offload_learner_py.data import records
from offload_learner_py.data.dataset import COLUMNS, TransitionTable

FIELDS = list(STATE_SCHEMA)
IDS = [f.name for f in FIELDS]
GOOD = {"input_size": 0.5, "cpu_availability": 0.6, "round_trip_s": 0.03, "local_plan_rate": PLAN_RATE}
PAPER_FIELDS = ("input_size", "cpu_availability", "round_trip_s")


def _spread(f, rng, n):
    """Values across a field's range; a log-scaled field's across three decades above its log floor (a spread far
    below the floor is invisible on the log scale and only tests float32 rounding)."""
    high = min(f.high, 2.0) if f.log_floor is None or f.log_floor < 1 else 1e3 * f.log_floor
    return rng.uniform(f.low, high, n)


def _good_state() -> dict:
    return {f.name: GOOD.get(f.name, f.low) for f in FIELDS}


def _table(n=4, **override) -> TransitionTable:
    columns = {name: np.full(n, value) for name, value in _good_state().items()}
    columns.update(t=np.arange(n), local_s=np.full(n, 0.1), cloud_s=np.full(n, 0.2), action=np.zeros(n, np.int64),
                   action_propensity=np.ones(n), reward=np.zeros(n))
    columns.update(override)
    return TransitionTable(**columns)


def test_the_schema_is_the_papers_state_then_the_robots_plan_rate():
    assert STATE_FIELDS == (*PAPER_FIELDS, "local_plan_rate") == tuple(IDS)
    assert [f.symbol for f in FIELDS] == ["d_t", "u_t", "b_t", "p_t"] and STATE_SIZE == 4
    d, u, b, p = FIELDS
    assert (d.low, d.high, d.recorded_high, d.log_floor) == (0.0, math.inf, 1e6, 1e-6)
    assert (u.low, u.high, u.recorded_high, u.log_floor) == (0.0, 1.0, 1.0, None)
    assert (b.low, b.high, b.recorded_high, b.log_floor, b.unit) == (0.0, math.inf, 3600.0, None, "s")
    assert (p.low, p.high, p.recorded_high, p.log_floor, p.unit) == (0.0, math.inf, 1e6, 0.1, "d_t/s")
    assert all(f.missing is None for f in FIELDS[:3])     # the paper's fields are in every recorded decision
    assert p.missing == 0.0                               # p_t was not: "not measured", as before a robot's first plan
    assert [STATE_SCHEMA.index(name) for name in IDS] == [0, 1, 2, 3] and STATE_SCHEMA["round_trip_s"] is b
    with pytest.raises(KeyError, match="'battery' is not a state field"):
        STATE_SCHEMA.index("battery")


def test_state_has_the_schemas_fields_in_its_order():
    state = State(**_good_state())
    assert tuple(State.__dataclass_fields__) == STATE_FIELDS
    assert state.as_tuple() == tuple(_good_state()[name] for name in STATE_FIELDS)
    assert state.as_dict() == _good_state() and list(state.as_dict()) == list(STATE_FIELDS)
    assert np.array_equal(state.as_array(), np.array(state.as_tuple()))
    assert State(*state.as_tuple()) == state          # positional arguments in schema order


@pytest.mark.parametrize("f", FIELDS, ids=IDS)
def test_a_state_outside_a_fields_physical_bounds_is_refused(f):
    State(**{**_good_state(), f.name: f.low})         # the bounds are inclusive
    if math.isfinite(f.high):
        State(**{**_good_state(), f.name: f.high})
    outside = [f.low - 1e-9, math.nan, math.inf, -math.inf] + ([f.high + 1e-9] if math.isfinite(f.high) else [])
    for value in outside:
        with pytest.raises(ValueError, match=re.escape(f"{f.name} must be {f.rule}, got")):
            State(**{**_good_state(), f.name: value})


@pytest.mark.parametrize("f", FIELDS, ids=IDS)
def test_the_table_has_a_column_per_field_in_schema_order_and_refuses_values_outside_its_bounds(f, tmp_path):
    assert COLUMNS[1:1 + STATE_SIZE] == STATE_FIELDS
    table = _table()
    assert np.array_equal(table.states[:, STATE_SCHEMA.index(f.name)], getattr(table, f.name))
    bad = np.full(4, GOOD.get(f.name, f.low))
    bad[2] = f.low - 1.0
    with pytest.raises(ValueError, match=re.escape(f"{f.name} must be {f.bounds_text} in every row; row 2")):
        _table(**{f.name: bad})
    if math.isfinite(f.high):
        bad[2] = f.high + 1.0
        with pytest.raises(ValueError, match=f"{f.name} must be"):
            _table(**{f.name: bad})
    path = tmp_path / "t.csv"
    table.to_csv(str(path))
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)


def test_a_table_without_a_schema_column_or_with_another_is_refused():
    columns = {name: getattr(_table(), name) for name in COLUMNS}
    with pytest.raises(TypeError, match="missing cpu_availability"):
        TransitionTable(**{k: v for k, v in columns.items() if k != "cpu_availability"})
    with pytest.raises(TypeError, match="unknown battery"):
        TransitionTable(**columns, battery=np.ones(4))


def test_decision_records_carry_every_field_and_the_table_rows_take_them():
    assert records.DECISION_FIELDS[1:1 + STATE_SIZE] == STATE_FIELDS
    assert {name: records.DECISION_DEFAULTS[name] for name in STATE_FIELDS} == {f.name: f.missing for f in FIELDS}
    log = records.pair_records([decision(1, d=0.25, u=0.75, b=0.125, p=400.0)], [outcome(1)])
    table = records.transition_table(log)
    assert table.states.tolist() == [[0.25, 0.75, 0.125, 400.0]]


@pytest.mark.parametrize("f", FIELDS, ids=IDS)
def test_a_recorded_decision_beyond_a_fields_recorded_bounds_is_a_counted_skip(f):
    pairing = records.Pairing()
    too_big = {**_good_state(), f.name: f.recorded_high * 2 + 1}
    for request_id, state in ((1, _good_state()), (2, too_big)):
        pairing.decision({**records.DECISION_DEFAULTS, **vars(decision(request_id)), **state})
        pairing.outcome({**records.OUTCOME_DEFAULTS, **vars(outcome(request_id))})
    log = pairing.log()
    assert log["request_id"].tolist() == [1] and pairing.counts.invalid == 1
    assert pairing.counts.invalid_examples == [f"request 2: {f.name} {f.recorded_high * 2 + 1} outside "
                                               f"[{f.low:g}, {f.recorded_high:g}]"]


def test_the_decision_message_has_every_field_as_float64_and_the_learner_fills_them_from_the_state(monkeypatch):
    # Skipped only where the built messages are not on the path (`make mutate` runs this file on a copy of the
    # package alone).
    OffloadDecision = pytest.importorskip("offload_msgs.msg", reason="offload_msgs is not built").OffloadDecision
    from offload_learner_py.nodes import learner_io

    types = dict(zip(OffloadDecision.__slots__, OffloadDecision._slot_types))
    assert {name: types.get(name) for name in STATE_FIELDS} == {name: "float64" for name in STATE_FIELDS}
    monkeypatch.setattr(learner_io, "stamped", lambda msg: msg)   # no ROS clock in a unit test
    state = State(**{name: value + 0.125 for name, value in _good_state().items()})
    routing = SimpleNamespace(state=state, decision=SimpleNamespace(action=1, propensity=0.9, q_local=0.1, q_cloud=0.2,
                                                                     model_version="f" * 64),
                              request_id=7, probe=False, mode="deployed", action=1, breaker="closed", deadline_s=0.5)
    msg = learner_io.decision_msg(routing, "dqn", 3)
    assert {name: getattr(msg, name) for name in STATE_FIELDS} == state.as_dict()
    assert (msg.request_id, msg.action, msg.policy, msg.model_version) == (7, 1, "dqn", "f" * 64)


def test_normalisation_log_scales_the_fields_the_schema_hints_and_records_the_fields():
    rng = np.random.default_rng(1)
    states = np.stack([_spread(f, rng, 200) for f in FIELDS], axis=1)
    norm = StateNormalisation.fit(states)
    logged = [i for i, f in enumerate(FIELDS) if f.log_floor is not None]
    expected = states.copy()
    for i in logged:
        expected[:, i] = np.log(states[:, i] + FIELDS[i].log_floor)
    assert [FIELDS[i].name for i in logged] == ["input_size", "local_plan_rate"]
    assert np.allclose(norm.mean, expected.mean(axis=0)) and np.allclose(norm.scale, expected.std(axis=0))
    plain = StateNormalisation.fit(states, log_input_size=False)
    assert np.allclose(plain.mean, states.mean(axis=0))
    assert norm.to_dict()["fields"] == list(STATE_FIELDS)
    assert StateNormalisation.from_dict(norm.to_dict()) == norm
    # A checkpoint from before the field list was saved holds the paper's three fields: refused, naming them.
    saved = {k: v for k, v in norm.to_dict().items() if k != "fields"}
    with pytest.raises(ValueError, match=re.escape(f"normalisation is of the state ({', '.join(PAPER_FIELDS)}), this "
                                                   f"code's state is ({', '.join(STATE_FIELDS)})")):
        StateNormalisation.from_dict(saved)
    for fields in (list(reversed(STATE_FIELDS)), [*STATE_FIELDS, "battery"], "input_size", [1, 2, 3]):
        with pytest.raises(ValueError, match="normalisation"):
            StateNormalisation.from_dict({**norm.to_dict(), "fields": fields})


def test_normalisation_refuses_states_of_another_width_rather_than_reshaping_them():
    norm = StateNormalisation.fit(np.ones((4, STATE_SIZE)))
    for width in (STATE_SIZE - 1, STATE_SIZE + 1):
        rows = np.ones((STATE_SIZE * (STATE_SIZE + 1), width))     # as many numbers as whole states
        with pytest.raises(ValueError, match=f"a raw state has {STATE_SIZE} fields"):
            StateNormalisation.fit(rows)
        with pytest.raises(ValueError, match=f"a raw state has {STATE_SIZE} fields"):
            norm.apply(rows)
    assert norm.apply(np.ones(STATE_SIZE)).shape == (STATE_SIZE,) and norm.apply(np.ones((0, STATE_SIZE))).shape == \
        (0, STATE_SIZE)


def test_the_fast_decision_takes_a_state_in_schema_order():
    from offload_learner_py.core.dqn import DQNAgent

    rng = np.random.default_rng(2)
    states = np.stack([_spread(f, rng, 20) for f in FIELDS], axis=1)
    agent = DQNAgent(normalisation=StateNormalisation.fit(states))
    fast = agent.fast_decision()
    for row in states:
        _, q_local, q_cloud = fast.decide(*State(*row).as_tuple())
        assert np.allclose((q_local, q_cloud), agent.q_values(row), atol=1e-5)
    with pytest.raises(TypeError, match=f"a state has {STATE_SIZE} fields, got 1"):
        fast.decide(0.5)    # numpy would broadcast one number over every input


def test_the_summary_and_the_offline_features_follow_the_schema():
    from offload_learner_py.core.lstm_baseline import FEATURE_COLUMNS
    from offload_learner_py.offline import off_policy, summary

    assert summary.FEATURES == tuple((f.name, f.symbol) for f in FIELDS)
    assert list(summary.oracle_share_by_tercile(_table())) == [f.symbol for f in FIELDS]
    assert FEATURE_COLUMNS == STATE_FIELDS
    log = records.pair_records([decision(1, d=0.25, u=0.75, b=0.125, p=400.0)], [outcome(1)])
    assert off_policy.LoggedSteps.from_log(log).states.tolist() == [[0.25, 0.75, 0.125, 400.0]]
    k = STATE_SIZE
    assert off_policy._features(np.random.default_rng(3).uniform(0.1, 1, (10, k))).shape == \
        (10, 1 + k + k * (k + 1) // 2)


@pytest.mark.parametrize("bad, message", [
    (dict(name="as_array"), "not a usable attribute name"), (dict(name="_x"), "not a usable attribute name"),
    (dict(low=1.0, high=0.0), "not an interval"), (dict(low=1.0, high=1.0), "not an interval"),
    (dict(low=math.nan), "not an interval"),
    (dict(recorded_max=2.0, high=1.0), "recorded_max"), (dict(recorded_max=None), "recorded_max"),
    (dict(recorded_max=0.0), "recorded_max"), (dict(recorded_max=-1.0), "recorded_max"),
    (dict(log_floor=0.0), "log_floor"), (dict(log_floor=-1.0), "log_floor"),
    (dict(missing=-1.0), "missing value"), (dict(missing=10.5), "missing value"),
])
def test_a_field_that_cannot_be_validated_is_refused(bad, message):
    good = dict(name="rate", symbol="p_t", unit="1/s", meaning="test", low=0.0, high=math.inf, recorded_max=10.0)
    for missing in (None, 0.0, 5.0, 10.0):      # a value for older records within the recorded bounds
        assert StateField(**good, missing=missing).missing == missing
    assert StateField(**{**good, "high": 10.0}).recorded_high == 10.0
    with pytest.raises(AttributeError):
        StateField(**good).low = -1.0     # a field is validated once: it cannot change after
    with pytest.raises(ValueError, match=message):
        StateField(**{**good, **bad})


def test_log_scaling_clamps_below_zero_and_leaves_the_other_fields():
    raw = np.array([[-0.5, 0.25, 0.125, -3.0], [2.0, 0.5, 0.5, 500.0]])
    columns = [i for i, _ in STATE_SCHEMA.log_columns]
    scaled = STATE_SCHEMA.log_scaled(raw)
    for i, f in enumerate(FIELDS):
        expected = np.log(np.maximum(raw[:, i], 0) + f.log_floor) if i in columns else raw[:, i]
        assert np.array_equal(scaled[:, i], expected)
    assert scaled[0, 0] == math.log(1e-6) and raw[0, 0] == -0.5     # a copy
    assert scaled[0, 3] == math.log(0.1) and scaled[1, 3] == math.log(500.0 + 0.1)


def test_state_documents_its_fields_with_their_units_and_rules():
    for f in FIELDS:
        unit = f" ({f.unit})" if f.unit else ""
        assert f"    {f.name}: {f.symbol}, {f.meaning}{unit}; {f.rule}" in State.__doc__
    assert "()" not in State.__doc__


def test_a_schema_needs_distinct_fields():
    with pytest.raises(ValueError, match="distinct"):
        StateSchema([FIELDS[0], FIELDS[0]])
    with pytest.raises(ValueError, match="distinct"):
        StateSchema([])
