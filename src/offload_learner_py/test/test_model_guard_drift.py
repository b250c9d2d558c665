"""A pooled model drifting in small steps (the warehouse robot of the fleet bench of 2026-11-26 went from the
oracle's 60 % local to 91 % local, every version passing): the guard judges each version against a reference that
does not move with each version (online/model_guard.py), and the robot goes back to that reference, not to the
version just before. And a fleet robot warms up like a robot learning alone (online/fleet.py): its first requests
probe both sides, so the fleet learner gets its rows."""
import numpy as np

from offload_learner_py import LOCAL
from offload_learner_py.core.model_file import load_model, model_bytes, model_version
from offload_learner_py.core.normalisation import StateNormalisation
from offload_learner_py.core.policies import Decision
from offload_learner_py.core.state import STATE_SIZE
from offload_learner_py.online.fleet import DeployedModel, FleetPolicy, FleetRobot
from offload_learner_py.online.learning import OnlineLearner
from offload_learner_py.online.model_guard import GuardConfig, ModelGuard
from offload_learner_py.online.router_types import Outcome
from routertools import STATE, STATUSES

WINDOW = 30


def version_model(k: int) -> DeployedModel:
    """A distinct valid model per k (its bias differs), always local."""
    bias = np.array([1.0 + k, 0.0], np.float32)
    data = model_bytes([np.zeros((STATE_SIZE, 2), np.float32)], [bias], StateNormalisation.identity())
    return DeployedModel(model_version(data), load_model(data)[0])


def drifting_versions(guard: ModelGuard, step: float = 0.04, versions: int = 6, seed: int = 3):
    """Versions v0..v5, each `step` slower than the one before, WINDOW requests each with 1 % spread; the
    verdicts in order (a worse one ends the chain)."""
    rng = np.random.default_rng(seed)
    names = [f"{k:064x}" for k in range(versions)]
    verdicts = []
    for k, name in enumerate(names):
        if k:
            guard.begin(name, names[k - 1])
        for _ in range(WINDOW):
            verdict = guard.observe(name, 0.040 * (1 + step) ** k * (1 + 0.01 * rng.standard_normal()))
            if verdict is not None:
                verdicts.append(verdict)
        if verdicts and verdicts[-1].worse:
            break
    return names, verdicts


def test_a_drift_in_steps_within_the_margin_is_caught_against_the_reference():
    names, verdicts = drifting_versions(ModelGuard(GuardConfig(requests=WINDOW)))
    # v1 (4 % slower than v0) is kept; v2 is 8 % slower than v0, the reference: rolled back to v0
    assert [v.worse for v in verdicts] == [False, True]
    assert verdicts[1].version == names[2] and verdicts[1].previous == names[0]
    assert abs(verdicts[1].mean_old_s - 0.040) < 0.001


def test_each_step_alone_is_within_the_margin():
    # the same steps judged one against the one before (a guard begun afresh each time): all kept
    rng = np.random.default_rng(3)
    for k in range(1, 6):
        guard = ModelGuard(GuardConfig(requests=WINDOW))
        for _ in range(WINDOW):
            guard.observe("a", 0.040 * 1.04 ** (k - 1) * (1 + 0.01 * rng.standard_normal()))
        guard.begin("b", "a")
        last = [guard.observe("b", 0.040 * 1.04 ** k * (1 + 0.01 * rng.standard_normal())) for _ in range(WINDOW)]
        assert not last[-1].worse


def test_a_faster_kept_version_becomes_the_reference_and_a_slower_kept_one_does_not():
    guard = ModelGuard(GuardConfig(requests=4))
    for x in [0.040] * 4:
        guard.observe("a", x)
    guard.begin("b", "a")
    assert [guard.observe("b", x) for x in [0.030] * 4][-1].worse is False
    assert guard.reference == "b"                        # faster: the new reference
    guard.begin("c", "b")
    assert [guard.observe("c", x) for x in [0.031] * 4][-1].worse is False
    assert guard.reference == "b"                        # kept (within 5 %) but slower: the reference stays
    guard.begin("d", "c")
    verdict = [guard.observe("d", x) for x in [0.0320] * 4][-1]
    assert verdict.worse and verdict.previous == "b"     # 6.7 % over b, though 3.2 % over c


def outcome(latency_s: float, version: str) -> Outcome:
    return Outcome(1, STATE, Decision(LOCAL, 1.0, model_version=version), False, LOCAL, latency_s)


def test_the_robot_rolls_back_to_the_reference_model_not_the_one_before():
    models = [version_model(k) for k in range(4)]
    robot = FleetRobot(FleetPolicy(models[0]), ModelGuard(GuardConfig(requests=WINDOW)))
    rng = np.random.default_rng(5)
    for k, model in enumerate(models):
        if k:
            robot.install(model.version, model.fast)
        for _ in range(WINDOW):
            robot.on_outcome(outcome(0.040 * 1.04 ** k * (1 + 0.01 * rng.standard_normal()),
                                     robot.policy.version))
        if robot.rolled_back():
            break
    assert robot.rolled_back() == (models[2].version,)
    assert robot.policy.model is models[0]               # the reference, not models[1]


def test_a_fleet_robot_probes_both_sides_on_its_first_requests():
    policy = FleetPolicy(version_model(0), warmup_requests=3)
    learner = OnlineLearner(policy, STATUSES)
    asked = []
    for _ in range(5):
        policy.decide(STATE)                             # the router decides, then asks
        asked.append(learner.needs_both_sides())
    assert asked == [True, True, True, False, False]
    assert not OnlineLearner(FleetPolicy(version_model(0)), STATUSES).needs_both_sides()   # 0: no warm-up


def test_a_robot_started_from_its_own_learning_runs_checkpoint_warms_up_only_for_what_that_run_lacked(tmp_path):
    """The warm-up gives the fleet the robot's both-sides rows; a learning run's checkpoint (every request measured
    on both sides) counts towards it, so a restarted deployed robot does not plan twice for 60 requests again. A
    model file (the fleet's pooled model) does not count."""
    import pytest
    from offload_learner_py.core.checkpoint import save_checkpoint
    from offload_learner_py.core.config import DQNConfig
    from offload_learner_py.core.dqn import DQNAgent
    from offload_learner_py.core.model_file import agent_model_bytes
    from offload_learner_py.online.fleet import make_fleet_robot
    from offload_learner_py.online.fleet_link import FleetConfig
    from fleettools import ERRORS, FakeLearner
    from statetools import raw_states

    def robot_from(path):
        robot = make_fleet_robot(FleetConfig(endpoint="tcp://x:1", insecure=True, warmup_requests=60), model=path,
                                 client_factory=FakeLearner, errors=ERRORS, start=False)
        return robot.policy.warmup_requests

    agent = DQNAgent(DQNConfig(seed=1, learning_starts=10, batch_size=8))
    states = raw_states(np.linspace(1e-3, 0.2, 26), np.full(26, 0.6), np.full(26, 0.03))
    for t in range(25):
        agent.observe(states[t], t % 2, 0.1, states[t + 1])
    save_checkpoint(agent, str(tmp_path / "short.pt"))
    assert robot_from(str(tmp_path / "short.pt")) == 60 - 25       # topped up to 60
    for t in range(50):
        agent.observe(states[t % 25], t % 2, 0.1, states[t % 25 + 1])
    save_checkpoint(agent, str(tmp_path / "run.pt"))
    assert robot_from(str(tmp_path / "run.pt")) == 0               # 75 requests: none
    (tmp_path / "fleet.npz").write_bytes(agent_model_bytes(agent))
    assert robot_from(str(tmp_path / "fleet.npz")) == 60           # a model file: the whole warm-up
    assert robot_from("") == 60
    with pytest.raises(ValueError):
        FleetConfig(endpoint="tcp://x:1", warmup_requests=-1)
