"""The robot's guard over a new fleet version (online/model_guard.py, through FleetRobot): a worse version rolled
back within its window and never offered again, a better or equal one kept, Welch's rule, no baseline, and the
decided side's latency read on a probe."""
import numpy as np
import pytest

from offload_learner_py import CLOUD
from offload_learner_py.online.fleet import FleetPolicy, FleetRobot
from offload_learner_py.online.model_guard import GuardConfig, ModelGuard, welch_worse
from fleettools import FakeLearner, fleet, model_file, outcome_of, run_versions, two_models, wait_for
from routertools import STATE


def test_a_worse_version_is_rolled_back_within_its_window_and_never_offered_again(caplog):
    old, new = two_models()
    fake = FakeLearner()
    robot = fleet(fake, guard=GuardConfig(requests=30), start=False)
    robot.policy.swap(old)
    with caplog.at_level("WARNING"):
        requests, verdict = run_versions(robot, old, new, old_ms=40, new_ms=55)
    assert requests == 30 and verdict.worse
    assert robot.policy.model is old and robot.rolled_back() == (new.version,)
    assert robot.policy.decide(STATE).model_version == old.version
    assert any("rolled back" in r.getMessage() and new.version[:12] in r.getMessage() for r in caplog.records)
    assert robot.stats()["rolled_back"] == [new.version] and robot.stats()["model_version"] == old.version
    fake.offer = new.version
    fake.files = {new.version: model_file(CLOUD)}
    robot.link.start()
    wait_for(lambda: fake.queries)
    robot.close()
    assert fake.queries[0] == (old.version, (new.version,)) and fake.fetches == []   # told, never fetched again
    robot.install(new.version, new.fast)
    assert robot.policy.model is old                        # and never installed again


@pytest.mark.parametrize("new_ms", [30.0, 40.0, 41.0])
def test_a_better_or_equal_version_is_kept(new_ms):
    old, new = two_models()
    robot = FleetRobot(FleetPolicy(old), ModelGuard(GuardConfig(requests=30)))
    requests, verdict = run_versions(robot, old, new, old_ms=40, new_ms=new_ms)
    assert requests == 30 and not verdict.worse
    assert robot.policy.model.version == new.version and robot.rolled_back() == ()


def test_welch_rule():
    same = [0.040, 0.041, 0.039, 0.040] * 8
    assert not welch_worse(same, same, 0.05, 0.95)[0]
    assert welch_worse([x * 1.3 for x in same], same, 0.05, 0.95)[0]
    assert not welch_worse([x * 1.04 for x in same], same, 0.05, 0.95)[0]      # within the margin
    noisy = list(np.random.default_rng(1).normal(0.04, 0.04, 30))
    assert not welch_worse([x + 0.004 for x in noisy], noisy, 0.05, 0.95)[0]   # 10 % worse, lost in noise
    assert welch_worse([0.05] * 5, [0.04] * 5, 0.05, 0.95)[0]                 # no spread: the margin decides


def test_a_version_without_a_baseline_is_kept_untested():
    old, new = two_models()
    robot = FleetRobot(FleetPolicy(None), ModelGuard(GuardConfig(requests=30)))
    robot.install(old.version, old.fast)
    for _ in range(40):
        assert robot.on_outcome(outcome_of(10.0, old.version)) is None
    assert robot.policy.model.version == old.version


def test_the_guard_reads_the_decided_sides_latency_on_a_probe():
    from offload_learner_py.online.fleet import policy_latency_s

    probe = outcome_of(0.020, probe=True, action=CLOUD)
    probe.local, probe.local_s, probe.cloud, probe.cloud_s = object(), 0.020, object(), 0.090
    assert policy_latency_s(probe) == 0.090
    assert policy_latency_s(outcome_of(0.020)) == 0.020


# --- what the robot pays: no learning -------------------------------------------------------------------------
