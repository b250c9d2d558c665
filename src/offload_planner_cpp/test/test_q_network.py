"""The compiled decision's binding (QNetworkForward, q_network.h): the Q-values of a numpy forward pass of the same
network, its input scaling, and clear errors for a state or a network that does not fit."""
import math

import numpy as np
import pytest

from offload_planner_cpp._core import QNetworkForward


def network(rng, sizes=(4, 16, 16, 2)):
    weights = [rng.standard_normal((a, b)).astype(np.float32) for a, b in zip(sizes, sizes[1:])]
    biases = [rng.standard_normal(b).astype(np.float32) for b in sizes[1:]]
    return weights, biases


def numpy_q(weights, biases, x):
    h = np.asarray(x, dtype=np.float64)
    for i, (w, b) in enumerate(zip(weights, biases)):
        h = h @ w.astype(np.float64) + b
        if i < len(weights) - 1:
            h = np.maximum(h, 0.0)
    return h


def test_q_values_are_the_forward_pass_of_the_scaled_state():
    rng = np.random.default_rng(3)
    weights, biases = network(rng)
    mean, inverse, floor = [0.5, 1.0, -2.0, 0.0], [2.0, 0.5, 1.0, 4.0], [0.0, 0.0, 1e-3, 0.0]
    forward = QNetworkForward(weights, biases, mean, inverse, floor)
    assert (forward.inputs, forward.outputs) == (4, 2)
    for state in rng.uniform(0.0, 3.0, (50, 4)):
        x = [(math.log(max(v, 0.0) + f) if f > 0 else v) for v, f in zip(state, floor)]
        x = [(v - m) * s for v, m, s in zip(x, mean, inverse)]
        expected = numpy_q(weights, biases, x)
        got = forward.q_values(*state)
        assert isinstance(got, tuple) and len(got) == 2
        np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)


def test_a_state_of_the_wrong_width_or_not_numbers_is_a_type_error():
    weights, biases = network(np.random.default_rng(4))
    forward = QNetworkForward(weights, biases, [0.0] * 4, [1.0] * 4, [0.0] * 4)
    with pytest.raises(TypeError, match="a state has 4 fields, got 3"):
        forward.q_values(1.0, 2.0, 3.0)
    with pytest.raises(TypeError, match="state field 2 is not a number"):
        forward.q_values(1.0, 2.0, "x", 4.0)


def test_a_network_that_does_not_fit_together_is_a_value_error():
    weights, biases = network(np.random.default_rng(5))
    with pytest.raises(ValueError, match="layer 1 takes 17 inputs, the layer before gives 16"):
        QNetworkForward([weights[0], np.zeros((17, 16), np.float32), weights[2]], biases, [0.0] * 4, [1.0] * 4,
                        [0.0] * 4)
    with pytest.raises(ValueError, match="one bias per weight matrix"):
        QNetworkForward(weights, biases[:2], [0.0] * 4, [1.0] * 4, [0.0] * 4)
    with pytest.raises(ValueError, match="one mean, inverse scale and log floor per input"):
        QNetworkForward(weights, biases, [0.0] * 3, [1.0] * 4, [0.0] * 4)
    with pytest.raises(ValueError, match="log floor finite and >= 0"):
        QNetworkForward(weights, biases, [0.0] * 4, [1.0] * 4, [0.0, -1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="do not match its shape"):
        QNetworkForward(weights, [np.zeros(15, np.float32)] + biases[1:], [0.0] * 4, [1.0] * 4, [0.0] * 4)
