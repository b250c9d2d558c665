import math

import numpy as np
import pytest

from offload_learner_py.state import State, input_size, input_size_from_cells, node_count, raw_input_size


def test_paper_worked_example_45_09_m_at_0_05_m():
    # Section IV.B: x ~ 45.09 m at r = 0.05 m gives n ~ 4.1e5 and d ~ 5.3e6 (natural log).
    n = node_count(45.09, 0.05)
    assert n == pytest.approx(4.1e5, rel=0.01)
    assert raw_input_size(45.09, 0.05) == pytest.approx(5.3e6, rel=0.01)
    # The example's own coordinates, start (0.001, -0.001) and goal (22.951, 39.054), are 45.30 m apart
    # (Fig. 3 prints 45.29); that distance is the one behind its exact n = 410,320.
    x = math.hypot(22.951 - 0.001, 39.054 + 0.001)
    assert x == pytest.approx(45.29, abs=0.01)
    assert node_count(x, 0.05) == pytest.approx(410320, rel=1e-3)


def test_paper_node_count_gives_its_input_size_with_the_natural_log():
    n = 410320.0  # the paper's n; it prints d = 5,303,251
    assert n * math.log(n) == pytest.approx(5303251, rel=1e-5)
    distance_m = math.sqrt(2.0 * n) * 0.05
    assert raw_input_size(distance_m, 0.05) == pytest.approx(5303251, rel=1e-5)


def test_input_size_is_normalised_by_the_map_cell_count():
    cells = 1984 * 1984
    d = input_size((0.001, -0.001), (22.951, 39.054), 0.05, cells)
    assert d == pytest.approx(raw_input_size(math.hypot(22.95, 39.055), 0.05) / cells, rel=1e-4)
    assert input_size_from_cells((0, 0), (300, 400), 0.05, cells) == pytest.approx(raw_input_size(25.0, 0.05) / cells)


def test_tiny_distances_give_zero_not_negative_input_size():
    assert raw_input_size(0.0, 0.05) == 0.0
    assert raw_input_size(0.05, 0.05) == 0.0  # n = 0.5 < 1


@pytest.mark.parametrize("bad", [dict(distance_m=-1, resolution_m=0.05), dict(distance_m=1, resolution_m=0)])
def test_invalid_geometry_is_rejected(bad):
    with pytest.raises(ValueError):
        node_count(**bad)


def test_state_validates_ranges():
    assert np.allclose(State(0.5, 0.6, 0.03).as_array(), [0.5, 0.6, 0.03])
    for bad in [(-1, 0.5, 0.03), (0.5, 1.5, 0.03), (0.5, 0.5, -0.1), (float("nan"), 0.5, 0.03)]:
        with pytest.raises(ValueError):
            State(*bad)
