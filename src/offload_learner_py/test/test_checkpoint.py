import io
import json
import os

import numpy as np
import pytest
import torch

from offload_learner_py.core.checkpoint import IncompatibleCheckpointError, load_checkpoint, remove_orphaned_temps, \
    save_checkpoint
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.state import STATE_SIZE
from statetools import raw_states


def _trained_agent(config=DQNConfig(seed=4, learning_starts=10, batch_size=8)):
    agent = DQNAgent(config)
    rng = np.random.default_rng(0)
    states = raw_states(rng.uniform(1e-4, 0.3, 40), rng.uniform(0.5, 0.7, 40), np.full(40, 0.03))
    for t in range(39):
        agent.observe(states[t], t % 2, 0.3 if t % 2 else 0.0, states[t + 1])
    return agent, states


def test_round_trip_keeps_weights_config_and_normalisation(tmp_path):
    agent, states = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    loaded = load_checkpoint(path, expected_config=DQNConfig())
    assert loaded.config == agent.config
    assert loaded.normalisation == agent.normalisation
    assert loaded.steps == agent.steps
    assert np.array_equal(loaded.q_values(states), agent.q_values(states))


def test_save_is_atomic_and_replaces_the_old_file(tmp_path):
    agent, states = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    with open(path, "w") as old:
        old.write("old model")
    save_checkpoint(agent, path)
    assert os.listdir(tmp_path) == ["dqn.pt"]  # no temp file left behind
    assert np.array_equal(load_checkpoint(path).q_values(states), agent.q_values(states))


def test_failed_save_leaves_the_previous_checkpoint_intact(tmp_path, monkeypatch):
    agent, states = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    before = open(path, "rb").read()

    def broken_save(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError):
        save_checkpoint(agent, path)
    assert open(path, "rb").read() == before
    assert os.listdir(tmp_path) == ["dqn.pt"]


def test_other_architecture_is_refused_clearly(tmp_path):
    agent, _ = _trained_agent(DQNConfig(hidden_sizes=(32, 32), learning_starts=10, batch_size=8))
    path = str(tmp_path / "small.pt")
    save_checkpoint(agent, path)
    with pytest.raises(IncompatibleCheckpointError, match=r"hidden layers \[32, 32\].*expected \[256, 256, 256\]"):
        load_checkpoint(path, expected_config=DQNConfig())


def test_weights_that_do_not_fit_their_config_are_refused(tmp_path):
    agent, _ = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    payload = torch.load(path, weights_only=True)
    payload["config"]["hidden_sizes"] = [128, 128, 128]
    torch.save(payload, path)
    with pytest.raises(IncompatibleCheckpointError, match="do not fit"):
        load_checkpoint(path)


@pytest.mark.parametrize("change,message", [({"version": 99}, "version 99"), ({"format": "other"}, "not an offload"),
                                            ({"config": {"gama": 1}}, "invalid config")])
def test_other_format_or_version_is_refused(tmp_path, change, message):
    agent, _ = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    payload = torch.load(path, weights_only=True)
    payload.update(change)
    torch.save(payload, path)
    with pytest.raises(IncompatibleCheckpointError, match=message):
        load_checkpoint(path)


def test_a_file_that_is_not_a_checkpoint_is_refused(tmp_path):
    path = tmp_path / "junk.pt"
    path.write_bytes(b"not a checkpoint at all")
    with pytest.raises(IncompatibleCheckpointError, match="not a readable"):
        load_checkpoint(str(path))


@pytest.mark.parametrize("key", ["steps", "gradient_steps"])
def test_missing_or_invalid_step_counters_are_refused(tmp_path, key):
    agent, _ = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    payload = torch.load(path, weights_only=True)
    for change in ({}, {key: "many"}, {key: -1}):
        damaged = {k: v for k, v in payload.items() if k != key}
        damaged.update(change)
        torch.save(damaged, path)
        with pytest.raises(IncompatibleCheckpointError, match=f"dqn.pt has no valid step counters.*{key}"):
            load_checkpoint(path)


def test_truncated_or_corrupt_checkpoints_are_refused(tmp_path):
    agent, _ = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    data = open(path, "rb").read()
    middle = len(data) // 2
    damaged = {"truncated.pt": data[:middle], "end_cut.pt": data[:-10],
               # bytes inside the stored weights: torch.load alone would load them silently
               "flipped.pt": data[:middle] + bytes(b ^ 0xFF for b in data[middle:middle + 64]) + data[middle + 64:],
               "empty.pt": b""}
    for name, content in damaged.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(IncompatibleCheckpointError, match=f"{name} is not a readable offload DQN checkpoint"):
            load_checkpoint(str(tmp_path / name))
    with pytest.raises(IncompatibleCheckpointError, match="absent.pt is not a readable"):
        load_checkpoint(str(tmp_path / "absent.pt"))


def test_config_and_normalisation_values_are_type_checked():
    from offload_learner_py.core.normalisation import StateNormalisation
    for bad, message in [({"batch_size": "64"}, "batch_size must be an integer"),
                         ({"learning_rate": float("nan")}, "learning_rate must be a finite number"),
                         ({"hidden_sizes": 5}, "hidden_sizes must be a list"), ({"seed": -1}, "seed must be >= 0")]:
        with pytest.raises(ValueError, match=message):
            DQNConfig.from_dict({**DQNConfig().to_dict(), **bad})
    with pytest.raises(ValueError, match="positive finite scales"):
        StateNormalisation.from_dict({**StateNormalisation.identity().to_dict(), "scale": [1, 0] + [1] * (STATE_SIZE - 2)})


def test_non_finite_weights_are_refused_at_save_and_at_load(tmp_path):
    agent, _ = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    good = open(path, "rb").read()
    with torch.no_grad():
        agent.q_network.layers[0].weight[0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        save_checkpoint(agent, path)
    assert open(path, "rb").read() == good and os.listdir(tmp_path) == ["dqn.pt"]
    payload = torch.load(path, weights_only=False)
    payload["target_network"]["layers.0.bias"][0] = float("inf")
    torch.save(payload, path)
    with pytest.raises(IncompatibleCheckpointError, match="non-finite"):
        load_checkpoint(path)


def test_orphaned_temp_files_of_killed_saves_are_removed(tmp_path):
    agent, _ = _trained_agent()
    path = str(tmp_path / "dqn.pt")
    save_checkpoint(agent, path)
    for name in (".checkpoint-abc.tmp", ".checkpoint-def.tmp"):
        (tmp_path / name).write_bytes(b"half a checkpoint")
    (tmp_path / "notes.tmp").write_text("not ours")
    assert sorted(remove_orphaned_temps(path)) == [".checkpoint-abc.tmp", ".checkpoint-def.tmp"]
    assert sorted(os.listdir(tmp_path)) == ["dqn.pt", "notes.tmp"]
    load_checkpoint(path)


def test_a_checkpoint_of_the_papers_three_field_state_is_refused_with_what_to_do(tmp_path):
    """A checkpoint saved before p_t joined the state (its normalisation of three fields, its network of three
    inputs): refused naming both states and how to get a usable one; the node prints this as its FATAL line."""
    agent, _ = _trained_agent()
    path = str(tmp_path / "paper.pt")
    save_checkpoint(agent, path)
    payload = torch.load(path, weights_only=True)
    normalisation = payload["normalisation"]
    payload["normalisation"] = {**normalisation, "mean": normalisation["mean"][:3], "scale": normalisation["scale"][:3]}
    del payload["normalisation"]["fields"]      # checkpoints of the paper's state were saved without the list
    for network in ("q_network", "target_network"):
        payload[network]["layers.0.weight"] = payload[network]["layers.0.weight"][:, :3].clone()
    torch.save(payload, path)
    with pytest.raises(IncompatibleCheckpointError, match=r"paper.pt was trained on another state: normalisation is "
                       r"of the state \(input_size, cpu_availability, round_trip_s\), this code's state is "
                       r"\(input_size, cpu_availability, round_trip_s, local_plan_rate\); retrain from its bags"):
        load_checkpoint(path)


def test_a_checkpoint_or_model_file_of_p_t_in_cells_per_second_is_refused(tmp_path):
    """Saved while p_t counted cells settled per second (before its unit was saved with the normalisation): the
    same four fields, another meaning of the fourth. Refused naming the units, never fed d_t per second."""
    from offload_learner_py.core.model_file import ModelFileError, agent_model_bytes, load_model

    agent, _ = _trained_agent()
    path = str(tmp_path / "cells.pt")
    save_checkpoint(agent, path)
    load_checkpoint(path)                                   # saved with its units: loads
    payload = torch.load(path, weights_only=True)
    del payload["normalisation"]["units"]
    torch.save(payload, path)
    with pytest.raises(IncompatibleCheckpointError, match=r"cells.pt was trained on another state: .*"
                       r"local_plan_rate \[cells/s\]\), this code's state is .*local_plan_rate \[d_t/s\]\)"):
        load_checkpoint(path)

    data = agent_model_bytes(agent)
    load_model(data)
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    saved = json.loads(str(arrays["normalisation"]))
    del saved["units"]
    arrays["normalisation"] = np.array(json.dumps(saved))
    old = io.BytesIO()
    np.savez(old, **arrays)
    with pytest.raises(ModelFileError, match=r"a model of another state: .*local_plan_rate \[cells/s\]"):
        load_model(old.getvalue())
