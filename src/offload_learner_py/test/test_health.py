"""online/health.py: the statuses the robot's nodes publish on /diagnostics, without ROS: the link's hysteresis
(a flapping link does not flip the status), each level's cause, and the learner's values."""
import pytest

from offload_learner_py.online.health import ERROR, OK, WARN, Hysteresis, LearnerHealth, LinkHealth


def test_hysteresis_needs_runs_in_a_row_both_ways():
    h = Hysteresis(set_after=2, clear_after=3)
    assert [h.observe(b) for b in (True, False, True, True)] == [False, False, False, True]
    assert [h.observe(b) for b in (False, False, True, False, False, False)] == [True, True, True, True, True, False]
    with pytest.raises(ValueError):
        Hysteresis(0, 1)


def test_a_link_goes_down_after_two_missed_heartbeats_and_up_after_two_answered():
    link = LinkHealth()
    assert link.status().level == WARN and "no heartbeat" in link.status().message
    link.heartbeat(True, 0.02)
    assert link.status().level == OK and "20.0 ms" in link.status().message
    link.heartbeat(False, 1.0)
    assert link.status().level == OK           # one lost heartbeat: no flip
    link.heartbeat(False, 1.0)
    status = link.status()
    assert status.level == ERROR and "2 heartbeats" in status.message
    assert status.values["heartbeats missed in a row"] == "2"
    assert status.values["round trip (ms)"] == "20.0"    # the last measured one, not the timeout
    link.heartbeat(True, 0.03)
    assert link.status().level == ERROR
    link.heartbeat(True, 0.03)
    assert link.status().level == OK


def test_a_rested_heartbeat_measures_the_link_but_is_no_ping():
    link = LinkHealth()
    link.heartbeat(True, 0.02, pinged=False)   # a plan's answer stood for the ping
    status = link.status()
    assert status.level == OK and "20.0 ms" in status.message
    assert status.values["heartbeats"] == "0" and status.values["heartbeats rested (a plan measured the link)"] == "1"
    link.heartbeat(True, 0.03)
    assert link.status().values["heartbeats"] == "1"


def test_a_flapping_link_never_flips_the_status():
    link = LinkHealth()
    levels = set()
    for k in range(30):
        link.heartbeat(k % 2 == 0, 0.02)
        levels.add(link.status().level)
    assert levels == {OK}


def test_slow_link_refused_map_and_plan_counts():
    link = LinkHealth(slow_round_trip_s=0.5)
    link.heartbeat(True, 0.8)
    assert link.status().level == WARN and "slow link" in link.status().message
    link.heartbeat(True, 0.1)
    link.map_refused = "width 0"
    assert link.status().level == WARN and "width 0" in link.status().message
    link.map_refused = ""
    for outcome in ("ok", "ok", "timeout", "failed"):
        link.plan(outcome)
    values = link.status().values
    assert (values["plans answered"], values["plans timed out"], values["plans failed"]) == ("2", "1", "1")


FLEET = {"model_version": "ab" * 32, "rolled_back": [], "fleet_rows_sent": 7, "fleet_rows_dropped": 1,
         "fleet_rows_pending": 2}


def test_the_learner_warns_while_the_breaker_is_open():
    health = LearnerHealth("deployed", "dqn", window=4)
    for cloud, probe in ((True, False), (False, True), (True, False), (True, False), (False, False)):
        health.decision(cloud, probe)
    health.outcome(0.0002)
    health.outcome(0.0004)
    status = health.status(False, "", None, now=0.0)
    assert status.level == OK
    assert status.values["cloud share (recent)"] == "0.50"      # the window: the last 4 (local, cloud, cloud, local)
    assert (status.values["decisions"], status.values["probes"]) == ("5", "1")
    assert status.values["learner CPU per request (ms)"] == "0.30"
    status = health.status(True, "heartbeat: cloud unreachable", None, now=1.0)
    assert status.level == WARN and "breaker open" in status.message and "unreachable" in status.message
    assert status.values["breaker"] == "open"


def test_a_rollback_warns_for_a_while_then_clears():
    health = LearnerHealth("deployed", "dqn", rollback_warn_s=60.0)
    assert health.status(False, "", dict(FLEET), now=0.0).level == OK
    rolled = dict(FLEET, rolled_back=["cd" * 32])
    status = health.status(False, "", rolled, now=10.0)
    assert status.level == WARN and "cdcdcdcdcdcd" in status.message
    assert status.values["models rolled back"] == "1" and status.values["fleet rows dropped"] == "1"
    assert health.status(False, "", rolled, now=69.0).level == WARN
    assert health.status(False, "", rolled, now=70.5).level == OK
