"""The robot side (offload_learner_py.online.fleet: make_fleet_robot, FleetLink, FleetPolicy; no ROS) against the REAL
fleet learner (`offload-cloud-learner serve --insecure`, a subprocess on loopback): rows reach the learner's pool;
the learner is SIGKILLed mid-run, the robot keeps deciding with the version it holds, keeps its rows (bounded) and
sends them when the learner is back on the same store; every row is in the pool but the ones counted as dropped."""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import fleet_helpers as h
from offload_demos.loopback import free_port
from offload_learner_py.core.model_file import model_bytes, model_version
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.state import STATE_SIZE, State
from offload_learner_py.data.bags import read_bags
from offload_learner_py.online.fleet import make_fleet_robot
from offload_learner_py.online.fleet_link import FleetConfig
from offload_learner_py.online.model_guard import GuardConfig

DEFS, MD5 = h.definitions()
STATE = State(1.2, 0.6, 0.05, 2e7)


def serve(store, port):
    """The learner as deployed, plaintext on loopback, a small DQN, no training round during the test."""
    return subprocess.Popen(
        [sys.executable, "-m", "offload_cloud.learner.cli", "serve", "--bind", f"tcp://127.0.0.1:{port}",
         "--insecure", "--store", str(store), "--train-every-rows", "1000000", "--train-every-s", "86400",
         "--epochs", "1", "--set", "hidden_sizes=[16,16]", "--rows-per-s", "0", "--log-level", "WARNING"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def wait_for(condition, timeout_s=30.0, what="condition"):
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"{what() if callable(what) else what} not met in {timeout_s} s"
        time.sleep(0.05)


def pooled_ids(store):
    paths = sorted(str(p) for p in (store / "pool").rglob("*.bag*"))
    if not paths:
        return []
    return [int(i) for i in read_bags(paths, workers=1).log["request_id"]]


def link_state(link, learner) -> str:
    stderr = ""
    if learner.poll() is not None:
        stderr = learner.stderr.read().decode(errors="replace")[-1500:]
    return f"sent {link.sent}, kept {len(link.buffer)}, dropped {link.dropped}, refused {link.refused}, " \
           f"failed sends {link.send_failures}; learner exit {learner.poll()} {stderr}"


def encode(row):
    """As the node's encode: the row kept in the buffer is not its bytes (re-encoded at every send)."""
    decision, outcome = row
    return h.serialize(decision, outcome, 1_700_000_000_000_000_000 + decision["request_id"] * 1000)


@pytest.mark.timeout(240)
def test_rows_survive_a_killed_learner_and_the_robot_decides_throughout(tmp_path):
    store, port = tmp_path / "store", free_port()
    model = tmp_path / "model.npz"
    data = model_bytes([np.zeros((STATE_SIZE, 2), np.float32)], [np.array([0.0, 1.0], np.float32)],
                       StateNormalisation.identity())
    model.write_bytes(data)
    requests = h.requests(300, seed=4)
    learner = serve(store, port)
    robot = make_fleet_robot(FleetConfig(endpoint=f"tcp://127.0.0.1:{port}", insecure=True, period_s=1.0,
                                         timeout_s=1.0, buffer_rows=64, batch_rows=16, send_every_s=0.05),
                             GuardConfig(requests=0), str(model), encode=encode, definitions=DEFS, md5=MD5)
    try:
        version = model_version(data)
        for start in range(0, 100, 20):              # in steps the buffer holds while the learner starts
            for row in requests[start:start + 20]:
                robot.link.enqueue(row)
            wait_for(lambda: robot.link.sent == start + 20, what=f"{start + 20} rows sent")
        assert robot.link.dropped == 0

        learner.send_signal(signal.SIGKILL)          # mid-run: no orderly close of its open bag
        learner.wait(10)
        for row in requests[100:200]:                # the outage: 100 rows into a buffer of 64
            assert robot.policy.decide(STATE).model_version == version
            robot.link.enqueue(row)
        wait_for(lambda: robot.link.send_failures >= 1, what="a failed send during the outage")
        assert robot.link.sent == 100 and len(robot.link.buffer) == 64 and robot.link.buffer.dropped == 36

        learner = serve(store, port)                 # back, on the same store and port
        wait_for(lambda: robot.link.sent == 164 and not len(robot.link.buffer), timeout_s=60,
                 what=lambda: f"the kept rows sent when the learner returned ({link_state(robot.link, learner)})")
        for start in range(200, 300, 20):
            for row in requests[start:start + 20]:
                robot.link.enqueue(row)
            wait_for(lambda: len(robot.link.buffer) <= 44, timeout_s=60, what="room in the buffer")
        wait_for(lambda: robot.link.sent == 264 and not len(robot.link.buffer), timeout_s=60,
                 what=lambda: f"the kept rows and the new ones sent ({link_state(robot.link, learner)})")
        assert robot.policy.version == version and robot.stats()["fleet_rows_dropped"] == 36
    finally:
        robot.close()
        learner.send_signal(signal.SIGTERM)           # orderly: the open bag sealed
        learner.wait(20)
    ids = pooled_ids(store)
    expected = set(range(1, 101)) | set(range(137, 301))   # the 36 oldest of the outage dropped, and counted
    assert set(ids) == expected, f"missing {sorted(expected - set(ids))[:10]}, extra {sorted(set(ids) - expected)[:10]}"
    assert os.path.isdir(store / "pool" / "insecure")
