"""Test helpers for the robot deployed with a fleet learner: a fake FleetClient (FakeLearner), a fleet robot wired to
it, one-layer model files, and a version run through the guard."""
import threading
import time

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.model_file import load_model, model_bytes, model_version
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.policies import Decision
from offload_learner_py.core.state import STATE_SIZE
from offload_learner_py.online.fleet import DeployedModel, make_fleet_robot
from offload_learner_py.online.fleet_link import FleetConfig
from offload_learner_py.online.model_guard import GuardConfig
from offload_learner_py.online.router_types import Outcome
from routertools import STATE


class Timeout(Exception):
    pass


class Busy(Exception):
    pass


class Refused(Exception):
    pass


ERRORS = (Timeout, Busy, Refused)


def model_file(action: int, q: float = 1.0) -> bytes:
    """A one-layer model that always prefers `action` by q."""
    bias = np.zeros(2, np.float32)
    bias[action] = q
    return model_bytes([np.zeros((STATE_SIZE, 2), np.float32)], [bias], StateNormalisation.identity())


class FakeLearner:
    """A FleetClient: rows kept per batch, versions offered from `offer`, files from `files`."""

    def __init__(self):
        self.batches, self.queries, self.fetches = [], [], []
        self.down = threading.Event()
        self.busy = False
        self.offer, self.files = "", {}
        self.closed = False

    def send_rows(self, definitions, md5, rows):
        if self.down.is_set():
            raise Timeout("learner unreachable")
        if self.busy:
            raise Busy("over rate")
        assert definitions == {"d": "def"} and md5 == {"d": "md5"}
        self.batches.append(list(rows))
        return len(rows), 0

    def current_version(self, current="", rolled_back=()):
        if self.down.is_set():
            raise Timeout("learner unreachable")
        self.queries.append((current, tuple(rolled_back)))
        return ("" if self.offer in rolled_back else self.offer), 0

    def fetch(self, version):
        self.fetches.append(version)
        return self.files[version]

    def close(self):
        self.closed = True

    @property
    def rows(self):
        return [row for batch in self.batches for row in batch]


def wait_for(condition, timeout_s=10.0):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.005)


def fleet(fake, guard=GuardConfig(requests=0), start=True, **config):
    settings = dict(endpoint="tcp://learner:5557", insecure=True, period_s=0.05, send_every_s=0.01, batch_rows=4,
                    buffer_rows=8, timeout_s=0.1)
    settings.update(config)
    return make_fleet_robot(FleetConfig(**settings), guard, client_factory=lambda: fake, errors=ERRORS,
                            definitions={"d": "def"}, md5={"d": "md5"}, start=start)


def outcome_of(latency_s, version="", probe=False, action=LOCAL):
    outcome = Outcome(1, STATE, Decision(action, 1.0, model_version=version), probe, action, latency_s)
    return outcome


def run_versions(robot, old, new, old_ms, new_ms, seed=0):
    rng = np.random.default_rng(seed)
    for _ in range(40):
        robot.on_outcome(outcome_of(rng.normal(old_ms, 3.0) / 1e3, old.version))
    robot.install(new.version, new.fast)
    for k in range(60):
        verdict = robot.on_outcome(outcome_of(rng.normal(new_ms, 3.0) / 1e3, robot.policy.decide(STATE).model_version))
        if verdict is not None:
            return k + 1, verdict
    return None, None


def two_models():
    a, b = model_file(LOCAL), model_file(CLOUD)
    return DeployedModel(model_version(a), load_model(a)[0]), DeployedModel(model_version(b), load_model(b)[0])
