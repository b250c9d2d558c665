"""A fleet training round's reference, its record and its holdout (found by `make mutate` over learner/training.py,
#31: 28 of 86 run survived test_fleet_learner.py and test_fleet_training.py): the first candidate is judged against
the greedy choices the robot logged (its Q-values), not the sides it took; a robot with one judged request is judged;
the round's time is its duration; a candidate equal to the version in use neither passes nor is published."""
import dataclasses

import numpy as np

import fleet_helpers as h
from offload_cloud.learner import training
from offload_cloud.learner.training import training_round
from offload_learner_py.core.model_file import load_model
from offload_learner_py.core.state import STATE_FIELDS, State
from test_fleet_learner import DEFS, MD5, SMALL, learner  # noqa: F401 (the fixture)


def logged_q_rows(n, seed):
    """Rows whose logged Q-values prefer the side the robot did not take (a probe, a breaker, a hedge routed it)."""
    out, chosen = [], []
    for i, (decision, outcome) in enumerate(h.requests(n, seed=seed)):
        other = 1 - int(decision["action"])
        decision["q_local"], decision["q_cloud"] = (0.9, 0.1) if other == 0 else (0.1, 0.9)
        chosen.append((decision, other))
        out.append(h.serialize(decision, outcome, 1_700_000_000_000_000_000 + (1 + i) * 1000))
    return out, chosen


def test_the_first_candidate_is_judged_against_the_logged_greedy_choices(learner):  # noqa: F811
    service, _ = learner()
    # Seed 9: against the logged greedy choice and against the taken side the counts add up to 90, so they tell the
    # two references apart unless the candidate disagrees with exactly half (seed 8's did, once p_t joined the state).
    rows, chosen = logged_q_rows(300, seed=9)
    service.pool.add("robot1", DEFS, MD5, rows)
    entry = service.train_once()
    figure = entry["gate"]["robot1"]
    judged = chosen[210:]   # the window's last 30 %
    fast, _ = load_model(service.store.get(entry["version"]))
    candidate = [fast.decide(*State(**{name: d[name] for name in STATE_FIELDS}).as_tuple())[0] for d, _ in judged]
    against_logged = sum(int(a != greedy) for a, (_, greedy) in zip(candidate, judged))
    against_taken = sum(int(a != d["action"]) for a, (d, _) in zip(candidate, judged))
    assert figure["rows"] == 90 and figure["disagree"] == against_logged
    assert against_logged != against_taken          # the two references tell apart here
    assert 0.0 <= entry["train_s"] < 600.0          # a duration, in seconds


def test_a_robot_with_a_single_judged_request_is_judged(learner):  # noqa: F811
    service, _ = learner()
    config = dataclasses.replace(SMALL, min_robot_rows=2, holdout=0.5)
    service.pool.add("robot1", DEFS, MD5, h.rows(2, seed=6))
    service.pool.add("robot2", DEFS, MD5, h.rows(2, seed=7, start_id=100))
    entry = training_round(service.pool, service.store, config)
    assert entry is not None and set(entry["gate"]) == {"robot1", "robot2"}
    assert [entry["gate"][robot]["rows"] for robot in ("robot1", "robot2")] == [1, 1]


def test_a_candidate_equal_to_the_version_in_use_neither_passes_nor_is_published(learner, monkeypatch):  # noqa: F811
    service, _ = learner()
    service.pool.add("robot1", DEFS, MD5, h.rows(300, seed=4))
    first = service.train_once()
    assert first["published"]
    current = service.store.get(first["version"])
    monkeypatch.setattr(training, "agent_model_bytes", lambda agent: current)   # training changed nothing
    service.pool.add("robot1", DEFS, MD5, h.rows(50, seed=5, start_id=1000))
    again = training_round(service.pool, service.store, SMALL)
    assert again["version"] == first["version"]
    assert again["gate_passed"] is False and again["published"] is False
    assert service.store.state()["current"] == first["version"]
    assert np.isfinite(again["train_s"])
