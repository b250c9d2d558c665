"""A fleet training round's choices that the service tests pass through without looking (found by `make mutate`
over learner/training.py, #31: 46 of 79 mutants survived test_fleet_learner.py): a round warm-starts from the
version in use, a robot with too few rows or no transition rows is left out without ending the round for the
robots after it, a round needs two transition rows, and a candidate equal to the version in use is not
published again."""
import dataclasses

import numpy as np

import fleet_helpers as h
from offload_cloud.learner.training import training_round
from offload_learner_py.core.model_file import load_model
from offload_learner_py.core.reward import CostWeights, reward
from offload_learner_py.core.state import STATE_FIELDS, State
from test_fleet_learner import DEFS, MD5, SMALL, learner  # noqa: F401 (the fixture)


def weights(store, version):
    fast, _ = load_model(store.get(version))
    return np.concatenate([w.ravel() for w in fast.weights])


def test_a_round_starts_from_the_version_in_use(learner, monkeypatch):  # noqa: F811
    service, _ = learner()
    service.pool.add("robot1", DEFS, MD5, h.rows(300, seed=4))
    first = service.train_once()
    assert first["published"]
    # The second candidate must be stored to be compared; whether the gate can judge a network one step from
    # the version in use (it disagrees on a request or two: "n/a") is not this test's question.
    from offload_cloud.learner import training
    monkeypatch.setattr(training, "published_by", lambda figures: True)
    service.pool.add("robot1", DEFS, MD5, h.rows(50, seed=5, start_id=1000))
    # one minibatch step: a warm-started network stays next to the one in use, a fresh one is elsewhere
    second = training_round(service.pool, service.store, dataclasses.replace(SMALL, epochs=0.001))
    assert second["parent"] == first["version"] and second["gradient_steps"] == 1
    before, after = weights(service.store, first["version"]), service.store.get(second["version"])
    fast, _ = load_model(after)
    moved = np.abs(np.concatenate([w.ravel() for w in fast.weights]) - before).max()
    assert moved < 0.05 * np.abs(before).max(), f"the candidate moved {moved} from the version in use"


def test_robots_without_enough_rows_are_left_out_and_the_rest_still_count(learner):  # noqa: F811
    service, _ = learner()
    config = dataclasses.replace(SMALL, min_robot_rows=40)
    service.pool.add("a-few", DEFS, MD5, h.rows(39, seed=1))                       # one row short: out
    service.pool.add("b-no-transitions", DEFS, MD5, h.rows(100, seed=2, probe=False))  # no row with both sides
    service.pool.add("c-exactly", DEFS, MD5, h.rows(40, seed=3, start_id=500))     # exactly enough: in
    service.pool.add("d-many", DEFS, MD5, h.rows(200, seed=4, start_id=900))
    entry = training_round(service.pool, service.store, config)
    assert set(entry["rows"]) == {"c-exactly", "d-many"} and set(entry["gate"]) == {"c-exactly", "d-many"}


def test_a_round_needs_two_transition_rows(learner):  # noqa: F811
    service, _ = learner()
    config = dataclasses.replace(SMALL, min_robot_rows=2, holdout=0.5)
    service.pool.add("robot1", DEFS, MD5, h.rows(2, seed=6))      # one trains, one judges: one row is not enough
    assert training_round(service.pool, service.store, config) is None
    service.pool.add("robot1", DEFS, MD5, h.rows(2, seed=7, start_id=100))
    assert training_round(service.pool, service.store, config) is not None


def test_the_gate_entry_counts_the_requests_where_the_candidate_disagrees(learner):  # noqa: F811
    service, _ = learner()
    service.pool.add("robot1", DEFS, MD5, h.rows(300, seed=8))
    entry = service.train_once()
    figure = entry["gate"]["robot1"]
    # the judged rows are the window's last 30 %; with no version in use the candidate is compared with the
    # actions the robot took (no Q-values logged)
    judged = [decision for decision, _ in h.requests(300, seed=8)][210:]
    fast, _ = load_model(service.store.get(entry["version"]))
    candidate = [fast.decide(*State(**{name: d[name] for name in STATE_FIELDS}).as_tuple())[0] for d in judged]
    expected = sum(int(action != d["action"]) for action, d in zip(candidate, judged))
    assert figure["rows"] == 90 and figure["disagree"] == expected and 0 < expected < 90


def test_without_a_version_in_use_a_candidate_is_judged_against_the_greedy_choice_logged_else_the_routed_side():
    from offload_cloud.learner.training import logged_actions
    from offload_learner_py.data.records import RequestLog

    nan = float("nan")
    log = RequestLog({"request_id": np.arange(4),
                      "q_local": np.array([0.9, 0.1, nan, 0.5]), "q_cloud": np.array([0.1, 0.9, 0.3, nan]),
                      "action": np.array([1, 0, 1, 1]), "routed": np.array([1, 0, 0, 0])})
    # Q known: the greedy side (the larger Q); Q unknown: the side it was routed to, not the policy's action
    assert list(logged_actions(log, np.arange(4))) == [0, 1, 0, 0]
    del log.columns["routed"]
    assert list(logged_actions(log, np.arange(4))) == [0, 1, 1, 1]   # an older bag: the action it took
    assert list(logged_actions(log, np.array([2, 0]))) == [1, 0]


def paper_state_model() -> bytes:
    """A model file of the state before p_t (input_size, cpu_availability, round_trip_s): 3 inputs."""
    import io
    import json

    from offload_learner_py.core.model_file import model_bytes
    from offload_learner_py.core.normalisation import StateNormalisation

    old = StateNormalisation(mean=(0.0,) * 3, scale=(1.0,) * 3)
    data = model_bytes([np.ones((3, 4), np.float32), np.ones((4, 2), np.float32)],
                       [np.zeros(4, np.float32), np.zeros(2, np.float32)], old)
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays["normalisation"] = np.array(json.dumps({**old.to_dict(), "fields": ["input_size", "cpu_availability",
                                                                              "round_trip_s"]}))
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def test_a_version_in_use_of_the_state_before_p_t_is_replaced_by_a_round_from_scratch(learner, caplog):  # noqa: F811
    """The fleet's current version was trained on the paper's three fields: this code can neither warm-start from
    it nor compare with it. The round trains from scratch, judges against what the robot logged, and its
    candidate replaces the old version; it does not fail (it used to raise in every round)."""
    from offload_learner_py.core.model_file import model_version

    service, _ = learner()
    old = paper_state_model()
    assert service.store.record_round({"version": model_version(old), "parent": ""}, old)
    service.pool.add("robot1", DEFS, MD5, h.rows(300, seed=4))
    with caplog.at_level("WARNING"):
        entry = service.train_once()
    assert service.round_errors == 0 and entry is not None
    assert entry["parent"] == model_version(old) and entry["published"]
    assert service.store.state()["current"] == entry["version"]
    fast, _ = load_model(service.store.get(entry["version"]))
    assert fast.weights[0].shape[0] == len(STATE_FIELDS)
    assert any("cannot be loaded here" in r.getMessage() and "round_trip_s), this code's state is" in r.getMessage()
               for r in caplog.records)


def test_a_round_tells_training_which_cloud_sides_answered(learner, monkeypatch):  # noqa: F811
    """Round-trip variants are made only of cloud sides that answered: the round hands training the outcomes'
    own verdict (a robot with a 2 s cloud timeout logs l_cloud = 2 s when it times out, under the paper's 5 s)."""
    from offload_cloud.learner import training
    service, _ = learner()
    requests = h.requests(60, seed=8)
    for k, (_, outcome) in enumerate(requests):
        if k % 5 == 0:
            outcome.update(cloud_s=2.0, cloud_timeout=True, cloud_status=9,
                           reward=reward(outcome["action"], outcome["local_s"], 2.0, CostWeights()))
    service.pool.add("robot1", DEFS, MD5, [h.serialize(d, o, 1_700_000_000_000_000_000 + k * 1000)
                                           for k, (d, o) in enumerate(requests)])
    seen = []
    original = training.train_offline
    monkeypatch.setattr(training, "train_offline",
                        lambda *a, **kw: seen.append(kw.get("cloud_answered")) or original(*a, **kw))
    assert training_round(service.pool, service.store, SMALL) is not None
    answered = seen[0]
    assert answered is not None and len(answered) > 20
    assert list(np.flatnonzero(~answered)) == [k for k in range(len(answered)) if k % 5 == 0]
