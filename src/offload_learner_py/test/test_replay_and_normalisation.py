import numpy as np
import pytest

from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.replay import ReplayMemory
from offload_learner_py.core.state import STATE_SIZE
from statetools import raw_states


def test_replay_is_fifo_with_fixed_capacity():
    memory = ReplayMemory(3)
    for i in range(5):
        memory.add(raw_states(i, 0, 0)[0], i % 2, float(i), raw_states(i + 1, 0, 0)[0])
    assert len(memory) == 3
    assert sorted(memory.rewards.tolist()) == [2.0, 3.0, 4.0]  # 0 and 1, the oldest, were replaced


def test_replay_samples_only_filled_slots():
    memory = ReplayMemory(10)
    memory.add(raw_states(1, 2, 3)[0], 1, 0.5, raw_states(4, 5, 6)[0])
    states, actions, rewards, next_states = memory.sample(4, np.random.default_rng(0))
    assert states.shape == (4, STATE_SIZE) and np.all(rewards == 0.5) and np.all(actions == 1)
    with pytest.raises(ValueError):
        ReplayMemory(5).sample(1, np.random.default_rng(0))


def test_normalisation_centres_scales_and_logs_input_size():
    rng = np.random.default_rng(0)
    states = raw_states(10.0 ** rng.uniform(-4, 0, 500), rng.uniform(0.5, 0.7, 500), np.full(500, 0.03))
    norm = StateNormalisation.fit(states)
    features = norm.apply(states)
    assert features.dtype == np.float32
    assert np.allclose(features[:, :2].mean(0), 0, atol=1e-5) and np.allclose(features[:, :2].std(0), 1, atol=1e-3)
    assert np.allclose(features[:, 2], 0)  # a constant round trip is centred, not blown up
    # On a log scale the four decades of d spread evenly: the median lands near the centre.
    assert abs(np.median(features[:, 0])) < 0.2
    assert norm.apply(states[0]).shape == (STATE_SIZE,)
    assert StateNormalisation.from_dict(norm.to_dict()) == norm


def test_normalisation_refuses_bad_input():
    with pytest.raises(ValueError):
        StateNormalisation.fit(np.zeros((0, 3)))
    with pytest.raises(ValueError):
        StateNormalisation.from_dict({"mean": [0, 0], "scale": [1, 1], "log_input_size": True})
