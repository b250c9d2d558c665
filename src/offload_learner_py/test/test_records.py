"""data/records.py: decisions and outcomes paired by request id into the request log, and the transition
table from it."""
import pytest

from recordtools import decision, outcome
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.reward import reward
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.data.records import RecordMismatchError, pair_records, transition_table


def test_records_rebuild_transition_table_rows_by_request_id():
    decisions = [decision(12, CLOUD, d=2.0), decision(10, LOCAL, d=0.5), decision(11, LOCAL)]
    outcomes = [outcome(10, LOCAL, 0.1, 0.3), outcome(12, CLOUD, 0.4, 0.2), outcome(11, reward_valid=False)]
    log = pair_records(decisions, outcomes)
    table = transition_table(log)
    assert isinstance(table, TransitionTable)
    assert table.t.tolist() == [10, 12]            # the request without a reward is not a transition
    assert table.action.tolist() == [LOCAL, CLOUD]
    assert table.input_size.tolist() == [0.5, 2.0]
    assert table.local_s.tolist() == [0.1, 0.4] and table.cloud_s.tolist() == [0.3, 0.2]
    assert table.reward[1] == pytest.approx(reward(CLOUD, 0.4, 0.2))


def test_records_keep_a_decision_whose_outcome_is_missing():
    log = pair_records([decision(1), decision(2)], [outcome(1)])
    assert log["has_outcome"].tolist() == [True, False]
    assert len(transition_table(log)) == 1


@pytest.mark.parametrize("decisions, outcomes, message", [
    ([decision(1)], [outcome(2)], "no decision"),
    ([decision(1, LOCAL)], [outcome(1, CLOUD)], "action"),
    ([decision(1), decision(1)], [], "two decisions"),
    ([decision(1)], [outcome(1), outcome(1)], "two outcomes"),
])
def test_records_that_disagree_are_rejected(decisions, outcomes, message):
    with pytest.raises(RecordMismatchError, match=message):
        pair_records(decisions, outcomes)


def test_one_pairing_strict_for_live_records_and_tolerant_for_bags():
    """The same pairing code: what strict pairing refuses, tolerant pairing (the bag reader) counts and drops."""
    from offload_learner_py.data.records import DECISION_DEFAULTS, OUTCOME_DEFAULTS, Pairing, _as_dict

    def fields(record, defaults):
        return _as_dict(record, defaults)
    bad = decision(3, propensity=1e-300)                    # outside the physical bounds
    with pytest.raises(RecordMismatchError, match="action_propensity"):
        pair_records([decision(1), bad], [outcome(1), outcome(3)])
    tolerant = Pairing()
    for record in (decision(1), bad, decision(4), decision(1)):
        tolerant.decision(fields(record, DECISION_DEFAULTS))
    for record in (outcome(1), outcome(3), outcome(5)):
        tolerant.outcome(fields(record, OUTCOME_DEFAULTS))
    log = tolerant.log()
    counts = tolerant.counts
    assert log["request_id"].tolist() == [1] and log["has_outcome"].tolist() == [True]
    assert (counts.invalid, counts.duplicate_decisions, counts.dropped_no_outcome, counts.orphan_outcomes) == \
        (1, 1, 1, 1)
    assert "action_propensity" in counts.invalid_examples[0]
    assert (counts.requests, counts.rewarded_steps, counts.probe_steps) == (1, 1, 1)


@pytest.mark.parametrize("propensity", [1.0 + 1e-9, 1.5, float("inf")])
def test_a_propensity_above_one_is_refused(propensity):
    """#31: a propensity above 1 (no probability) was accepted by a mutant; the pairing refuses it."""
    with pytest.raises(RecordMismatchError, match="action_propensity"):
        pair_records([decision(1, propensity=propensity)], [outcome(1)])
    assert len(pair_records([decision(1, propensity=1.0)], [outcome(1)])) == 1
