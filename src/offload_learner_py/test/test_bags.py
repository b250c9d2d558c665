"""The bag reader on bags the tests write: pairing, the table it rebuilds, old message definitions,
unknown topics, duplicates, parallel reading (damaged and hostile bags: test_bags_damaged)."""
import math
import shutil

import numpy as np
import pytest

from bagtools import make_requests, write
from offload_learner_py.data import bags, records
from offload_demos.bag_writer import (DECISION_TOPIC, DECISION_TYPE, OUTCOME_TOPIC, OUTCOME_TYPE, BagWriter,
                                           installed_definitions, typestore_for)
from offload_learner_py.core.reward import reward


def _by_id(requests):
    return {decision["request_id"]: (decision, outcome) for decision, outcome in requests}


def test_a_bag_rebuilds_every_request_and_the_table_holds_the_probe_steps(tmp_path):
    requests = make_requests(60, probe_every=3)
    data = bags.read_bags([write(tmp_path / "run.bag", requests)])
    log, report = data.log, data.report
    assert len(log) == 60 and report.bags[0].ok
    written = _by_id(requests)
    for i, request_id in enumerate(log["request_id"]):
        decision, outcome = written[int(request_id)]
        assert log["input_size"][i] == decision["input_size"]
        assert log["cpu_availability"][i] == decision["cpu_availability"]
        assert log["round_trip_s"][i] == decision["round_trip_s"]
        assert log["action"][i] == decision["action"]
        assert log["action_propensity"][i] == decision["action_propensity"]
        assert bool(log["probe"][i]) == decision["probe"]
        taken = "cloud" if decision["action"] == 1 else "local"
        assert log[f"outcome_{taken}_s"][i] == outcome[f"{taken}_s"]
        if not decision["probe"]:   # the other side was not measured: NaN, never a made-up number
            other = "local" if taken == "cloud" else "cloud"
            assert math.isnan(log[f"outcome_{other}_s"][i])
    assert list(log["request_id"]) == sorted(written)   # time order
    table = data.transition_table()
    probes = [written[i] for i in sorted(written) if written[i][0]["probe"]]
    assert len(table) == len(probes) == 20
    assert list(table.t) == [d["request_id"] for d, _ in probes]
    np.testing.assert_array_equal(table.local_s, [o["local_s"] for _, o in probes])
    np.testing.assert_array_equal(table.cloud_s, [o["cloud_s"] for _, o in probes])
    np.testing.assert_array_equal(table.reward, [o["reward"] for _, o in probes])
    bag = report.bags[0]
    assert (bag.decisions, bag.outcomes, bag.requests, bag.rewarded_steps, bag.one_latency_steps) == (60, 60, 60, 20, 40)
    assert "60 requests" in report.format()


def test_unknown_extra_topics_are_ignored_and_counted(tmp_path):
    requests = make_requests(30)
    decision_msg, outcome_msg = installed_definitions()
    weird = "float64[] samples\nstring note\nuint8 level\n"
    store = typestore_for(decision_msg, outcome_msg, {"robot_extras/msg/Weird": weird})

    def extra(bag, index, time_ns):
        bag.write("/robot/weird", "robot_extras/msg/Weird", {"samples": np.arange(index, dtype=np.float64),
                                                            "note": "x" * index, "level": index % 7}, time_ns)
        bag.write("/chatter", "std_msgs/msg/String", {"data": f"hello {index}"}, time_ns)

    path = write(tmp_path / "extra.bag", requests, store=store, extra=extra)
    data = bags.read_bags([path])
    assert len(data.log) == 30 and len(data.transition_table()) == 30
    assert data.report.bags[0].ignored_topics == {"/robot/weird": 30, "/chatter": 30}
    assert "/robot/weird (30)" in data.report.format()


OLD_DECISION = """# an older OffloadDecision: no Q-values, no model steps, no probe flag; a field since removed
Header header
uint64 request_id
float32 battery
float64 input_size
float64 cpu_availability
float64 round_trip_s
uint8 action
float64 action_propensity
string policy
"""
OLD_OUTCOME = """# an older OffloadOutcome: no measured flags, no reward fields, no loss, fields in another order
Header header
uint64 request_id
float64 cloud_s
float64 local_s
uint8 action
string comment
"""


def test_a_bag_written_with_older_message_definitions_still_reads(tmp_path):
    requests = make_requests(25, probe_every=1)
    store = typestore_for(OLD_DECISION, OLD_OUTCOME)
    old = [({**d, "battery": 0.5}, {k: v for k, v in o.items() if k in ("request_id", "cloud_s", "local_s", "action")})
           for d, o in requests]
    data = bags.read_bags([write(tmp_path / "old.bag", old, store=store)])
    bag = data.report.bags[0]
    assert bag.ok, bag.error
    installed = typestore_for(*installed_definitions())
    assert bag.definitions[DECISION_TYPE] != installed.generate_msgdef(DECISION_TYPE)[1]   # really another md5
    table = data.transition_table()
    assert len(table) == 25
    written = _by_id(requests)
    for row in range(25):
        decision, outcome = written[int(table.t[row])]
        assert table.input_size[row] == decision["input_size"]
        assert table.local_s[row] == outcome["local_s"] and table.cloud_s[row] == outcome["cloud_s"]
        # no reward in the old outcome: eq. 10 from the two latencies, with the one reward function
        assert table.reward[row] == pytest.approx(reward(decision["action"], outcome["local_s"], outcome["cloud_s"]))
    assert np.all(np.isnan(data.log["q_local"])) and np.all(data.log["probe"] == 1)
    assert list(data.log["model_version"]) == [""] * 25     # no model version in the old definition


def test_the_model_version_that_decided_reads_back_from_the_bag(tmp_path):
    requests = make_requests(6)
    versions = ["", "a" * 64, "b" * 64, "b" * 64, "", "c" * 64]
    for (decision, _), version in zip(requests, versions):
        decision["model_version"] = version
    data = bags.read_bags([write(tmp_path / "versions.bag", requests)])
    assert data.report.bags[0].ok and list(data.log["model_version"]) == versions


def test_a_definition_without_a_required_field_is_an_error_naming_the_file_and_field(tmp_path):
    no_propensity = OLD_DECISION.replace("float64 action_propensity\n", "")
    path = write(tmp_path / "nopropensity.bag", make_requests(5), store=typestore_for(no_propensity, OLD_OUTCOME))
    data = bags.read_bags([path])
    bag = data.report.bags[0]
    assert not bag.ok and str(path) in bag.error and "action_propensity" in bag.error
    with pytest.raises(bags.BagReadError, match="action_propensity"):
        bags.read_bag(str(path))


def test_decisions_without_outcomes_orphans_duplicates_and_invalid_values_are_dropped_and_counted(tmp_path):
    requests = make_requests(20)
    requests[3] = (requests[3][0], None)                   # the run stopped before the outcome
    requests[4] = (None, requests[4][1])                   # the bag started after the decision
    requests.append(requests[7])                           # published twice
    bad_cpu = dict(requests[9][0], cpu_availability=1.5)
    requests[9] = (bad_cpu, requests[9][1])
    bad_propensity = dict(requests[10][0], action_propensity=0.0)
    requests[10] = (bad_propensity, requests[10][1])
    mismatch = dict(requests[11][1], action=1 - requests[11][1]["action"])
    requests[11] = (requests[11][0], mismatch)
    data = bags.read_bags([write(tmp_path / "messy.bag", requests)])
    bag = data.report.bags[0]
    assert (bag.dropped_no_outcome, bag.orphan_outcomes, bag.duplicate_decisions, bag.duplicate_outcomes,
            bag.invalid) == (1, 1, 1, 1, 3)
    assert bag.requests == len(data.log) == 20 - 5
    dropped = {1003, 1004, 1009, 1010, 1011}
    assert not dropped & set(int(i) for i in data.log["request_id"])
    text = data.report.format()
    assert "1 decisions without outcome dropped" in text and "3 invalid requests dropped" in text
    assert "cpu_availability 1.5" in text


def test_the_same_bag_twice_counts_each_request_once_and_parallel_equals_serial(tmp_path):
    first = write(tmp_path / "a.bag", make_requests(30, seed=1, first_id=1))
    second = write(tmp_path / "b.bag", make_requests(30, seed=2, first_id=100))
    shutil.copy(first, tmp_path / "a_copy.bag")
    serial = bags.read_bags([str(tmp_path)], workers=1)
    parallel = bags.read_bags([str(tmp_path)], workers=3)
    assert len(serial.log) == 60 and serial.report.duplicates_across_bags == 30
    for name in serial.log.columns:
        if name != "policy":
            np.testing.assert_array_equal(serial.log[name], parallel.log[name])
    assert second in [bag.path for bag in serial.report.bags]


def test_one_robot_reusing_another_robots_ids_keeps_both(tmp_path):
    write(tmp_path / "robot1.bag", make_requests(10, seed=1, first_id=1))
    write(tmp_path / "robot2.bag", make_requests(10, seed=2, first_id=1))
    data = bags.read_bags([str(tmp_path)])
    assert len(data.log) == 20 and data.report.id_collisions == 10


def test_an_outcome_without_measured_latency_for_the_taken_side_is_invalid(tmp_path):
    decision, outcome = make_requests(1, probe_every=5)[0]
    taken = "cloud" if decision["action"] == 1 else "local"
    outcome = dict(outcome, **{f"{taken}_measured": False})
    data = bags.read_bags([write(tmp_path / "x.bag", [(decision, outcome)])])
    assert data.report.bags[0].invalid == 1 and len(data.log) == 0
    assert len(data.transition_table()) == 0


def test_a_hedged_request_whose_other_side_won_is_a_request_and_enters_off_policy_at_a_lower_bound(tmp_path):
    """Routed local, the local plan missed the hedge deadline, the cloud answered first and the local plan was
    cancelled: the robot waited for it like any request (it is among the delivered figures); the taken side's
    latency is only known to exceed the delivery time, at which off-policy evaluation takes it, and says so."""
    from offload_demos.bag_writer import probe_request
    from offload_learner_py.offline.off_policy import LoggedSteps, evaluate_policy, format_results
    from offload_learner_py.offline.summary import delivered_figures
    plain = [probe_request(k, 1.0, 0.5, 0.05, 0.02, 0.08, 0, 1.0, math.nan, probe=False) for k in range(1, 40)]
    hedged = probe_request(40, 1.0, 0.5, 0.05, 0.02, 0.08, 0, 1.0, math.nan, probe=False)
    hedged[1].update(local_measured=False, local_s=0.0, cloud_measured=True, cloud_s=0.06, delivered=1,
                     delivered_s=0.12, hedged=True)
    data = bags.read_bags([write(tmp_path / "run.bag", plain + [hedged])])
    assert data.report.bags[0].invalid == 0 and len(data.log) == 40
    figures = delivered_figures(data.log)
    assert figures["hedged"] == 1 and figures["max_s"] == pytest.approx(0.12)
    steps = LoggedSteps.from_log(data.log)
    assert len(steps) == 40 and steps.censored == 1 and steps.latency_s[-1] == pytest.approx(0.12)
    result = evaluate_policy(steps, np.zeros(len(steps), np.int64))
    assert result["latency_ips_s"].value == pytest.approx((39 * 0.02 + 0.12) / 40)   # its delivery time, a lower bound
    assert "1 hedged requests enter at their delivery time" in format_results({"always_local": result})


def test_a_request_with_neither_its_latency_nor_a_delivery_time_is_left_out_not_censored(tmp_path):
    """#31: 1c0e6cb counts as censored only a row that enters at its delivery time; a row with neither the taken
    side's latency nor a delivery time (a request log not from the bag reader, which refuses such rows) is left
    out, and a mutant counting it as censored survived."""
    from offload_demos.bag_writer import probe_request
    from offload_learner_py.data.records import RequestLog
    from offload_learner_py.offline.off_policy import LoggedSteps
    plain = [probe_request(k, 1.0, 0.5, 0.05, 0.02, 0.08, 0, 1.0, math.nan, probe=False) for k in range(1, 41)]
    log = bags.read_bags([write(tmp_path / "run.bag", plain)]).log
    columns = {name: np.array(values, copy=True) for name, values in log.columns.items()}
    columns["outcome_local_s"][-1] = columns["outcome_delivered_s"][-1] = math.nan    # nothing known of it
    columns["outcome_local_s"][-2] = math.nan                                         # known: its delivery time
    steps = LoggedSteps.from_log(RequestLog(columns))
    assert steps.censored == 1 and len(steps) == 39


def test_writer_roundtrip_of_raw_messages_with_installed_types(tmp_path):
    store = typestore_for(*installed_definitions())
    path = str(tmp_path / "raw.bag")
    decision, outcome = make_requests(1)[0]
    with BagWriter(path, store) as bag:
        bag.write(DECISION_TOPIC, DECISION_TYPE, decision, 10)
        bag.write(OUTCOME_TOPIC, OUTCOME_TYPE, outcome, 20)
    columns, report = bags.read_bag(path)
    assert report.requests == 1 and columns["request_id"][0] == decision["request_id"]


def test_requests_the_router_routed_otherwise_are_kept(tmp_path):
    """A probe whose decided side was dropped before it started (a newer request needed it) and a cloud
    decision the open breaker kept local are requests like any other; a non-probe whose routed side has no
    latency is not."""
    from offload_demos.bag_writer import probe_request
    cancelled = probe_request(1, 1.0, 0.5, 0.05, 0.2, 0.05, 0, 1.0, math.nan, probe=True)
    cancelled[1].update(local_measured=False, local_s=0.0, reward_valid=False, delivered=1)
    kept_local = probe_request(2, 1.0, 0.5, 0.05, 0.2, 0.05, 0, 1.0, math.nan, probe=False)
    kept_local[0].update(action=1, breaker="open")
    kept_local[1].update(action=1)
    broken = probe_request(3, 1.0, 0.5, 0.05, 0.2, 0.05, 1, 1.0, math.nan, probe=False)
    broken[1].update(cloud_measured=False, cloud_s=0.0)
    data = bags.read_bags([write(tmp_path / "run.bag", [cancelled, kept_local, broken])])
    assert list(data.log["request_id"]) == [1, 2]
    assert list(data.log["routed"]) == [0, 0] and list(data.log["breaker"]) == ["", "open"]
    assert "routed side (cloud)" in data.report.bags[0].invalid_examples[0]


def test_values_outside_physical_bounds_are_counted_skips(tmp_path):
    """One row with a propensity of 1e-300 or a round trip of 1e308 s would own every figure computed from
    the bag (an IPS weight of 1e300, a NaN network): such rows are skipped and counted, the rest read."""
    requests = make_requests(20, probe_every=1)
    requests[3][0]["action_propensity"] = 1e-300
    requests[5][0]["round_trip_s"] = 1e308
    requests[7][1]["local_s"] = 1e308
    requests[9][0]["input_size"] = 3.8e27
    data = bags.read_bags([write(tmp_path / "run.bag", requests)])
    report = data.report.bags[0]
    assert len(data.log) == 16 and report.invalid == 4
    assert any("action_propensity" in why for why in report.invalid_examples)
    assert np.all(data.log["action_propensity"] >= records.MIN_PROPENSITY)
    assert np.nanmax(data.log["outcome_local_s"]) <= records.MAX_LATENCY_S
