"""Shared fixtures: a small fake trace (no planner needed) and the bundled real one."""
import os
import sys

import numpy as np
import pytest

from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.data.trace import PlanningTrace

BUNDLED_TRACE = os.path.join(os.path.dirname(__file__), "..", "src", "offload_learner_py", "data",
                             "husky_playpen_trace.npz")


@pytest.fixture(autouse=True, scope="session")
def _one_torch_thread():
    # Tests share two cores with other work; one thread is also the fastest for these tiny networks.
    # torch is imported by the test modules that need it (collected before this runs); tests of the
    # torch-free modules start without it, which keeps `make mutate` fast.
    torch = sys.modules.get("torch")
    if torch is not None:
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


def _size_split_table(n, seed, cut=0.01):
    """Cloud is faster exactly for large inputs, like the paper's real data (offload above d ~ 1.1)."""
    rng = np.random.default_rng(seed)
    d = 10.0 ** rng.uniform(-4, -0.5, n)
    local_s = 0.002 + d
    cloud_s = np.where(d > cut, 0.5, 2.0) * local_s
    return TransitionTable(t=np.arange(n), input_size=d, cpu_availability=rng.uniform(0.5, 0.7, n),
                           round_trip_s=np.full(n, 0.03), local_s=local_s, cloud_s=cloud_s,
                           action=np.zeros(n, np.int64), action_propensity=np.ones(n), reward=np.zeros(n))


@pytest.fixture
def size_split_table():
    """Factory of tables whose faster action is set by the input size alone."""
    return _size_split_table
