"""The rows of a real learning-mode run that the off-policy calibration test resamples (test/data/*.npz):
every request's state, the logged DQN's action and both measured latencies.

    python src/offload_learner_py/test/ope_rows.py runs/<time>/offload.bag OUT.npz
"""
import sys

import numpy as np

COLUMNS = ("input_size", "cpu_availability", "round_trip_s", "action", "local_s", "cloud_s")


def rows_from_bag(path: str) -> dict:
    """Requests with both sides measured (a learning-mode bag: every one), as float32 / int8 columns."""
    from offload_learner_py.data.bags import read_bags
    from offload_learner_py.offline.off_policy import LoggedSteps

    data = read_bags([path])
    steps = LoggedSteps.from_log(data.log)
    both = steps.probe
    return {"input_size": steps.states[both, 0].astype(np.float32),
            "cpu_availability": steps.states[both, 1].astype(np.float32),
            "round_trip_s": steps.states[both, 2].astype(np.float32),
            "action": steps.action[both].astype(np.int8),
            "local_s": steps.local_s[both].astype(np.float32), "cloud_s": steps.cloud_s[both].astype(np.float32)}


def load_rows(path: str) -> dict:
    with np.load(path) as data:
        return {name: data[name].astype(np.int64 if name == "action" else np.float64) for name in COLUMNS}


if __name__ == "__main__":
    rows = rows_from_bag(sys.argv[1])
    np.savez_compressed(sys.argv[2], **rows)
    print(f"{len(rows['action'])} requests with both sides measured -> {sys.argv[2]}")
