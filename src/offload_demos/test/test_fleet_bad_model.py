"""The bad model the fleet benchmark pushes on purpose (fleet_bad_model.py): a valid model file that always
offloads, pinned for the fleet in a fleet learner's store, which every robot is then offered until its guard
rolls it back."""
import time

import numpy as np

from offload_cloud.learner.store import ModelStore
from offload_demos.fleet_bad_model import DelayedPush, always_side_model, push_bad_model
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.model_file import agent_model_bytes, load_model, model_version
from offload_learner_py.core.state import STATE_SIZE


def a_model(seed=1) -> bytes:
    return agent_model_bytes(DQNAgent(DQNConfig.from_dict({"hidden_sizes": [8], "seed": seed})))


def test_the_bad_model_is_a_valid_file_that_always_picks_its_side():
    states = np.random.default_rng(0).uniform(0.0, 2.0, (200, STATE_SIZE))
    for side in (CLOUD, LOCAL):
        fast, _ = load_model(always_side_model(a_model(), side))
        assert {fast.decide(*row)[0] for row in states} == {side}


def test_pushed_the_fleet_is_offered_it_until_a_robot_rolls_it_back(tmp_path):
    store = ModelStore(str(tmp_path / "store"))
    good = a_model()
    assert store.record_round({"version": model_version(good), "parent": "", "rows": {}, "gate": {}}, good)
    bad = push_bad_model(str(tmp_path / "store"))
    assert bad != model_version(good) and load_model(store.get(bad), bad)
    assert store.version_for("robot-a", model_version(good), []) == bad
    assert store.version_for("robot-b", "", []) == bad
    # robot-a's guard rolled it back: it goes back to the good one, robot-b is still offered the bad one
    assert store.version_for("robot-a", model_version(good), [bad]) == model_version(good)
    assert store.version_for("robot-a", model_version(good), []) == model_version(good)
    assert store.version_for("robot-b", "", []) == bad


def test_a_push_waits_for_its_moment_and_says_why_it_failed(tmp_path):
    push = DelayedPush(str(tmp_path / "empty"), time.monotonic() + 0.2)
    assert push.version == "" and push.error == ""
    push.join(5.0)
    assert push.version == "" and "no current version" in push.error


def test_a_push_reaches_its_robot_through_the_robots_own_pin(tmp_path):
    store = ModelStore(str(tmp_path / "store"))
    good, older = a_model(1), a_model(2)
    assert store.record_round({"version": model_version(older), "parent": "", "rows": {}, "gate": {}}, older)
    assert store.record_round({"version": model_version(good), "parent": model_version(older), "rows": {},
                               "gate": {}}, good)
    # robot-a's guard rolled the good version back to the older one it ran: the learner pins robot-a to that
    assert store.version_for("robot-a", model_version(older), [model_version(good)]) == model_version(older)
    fleet_only = push_bad_model(str(tmp_path / "store"))
    assert store.version_for("robot-a", model_version(older), []) == model_version(older)   # its pin wins
    bad = push_bad_model(str(tmp_path / "store"), base=good, robot="robot-a")
    assert bad == fleet_only
    assert store.version_for("robot-a", model_version(older), []) == bad
