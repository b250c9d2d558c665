"""Goal sampling: the planner's free-cell rule, the start's component, seeded draws."""
import math

import numpy as np
import pytest

from offload_planner_cpp import free_cells
from offload_demos.goals import GoalSampler, default_start_cell


def test_free_cells_follow_the_planner_rules():
    grid = np.array([[0, 49, 50, 100, -1]], dtype=np.int8)
    assert free_cells(grid, 50, unknown_is_obstacle=True).tolist() == [[True, True, False, False, False]]
    assert free_cells(grid, 50, unknown_is_obstacle=False).tolist() == [[True, True, False, False, True]]
    with pytest.raises(ValueError, match="lethal_threshold"):
        free_cells(grid, 0)


def test_goals_are_only_drawn_from_the_start_component_and_are_seeded():
    grid = np.zeros((20, 30), dtype=np.int8)
    grid[:, 10] = 100                      # a wall: x > 10 is unreachable from x < 10
    free = free_cells(grid)
    sampler = GoalSampler(free, (2, 5), seed=4)
    goals = [sampler.draw() for _ in range(300)]
    assert all(x < 10 for x, _ in goals)
    assert sampler.reachable_cells == 10 * 20
    assert goals == [GoalSampler(free, (2, 5), seed=4).draw() for _ in range(1)] + goals[1:]
    far = GoalSampler(free, (0, 0), seed=1, min_distance_cells=15)
    assert all(math.hypot(x, y) >= 15 for x, y in (far.draw() for _ in range(100)))


def test_goal_sampler_rejects_a_blocked_or_off_map_start():
    free = free_cells(np.array([[0, 100], [0, 0]], dtype=np.int8))
    with pytest.raises(ValueError, match="not free"):
        GoalSampler(free, (1, 0))
    with pytest.raises(ValueError, match="off the"):
        GoalSampler(free, (5, 0))
    assert default_start_cell(free) == (1, 1)
