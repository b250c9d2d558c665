import math

import numpy as np
import pytest

from offload_learner_py.core.state import State, input_size, input_size_from_cells, node_count, raw_input_size


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
    assert np.allclose(State(0.5, 0.6, 0.03, 2e7).as_array(), [0.5, 0.6, 0.03, 2e7])
    for bad in [(-1, 0.5, 0.03, 2e7), (0.5, 1.5, 0.03, 2e7), (0.5, 0.5, -0.1, 2e7), (float("nan"), 0.5, 0.03, 2e7),
                (0.5, 0.5, 0.03, -1.0), (0.5, 0.5, 0.03, math.inf)]:
        with pytest.raises(ValueError):
            State(*bad)
    with pytest.raises(TypeError, match="local_plan_rate"):   # every field measured: no default for p_t
        State(0.5, 0.6, 0.03)


def test_the_state_has_the_papers_three_features_and_the_robots_plan_rate():
    from offload_learner_py.core.state import STATE_FIELDS, STATE_SIZE
    assert STATE_SIZE == 4 and STATE_FIELDS == ("input_size", "cpu_availability", "round_trip_s", "local_plan_rate")
    assert State(0.5, 0.6, 0.03, 2e7).as_array().shape == (STATE_SIZE,)


def test_input_size_between_one_and_two_nodes_is_n_ln_n():
    # n = x^2 / 2 / r^2 = 1.5 for x = r sqrt(3): above one node the formula applies, d = 1.5 ln 1.5.
    assert raw_input_size(0.05 * math.sqrt(3.0), 0.05) == pytest.approx(1.5 * math.log(1.5))
    assert raw_input_size(0.05 * math.sqrt(2.0), 0.05) == pytest.approx(0.0, abs=1e-12)  # n = 1: ln 1 = 0


def test_input_size_uses_the_offset_between_start_and_goal_on_both_axes():
    # A 3-4-5 triangle away from the origin: x = 5 m, n = 12.5 / 0.05^2 = 5000, d = n ln n / cells.
    cells = 1000
    expected = 5000.0 * math.log(5000.0) / cells
    assert input_size((10.0, 20.0), (13.0, 24.0), 0.05, cells) == pytest.approx(expected, rel=1e-12)
    assert input_size((13.0, 24.0), (10.0, 20.0), 0.05, cells) == pytest.approx(expected, rel=1e-12)
    # The same in cells: (70, 30) to (130, 110) is 60 x 80 cells = 100 cells = 5 m at 0.05 m.
    assert input_size_from_cells((70, 30), (130, 110), 0.05, cells) == pytest.approx(expected, rel=1e-12)
    assert input_size_from_cells((130, 30), (70, 110), 0.05, cells) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("cells", [0, -5])
def test_map_cell_count_must_be_positive(cells):
    with pytest.raises(ValueError, match="map_cell_count must be positive"):
        input_size((0, 0), (1, 1), 0.05, cells)


def test_one_cell_map_is_valid():
    assert input_size((0, 0), (1.0, 0), 0.05, 1) == pytest.approx(raw_input_size(1.0, 0.05))


def test_negative_resolution_is_rejected():
    with pytest.raises(ValueError, match="resolution_m must be positive"):
        node_count(1.0, -0.05)


def test_state_bounds_are_inclusive_and_the_state_is_immutable():
    for edge in [(0.0, 0.5, 0.03, 2e7), (0.5, 0.0, 0.03, 2e7), (0.5, 1.0, 0.03, 2e7), (0.5, 0.5, 0.0, 2e7),
                 (0.5, 0.5, 0.03, 0.0)]:
        State(*edge)  # d = 0 (goal beside the start), an idle or saturated CPU, a zero round trip, no plan timed yet
    for bad in [(0.5, -0.5, 0.03, 2e7), (0.5, -1e-9, 0.03, 2e7), (0.5, 1.0 + 1e-9, 0.03, 2e7)]:
        with pytest.raises(ValueError, match="cpu_availability must be in"):
            State(*bad)
    state = State(0.5, 0.6, 0.03, 2e7)
    with pytest.raises(AttributeError):
        state.cpu_availability = 2.0  # would bypass the validation
