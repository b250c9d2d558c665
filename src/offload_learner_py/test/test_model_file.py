"""The deployed model file: the same decisions as the agent it came from, one version per content, and a file
that is not a valid model refused with ModelFileError (the robot keeps the model it has)."""
import io
import json
import re
import zipfile

import numpy as np
import pytest

from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.model_file import (ModelFileError, agent_model_bytes, load_model, model_bytes,
                                                model_version)
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.state import STATE_FIELDS, STATE_SIZE
from statetools import PAPER_FIELDS, paper_state_model_file, raw_states


@pytest.fixture(scope="module")
def agent():
    rng = np.random.default_rng(3)
    agent = DQNAgent(DQNConfig(seed=3))
    states = raw_states(10 ** rng.uniform(-4, 0, 300), rng.uniform(0, 1, 300), rng.uniform(0, 0.2, 300),
                        10 ** rng.uniform(6, 8, 300))
    agent.normalisation = StateNormalisation.fit(states)
    return agent


def test_the_file_decides_as_the_agent(agent):
    data = agent_model_bytes(agent)
    fast, normalisation = load_model(data, model_version(data))
    reference = agent.fast_decision()
    rng = np.random.default_rng(4)
    for _ in range(200):
        state = raw_states(10 ** rng.uniform(-4, 0), rng.uniform(0, 1), rng.uniform(0, 0.2), 10 ** rng.uniform(6, 8))[0]
        assert fast.decide(*state)[0] == reference.decide(*state)[0]
        assert fast.decide(*state)[1] == pytest.approx(reference.decide(*state)[1], rel=1e-5, abs=1e-6)
    assert normalisation == agent.normalisation


def test_one_content_one_version(agent):
    assert agent_model_bytes(agent) == agent_model_bytes(agent)
    other = DQNAgent(DQNConfig(seed=4))
    other.normalisation = agent.normalisation
    assert model_version(agent_model_bytes(other)) != model_version(agent_model_bytes(agent))


def _rewritten(data: bytes, **replace) -> bytes:
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays.update(replace)
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()


def test_a_file_that_is_not_a_valid_model_is_refused(agent):
    data = agent_model_bytes(agent)
    with pytest.raises(ModelFileError, match="SHA-256"):
        load_model(data, model_version(data[:-1] + b"x"))
    nan = np.array(agent.fast_decision().weights[1], copy=True)
    nan[0, 0] = np.nan
    bad = {
        "not finite": _rewritten(data, weight_1=nan),
        "do not chain": _rewritten(data, weight_1=np.zeros((3, 7), np.float32)),
        "not a model file": b"PK\x03\x04 garbage" + bytes(100),
        "not a offload-model-1": _rewritten(data, format=np.array("something else")),
        "normalisation": _rewritten(data, normalisation=np.array(json.dumps({"mean": [0.0], "scale": [1.0],
                                                                               "log_input_size": True}))),
    }
    for expected, content in bad.items():
        with pytest.raises(ModelFileError, match=expected):
            load_model(content)
    pickled = io.BytesIO()
    with zipfile.ZipFile(pickled, "w") as archive:   # an object array: loading it needs pickle, refused
        member = io.BytesIO()
        np.lib.format.write_array(member, np.array([{"payload": 1}], dtype=object), allow_pickle=True)
        archive.writestr("format.npy", member.getvalue())
    with pytest.raises(ModelFileError):
        load_model(pickled.getvalue())
    with pytest.raises(ModelFileError, match="at most"):
        load_model(bytes(17 << 20))


def test_the_loaded_model_keeps_to_the_width_it_declares():
    normalisation = StateNormalisation.identity()
    weights = [np.ones((STATE_SIZE, 4), np.float32), np.ones((4, 2), np.float32)]
    biases = [np.zeros(4, np.float32), np.array([0.0, 1.0], np.float32)]
    fast, _ = load_model(model_bytes(weights, biases, normalisation))
    assert fast.decide(*raw_states(0.1, 0.5, 0.03)[0])[0] == 1   # Q(cloud) = Q(local) + 1
    with pytest.raises(ModelFileError, match="2 action values"):
        load_model(model_bytes(weights[:1], biases[:1], normalisation))


def test_a_model_of_the_papers_three_field_state_is_refused_naming_both_states(tmp_path):
    """A fleet model trained before p_t existed (3 inputs): refused rather than fed a state it never learned. A
    robot given it as ~model stops at start with this error (one FATAL line); one offered it by the fleet learner
    keeps the model it has (test_fleet_robot.py)."""
    from offload_learner_py.online.fleet import load_initial

    message = re.escape(f"normalisation is of the state ({', '.join(PAPER_FIELDS)}), this code's state is "
                        f"({', '.join(STATE_FIELDS)})")
    with pytest.raises(ModelFileError, match=message):
        load_model(paper_state_model_file())
    (tmp_path / "old.npz").write_bytes(paper_state_model_file())
    with pytest.raises(ModelFileError, match=message):
        load_initial(str(tmp_path / "old.npz"))
