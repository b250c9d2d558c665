"""Bags recorded before p_t (the paper's three state fields on purpose): an OffloadDecision definition without
local_plan_rate, and main's (the field there, published as 0 and read by nobody). retrain, report and off_policy
read them as before, p_t at the schema's value for older records ("not measured"), and a bag of the current
definition reads its measured p_t back."""
import json

import numpy as np

from bagtools import make_requests, write
from offload_demos.bag_writer import installed_definitions, typestore_for
from offload_learner_py.core.checkpoint import load_checkpoint
from offload_learner_py.core.state import STATE_SCHEMA
from offload_learner_py.data import bags
from offload_learner_py.offline import off_policy, report, retrain

NOT_MEASURED = STATE_SCHEMA["local_plan_rate"].missing


def definition_before_plan_rate() -> str:
    """The installed OffloadDecision.msg without its local_plan_rate field (and the comment line that follows it)."""
    lines = installed_definitions()[0].splitlines(keepends=True)
    at = next(i for i, line in enumerate(lines) if line.startswith("float64 local_plan_rate"))
    following = 1 if lines[at + 1].lstrip().startswith("#") else 0
    return "".join(lines[:at] + lines[at + 1 + following:])


def old_bag(path, n=120):
    old = definition_before_plan_rate()
    assert "local_plan_rate" not in old and "round_trip_s" in old
    return write(path, make_requests(n, seed=4), store=typestore_for(old, installed_definitions()[1]))


def test_the_bag_reader_gives_a_bag_without_the_field_its_missing_value_and_one_with_it_its_values(tmp_path):
    data = bags.read_bags([old_bag(tmp_path / "old.bag")])
    assert data.report.bags[0].ok and data.report.bags[0].invalid == 0
    assert np.all(data.log["local_plan_rate"] == NOT_MEASURED)
    assert np.all(data.transition_table().local_plan_rate == NOT_MEASURED)
    measured = make_requests(30, seed=5)
    for i, (decision, _) in enumerate(measured):
        decision["local_plan_rate"] = 500.0 + i
    table = bags.read_bags([write(tmp_path / "new.bag", measured)]).transition_table()
    assert table.local_plan_rate.tolist() == [500.0 + i for i in range(30)]


def test_a_bag_of_the_old_p_t_in_cells_per_second_is_skipped_never_read_as_a_rate(tmp_path):
    """Bags recorded while p_t counted cells settled per second (4e6-7e7 here) carry the same field: their values
    lie above the recorded bound of d_t per second, so their requests are skipped and counted, not learned as a
    robot planning ten thousand times faster."""
    requests = make_requests(30, seed=6)
    for i, (decision, _) in enumerate(requests):
        decision["local_plan_rate"] = 4e6 + 1e6 * i if i < 20 else 300.0 + i
    data = bags.read_bags([write(tmp_path / "cells_per_second.bag", requests)])
    assert data.report.bags[0].invalid == 20
    assert data.transition_table().local_plan_rate.tolist() == [300.0 + i for i in range(20, 30)]


def test_retrain_report_and_off_policy_read_a_bag_from_before_the_field(tmp_path, capsys):
    path = old_bag(tmp_path / "old.bag")
    assert retrain.main([path, "--out", str(tmp_path / "retrained"), "--steps", "50", "--quiet", "--workers", "1"]) == 0
    agent = load_checkpoint(str(tmp_path / "retrained" / "checkpoint.pt"))
    assert agent.normalisation.to_dict()["fields"] == list(STATE_SCHEMA.names)   # trained on today's state
    assert json.load(open(tmp_path / "retrained" / "evaluation.json"))["retrained"]
    assert report.main([path, "--out", str(tmp_path / "report"), "--quiet"]) == 0
    numbers = json.load(open(tmp_path / "report" / "report.json"))
    assert numbers["requests"] == 120
    capsys.readouterr()
    assert off_policy.main([path]) == 0
    assert "always_local" in capsys.readouterr().out
