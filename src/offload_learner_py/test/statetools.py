"""Raw states for tests, built by field name through the state schema: a test names the fields it sets, and a
field added to the schema gets a plausible value instead of shifting every column."""
import numpy as np

from offload_learner_py.core.state import STATE_SCHEMA

# cells/s: a measured local planning rate of this machine's planner (4e6-7e7 in the demo's bags, 2026-11)
PLAN_RATE = 2e7


def raw_states(input_size, cpu_availability, round_trip_s, local_plan_rate=PLAN_RATE) -> np.ndarray:
    """N x STATE_SIZE raw states in schema order from the fields' columns (scalars broadcast)."""
    columns = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, dtype=np.float64))
                                    for v in (input_size, cpu_availability, round_trip_s, local_plan_rate)))
    named = dict(zip(("input_size", "cpu_availability", "round_trip_s", "local_plan_rate"), columns))
    return STATE_SCHEMA.stack(named.__getitem__)
