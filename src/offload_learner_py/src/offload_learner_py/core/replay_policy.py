"""A recorded or computed decision list replayed live, one action a request (the router's `replay` policy;
bench-policies' oracle). Apart from policies.py: a baseline for benchmarks and what-if runs, not a learner."""
import threading
from typing import Optional

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.policies import Decision, Policy


class ReplayPolicy(Policy):
    """Decide request k (in the order the router asks) with the k-th action of a given sequence: a recorded or
    computed decision list replayed live, e.g. a run's decisions under other conditions, or bench-policies' oracle
    (each request's faster side in a probe run, offload_demos). Requests past the list's end plan locally and are
    counted (`beyond`): the list was shorter than the run."""
    name = "replay"

    def __init__(self, actions, name: Optional[str] = None):
        actions = [int(action) for action in actions]
        if not actions or any(action not in (LOCAL, CLOUD) for action in actions):
            raise ValueError(f"replay needs a non-empty list of actions {LOCAL} (local) or {CLOUD} (cloud)")
        self.actions = np.asarray(actions, dtype=np.int64)
        self.name = name or self.name
        self.next_index = 0
        self.beyond = 0
        self._lock = threading.Lock()

    MAX_FILE_BYTES = 16 << 20   # millions of requests; a larger file is a mistake or hostile, not a run

    @classmethod
    def from_file(cls, path: str, name: Optional[str] = None) -> "ReplayPolicy":
        """One action per line (0 local, 1 cloud); blank lines and '#' comments skipped."""
        with open(path, "rb") as stream:
            data = stream.read(cls.MAX_FILE_BYTES + 1)
        if len(data) > cls.MAX_FILE_BYTES:
            raise ValueError(f"replay actions file {path}: over {cls.MAX_FILE_BYTES >> 20} MiB")
        lines = [line.split("#", 1)[0].strip() for line in data.decode("utf-8", "replace").splitlines()]
        try:
            return cls([int(line) for line in lines if line], name)
        except ValueError as error:
            raise ValueError(f"replay actions file {path}: {error}") from None

    def choose(self, table):
        if len(table) > len(self.actions):
            raise ValueError(f"replay has {len(self.actions)} actions for {len(table)} rows")
        return self.actions[:len(table)].copy()

    def decide(self, state):
        with self._lock:
            index, self.next_index = self.next_index, self.next_index + 1
            if index >= len(self.actions):
                self.beyond += 1
                return Decision(LOCAL, 1.0)
        return Decision(int(self.actions[index]), 1.0)
