"""Shared fixtures: a small fake trace (no planner needed) and the bundled real one."""
import os

import numpy as np
import pytest
import torch

from offload_learner_py.trace import PlanningTrace

BUNDLED_TRACE = os.path.join(os.path.dirname(__file__), "..", "src", "offload_learner_py", "data",
                             "husky_playpen_trace.npz")


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    # Tests share two cores with other work; one thread is also the fastest for these tiny networks.
    torch.set_num_threads(1)


@pytest.fixture
def small_trace() -> PlanningTrace:
    rng = np.random.default_rng(0)
    n = 50
    input_size = 10.0 ** rng.uniform(-4, -0.5, n)
    return PlanningTrace(start_cell=np.zeros((n, 2), np.int64), goal_cell=np.ones((n, 2), np.int64),
                         distance_m=np.ones(n), input_size=input_size, local_s=1e-3 + input_size * 1e-2,
                         planner_s=np.full(n, np.nan), expansions=np.full(n, -1), metadata={"map_name": "fake"})


@pytest.fixture(scope="session")
def bundled_trace() -> PlanningTrace:
    return PlanningTrace.load_npz(BUNDLED_TRACE)
