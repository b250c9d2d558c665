"""Raw states for tests, built by field name through the state schema: a test names the fields it sets, and a
field added to the schema gets a plausible value instead of shifting every column."""
import numpy as np

from offload_learner_py.core.state import STATE_SCHEMA

# d_t/s: a measured local planning rate of this machine's planner (114-746 in the demo's bag, 2026-11)
PLAN_RATE = 500.0


def raw_states(input_size, cpu_availability, round_trip_s, local_plan_rate=PLAN_RATE) -> np.ndarray:
    """N x STATE_SIZE raw states in schema order from the fields' columns (scalars broadcast)."""
    columns = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, dtype=np.float64))
                                    for v in (input_size, cpu_availability, round_trip_s, local_plan_rate)))
    named = dict(zip(("input_size", "cpu_availability", "round_trip_s", "local_plan_rate"), columns))
    return STATE_SCHEMA.stack(named.__getitem__)


PAPER_FIELDS = ("input_size", "cpu_availability", "round_trip_s")


def paper_state_model_file() -> bytes:
    """A model file as the fleet learner wrote them before p_t: a network of the paper's three inputs, its
    normalisation naming those three fields."""
    import io
    import json

    from offload_learner_py.core.model_file import model_bytes
    from offload_learner_py.core.normalisation import StateNormalisation

    old = StateNormalisation(mean=(0.0,) * 3, scale=(1.0,) * 3)
    data = model_bytes([np.ones((3, 4), np.float32), np.ones((4, 2), np.float32)],
                       [np.zeros(4, np.float32), np.zeros(2, np.float32)], old)
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays["normalisation"] = np.array(json.dumps({**old.to_dict(), "fields": list(PAPER_FIELDS)}))
    out = io.BytesIO()
    np.savez(out, **arrays)
    return out.getvalue()
