"""`offload-cloud-learner import`: a model the operator trained (retrain's checkpoint.pt, or a model file) reaches
the fleet's store checked as a robot checks a model, becomes the fleet's version with --publish, training goes on
from it, and a file that is not a model is refused with the store unchanged."""
import io
import json
import os

import numpy as np
import pytest

import fleet_helpers as h
from offload_cloud.learner import cli
from offload_cloud.learner.store import ModelStore, StoreError
from offload_learner_py.core.checkpoint import save_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.model_file import agent_model_bytes, model_version
from test_fleet_learner import DEFS, MD5, learner  # noqa: F401  (the fixture)


def _agent(seed):
    return DQNAgent(DQNConfig.from_dict({"hidden_sizes": [8], "seed": seed}))


def _files(store: str):
    return sorted(os.listdir(os.path.join(store, "models"))) if os.path.isdir(os.path.join(store, "models")) else []


def test_a_retrained_checkpoint_becomes_the_fleets_version_and_rollback_returns_to_the_one_it_replaced(tmp_path, capsys):
    store_dir = str(tmp_path / "store")
    store = ModelStore(store_dir)
    before = agent_model_bytes(_agent(1))
    store.record_round({"version": model_version(before), "parent": "", "rows": {}, "gate": {}}, before)
    agent = _agent(2)
    save_checkpoint(agent, str(tmp_path / "checkpoint.pt"))
    assert cli.main(["import", str(tmp_path / "checkpoint.pt"), "--store", store_dir]) == 0
    imported = model_version(agent_model_bytes(agent))
    assert store.state()["current"] == model_version(before) and store.has(imported)   # stored, not yet run
    assert cli.main(["import", str(tmp_path / "checkpoint.pt"), "--publish", "--store", store_dir]) == 0
    state = store.state()
    assert state["current"] == imported and not state["fleet_pinned"]
    assert store.version_for("robot", "", []) == imported
    assert cli.main(["list", "--store", store_dir]) == 0
    assert f"{imported[:16]} parent {model_version(before)[:16]} published imported from" in capsys.readouterr().out
    assert cli.main(["import", str(tmp_path / "checkpoint.pt"), "--publish", "--store", store_dir]) == 0   # again
    store.rollback()
    assert store.state()["current"] == model_version(before)


def test_a_model_file_is_imported_byte_for_byte(tmp_path):
    data = agent_model_bytes(_agent(3))
    (tmp_path / "model.npz").write_bytes(data)
    assert cli.main(["import", str(tmp_path / "model.npz"), "--publish", "--store", str(tmp_path / "store")]) == 0
    assert ModelStore(str(tmp_path / "store")).get(model_version(data)) == data


def _pickled_npz() -> bytes:
    out = io.BytesIO()
    np.savez(out, format=np.array("offload-model-1"), weight_0=np.array([object()], dtype=object))
    return out.getvalue()


@pytest.mark.parametrize("content", [b"", b"garbage" * 100, _pickled_npz(), b"PK\x03\x04" + os.urandom(512)])
def test_a_file_that_is_no_model_is_refused_and_the_store_is_unchanged(tmp_path, capsys, content):
    store_dir = str(tmp_path / "store")
    (tmp_path / "hostile").write_bytes(content)
    assert cli.main(["import", str(tmp_path / "hostile"), "--publish", "--store", store_dir]) == 1
    assert "is neither a model file" in capsys.readouterr().err
    assert _files(store_dir) == [] and ModelStore(store_dir).state()["current"] == ""
    assert cli.main(["import", str(tmp_path / "missing.pt"), "--store", store_dir]) == 1
    with pytest.raises(StoreError, match="not a model file|at most"):   # the store's own check, for any caller
        ModelStore(store_dir).import_model(content, "hostile", publish=True)
    assert _files(store_dir) == [] and ModelStore(store_dir).history() == []


def test_a_pinned_fleet_is_not_moved_by_an_import(tmp_path):
    store = ModelStore(str(tmp_path / "store"))
    pinned = agent_model_bytes(_agent(4))
    store.record_round({"version": model_version(pinned), "parent": "", "rows": {}, "gate": {}}, pinned)
    store.pin(model_version(pinned))
    with pytest.raises(StoreError, match="pinned"):
        store.import_model(agent_model_bytes(_agent(5)), "retrained.npz", publish=True)
    assert store.state()["current"] == model_version(pinned) and store.state()["fleet_pinned"]
    assert not [e for e in store.history() if e.get("event") == "imported"]


def test_training_goes_on_from_the_imported_version(learner, tmp_path):  # noqa: F811
    service, client = learner()
    agent = _agent(6)
    save_checkpoint(agent, str(tmp_path / "checkpoint.pt"))
    assert cli.main(["import", str(tmp_path / "checkpoint.pt"), "--publish", "--store", str(tmp_path / "store")]) == 0
    imported = model_version(agent_model_bytes(agent))
    assert client.current_version("")[0] == imported      # the running service serves it to the robots
    client.send_rows(DEFS, MD5, h.rows(300, seed=6))
    entry = service.train_once()
    assert entry["parent"] == imported                     # warm-started from it, judged against it
    history = ModelStore(str(tmp_path / "store")).history()
    assert [e["event"] for e in history] == ["imported", "trained"]
    assert json.loads(json.dumps(history[0]))["source"].endswith("checkpoint.pt")
