"""The learner node's fleet mode without a master (nodes/learner_fleet.py): its parameters and their defaults,
rows as the exact published messages (genpy's bytes, read back by the bag decoder with the classes' definitions),
a fleet robot only for a deployed DQN, the guard's CPU counted in learner_cpu_s, and the TrainingStats fields.
Also a benchmark-style print of the learner's CPU per request in fleet mode against a robot that trains."""
import logging
import time

import pytest

offload_msgs = pytest.importorskip("offload_msgs.msg", reason="offload_msgs is not built")

from offload_learner_py.core.model_file import load_model, model_version  # noqa: E402
from offload_learner_py.nodes import learner_fleet  # noqa: E402
from offload_learner_py.nodes.learner_params import PARAMETERS, read_learner_parameters  # noqa: E402
from offload_learner_py.online.fleet_link import FleetConfig  # noqa: E402
from offload_learner_py.online.model_guard import GuardConfig  # noqa: E402
from offload_learner_py.online.router_types import Outcome  # noqa: E402
from offload_learner_py.core.policies import Decision  # noqa: E402
from routertools import STATE  # noqa: E402
from test_fleet_robot import model_file  # noqa: E402

LOG = logging.getLogger("test")


def fleet_settings(given):
    """(FleetConfig, GuardConfig) as the node reads them, with the learner's other parameters."""
    settings = read_learner_parameters(lambda name, default: given.get(name, default))
    return settings.fleet, settings.guard


def test_parameters_default_to_the_dataclasses_and_reach_them():
    assert fleet_settings({}) == (FleetConfig(), GuardConfig())
    given = {"fleet_endpoint": "tcp://cloud:5557", "fleet_keys_dir": "/keys", "fleet_period_s": 10,
             "guard_requests": 50, "guard_margin": 0.1}
    fleet, guard = fleet_settings(given)
    assert (fleet.endpoint, fleet.keys_dir, fleet.period_s, guard.requests, guard.margin) == \
        ("tcp://cloud:5557", "/keys", 10.0, 50, 0.1)
    assert set(PARAMETERS) >= {"fleet_endpoint", "fleet_keys_dir", "fleet_period_s", "fleet_buffer_rows",
                               "guard_requests"}


def test_rows_are_the_published_messages_as_genpy_serializes_them():
    decision = offload_msgs.OffloadDecision(request_id=7, input_size=0.5, cpu_availability=0.4, round_trip_s=0.03,
                                            action=1, action_propensity=1.0, policy="dqn", model_version="a" * 64)
    outcome = offload_msgs.OffloadOutcome(request_id=7, action=1, delivered=1, delivered_s=0.05)
    d, o = learner_fleet.encode((decision, outcome))
    assert offload_msgs.OffloadDecision().deserialize(d) == decision
    assert offload_msgs.OffloadOutcome().deserialize(o) == outcome
    assert learner_fleet.MD5["offload_msgs/OffloadDecision"] == offload_msgs.OffloadDecision._md5sum
    assert "string model_version" in learner_fleet.DEFINITIONS["offload_msgs/OffloadDecision"]


def test_a_fleet_robot_only_for_a_deployed_dqn(tmp_path):
    data = model_file(1)
    path = tmp_path / "model.npz"
    path.write_bytes(data)
    fleet, guard = fleet_settings({"fleet_endpoint": "tcp://127.0.0.1:9", "fleet_insecure": True,
                                   "fleet_timeout_s": 0.2})
    assert learner_fleet.NodeFleet(fleet, guard, "learning", "dqn", str(path), LOG).robot is None
    assert learner_fleet.NodeFleet(fleet, guard, "deployed", "local", str(path), LOG).robot is None
    assert learner_fleet.NodeFleet(*fleet_settings({}), "deployed", "dqn", str(path), LOG).robot is None
    node = learner_fleet.NodeFleet(fleet, guard, "deployed", "dqn", str(path), LOG)
    try:
        assert node.robot.policy.version == model_version(data)
        stats = node.fill_stats(offload_msgs.TrainingStats())
        assert (stats.model_version, stats.rolled_back, stats.fleet_rows_pending) == (model_version(data), [], 0)
        decision = offload_msgs.OffloadDecision(request_id=3)
        msg = offload_msgs.OffloadOutcome(request_id=3, learner_cpu_s=0.0)
        node.outcome(Outcome(3, STATE, Decision(1, 1.0, model_version=model_version(data)), False, 1, 0.05), msg,
                     decision)
        assert len(node.robot.link.buffer) == 1 and node.robot.link.buffer.take(1) == [(decision, msg)]
        assert msg.learner_cpu_s >= 0.0
    finally:
        node.close()


def test_print_learner_cpu_per_request_fleet_against_training(capsys):
    """Benchmark-style, not a timed assertion: the learner's CPU per request in fleet mode (inference, latency
    models, guard) against a DQN that trains on the robot (learning.yaml's schedule)."""
    from offload_learner_py.core.config import DQNConfig
    from offload_learner_py.core.dqn import DQNAgent
    from offload_learner_py.core.policies import DQNPolicy
    from offload_learner_py.online.fleet import DeployedModel, FleetPolicy, FleetRobot
    from offload_learner_py.online.model_guard import ModelGuard
    from routertools import STATUSES, FakePlanner, VirtualClock, finish, wired_router
    from offload_learner_py.online.router_types import RouterConfig
    import torch

    torch.set_num_threads(1)
    data = model_file(1)
    figures = {}
    for name in ("training", "fleet"):
        if name == "fleet":
            policy = FleetPolicy(DeployedModel(model_version(data), load_model(data)[0]))
            robot = FleetRobot(policy, ModelGuard(GuardConfig()))
        else:
            config = DQNConfig(learning_starts=20, train_frequency=1, gradient_steps=1, seed=1)
            policy = DQNPolicy(config, agent=DQNAgent(config), explore=False)
            robot = None
        clock = VirtualClock()
        cpu = []
        def on_outcome(outcome):
            began = time.thread_time()      # as the node adds the guard's CPU to learner_cpu_s
            if robot is not None:
                robot.on_outcome(outcome)
            cpu.append(outcome.learner_cpu_s + time.thread_time() - began)

        router = wired_router(policy, FakePlanner(clock, 0.03), FakePlanner(clock, 0.05), STATUSES,
                              RouterConfig(probe_rate=1.0, seed=3, probe_while_warming_up=False),
                              on_outcome=on_outcome, clock=clock)
        decide = []
        for _ in range(300):
            began = time.thread_time()
            policy.decide(STATE)
            decide.append(time.thread_time() - began)
            router.route({"goal": 1}, STATE)
        finish(router)
        figures[name] = (1e3 * sum(cpu[100:]) / len(cpu[100:]), 1e6 * sum(decide) / len(decide))
    with capsys.disabled():
        for name, (learn_ms, decide_us) in figures.items():
            print(f"\nlearner CPU per request, {name}: {learn_ms:.3f} ms (after 100 requests); decision {decide_us:.0f} us")
    assert figures["fleet"][0] < figures["training"][0]
