"""The robot deployed with a fleet learner (online/fleet.py, fleet_link.py, model_guard.py): rows streamed off the
request path, bounded, dropped oldest first and counted, kept through an outage and sent when the learner
returns; new versions fetched, checked (hash, weights-only) and hot-swapped whole; a worse version rolled back by
the guard, a better one kept (test_fleet_robot_guard); no learning on the robot. A fake FleetClient stands in for the
learner (fleettools)."""
import io
import pickle
import threading
import time

import numpy as np
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.model_file import load_model, model_version
from offload_learner_py.core.policies import Decision
from offload_learner_py.online.fleet import DeployedModel, FleetPolicy, make_fleet_robot
from offload_learner_py.online.fleet_link import FleetConfig, RowBuffer
from offload_learner_py.online.learning import OnlineLearner
from offload_learner_py.online.model_guard import GuardConfig
from offload_learner_py.online.router_types import RouterConfig
from statetools import paper_state_model_file
from routertools import STATE, STATUSES, FakePlanner, Recorder, VirtualClock, finish, wired_router
from fleettools import ERRORS, FakeLearner, fleet, model_file, outcome_of, two_models, wait_for


# --- streaming --------------------------------------------------------------------------------------------------
def test_a_full_buffer_drops_its_oldest_rows_and_counts_them():
    buffer = RowBuffer(3)
    for row in range(5):
        buffer.put(row)
    assert buffer.take(10) == [2, 3, 4] and buffer.dropped == 2
    buffer.put(5)
    buffer.put(6)
    buffer.put_back([3, 4])      # a failed send's rows go back first; the bound still holds, oldest out
    assert buffer.take(10) == [4, 5, 6] and buffer.dropped == 3


def test_rows_reach_the_learner_in_order_in_batches():
    fake = FakeLearner()
    robot = fleet(fake)
    for i in range(6):
        robot.link.enqueue((b"d%d" % i, b"o%d" % i))
    wait_for(lambda: len(fake.rows) == 6)
    robot.close()
    assert fake.rows == [(b"d%d" % i, b"o%d" % i) for i in range(6)]
    assert all(len(batch) <= 4 for batch in fake.batches)
    assert robot.stats()["fleet_rows_sent"] == 6 and robot.stats()["fleet_rows_dropped"] == 0 and fake.closed


def test_an_outage_keeps_rows_up_to_the_bound_and_sends_them_when_the_learner_returns():
    fake = FakeLearner()
    fake.down.set()
    robot = fleet(fake, buffer_rows=8)
    for i in range(11):      # 3 more than the buffer holds: the 3 oldest are dropped and counted
        robot.link.enqueue((b"d%d" % i, b"o%d" % i))
    time.sleep(0.2)           # send attempts fail meanwhile
    assert fake.rows == [] and robot.link.send_failures >= 1
    assert robot.stats()["fleet_rows_pending"] == 8 and robot.stats()["fleet_rows_dropped"] == 3
    fake.down.clear()
    wait_for(lambda: len(fake.rows) == 8, timeout_s=15)
    robot.close()
    assert fake.rows == [(b"d%d" % i, b"o%d" % i) for i in range(3, 11)]
    assert robot.stats() == {**robot.stats(), "fleet_rows_sent": 8, "fleet_rows_dropped": 3, "fleet_rows_pending": 0}


def test_rows_kept_through_an_outage_are_the_node_s_rows_encoded_again_when_resent():
    """The node's encode serializes messages: what goes back into the buffer after a failed send is the messages,
    not their bytes (bytes encoded again would be unencodable, dropped after every outage)."""
    fake = FakeLearner()
    fake.down.set()

    def encode(row):
        decision, outcome = row
        return decision["id"].to_bytes(2, "big"), outcome["id"].to_bytes(2, "big")

    robot = make_fleet_robot(FleetConfig(endpoint="tcp://x:1", insecure=True, period_s=0.05, send_every_s=0.01,
                                         batch_rows=4, buffer_rows=8, timeout_s=0.1), GuardConfig(requests=0),
                             client_factory=lambda: fake, errors=ERRORS, definitions={"d": "def"}, md5={"d": "md5"},
                             encode=encode)
    for i in range(6):
        robot.link.enqueue(({"id": i}, {"id": i}))
    wait_for(lambda: robot.link.send_failures >= 2)
    fake.down.clear()
    wait_for(lambda: len(fake.rows) == 6)
    robot.close()
    assert fake.rows == [(i.to_bytes(2, "big"),) * 2 for i in range(6)]
    assert robot.stats()["fleet_rows_dropped"] == 0 and robot.link.unencodable == 0


def test_busy_keeps_rows_and_refused_batches_and_unencodable_rows_are_counted_as_dropped():
    fake = FakeLearner()
    fake.busy = True

    def encode(row):
        if row == "bad":
            raise ValueError("not a message")
        return row

    robot = make_fleet_robot(FleetConfig(endpoint="tcp://x:1", insecure=True, period_s=0.05, send_every_s=0.01,
                                         batch_rows=4, buffer_rows=8), GuardConfig(requests=0),
                             client_factory=lambda: fake, errors=ERRORS, definitions={"d": "def"}, md5={"d": "md5"},
                             encode=encode)
    robot.link.enqueue((b"a", b"a"))
    robot.link.enqueue("bad")
    time.sleep(0.1)
    assert fake.rows == [] and len(robot.link.buffer) == 1
    fake.busy = False
    wait_for(lambda: len(fake.rows) == 1)
    robot.close()
    assert robot.link.unencodable == 1 and robot.stats()["fleet_rows_dropped"] == 1


def test_enqueue_never_waits_for_the_learner():
    """The request's side only appends: a learner that hangs in send_rows holds up no request."""
    fake = FakeLearner()
    gate = threading.Event()
    sending = threading.Event()
    send = fake.send_rows

    def hanging(*args):
        sending.set()
        gate.wait(10)
        return send(*args)

    fake.send_rows = hanging
    robot = fleet(fake, buffer_rows=100)
    robot.link.enqueue((b"d", b"o"))
    assert sending.wait(5)
    requests = threading.Thread(target=lambda: [robot.on_outcome(outcome_of(latency_s=0.01), row=(b"d%d" % i, b"o"))
                                                for i in range(50)])
    requests.start()
    requests.join(2.0)
    stuck = requests.is_alive()                       # 50 appends while the link's thread is stuck in send_rows
    gate.set()
    assert not stuck
    wait_for(lambda: len(fake.rows) == 51)
    robot.close()


# --- versions: checked, weights-only, hot-swapped ------------------------------------------------------------
def test_a_new_version_is_fetched_checked_loaded_and_decides():
    fake = FakeLearner()
    data = model_file(CLOUD)
    fake.offer, fake.files = model_version(data), {model_version(data): data}
    robot = fleet(fake, start=False)
    assert robot.policy.decide(STATE) == Decision(LOCAL, 1.0)     # no model yet: local, version ""
    robot.link.start()
    wait_for(lambda: robot.policy.version == model_version(data))
    decision = robot.policy.decide(STATE)
    assert decision.action == CLOUD and decision.model_version == model_version(data)
    robot.close()
    assert fake.fetches == [model_version(data)]          # fetched once, not at every period


@pytest.mark.parametrize("kind", ["hash", "pickle", "garbage", "paper state"])
def test_a_file_of_the_wrong_hash_or_a_hostile_one_is_refused_and_the_old_model_kept(kind, caplog):
    fake = FakeLearner()
    good = model_file(LOCAL)
    old = DeployedModel(model_version(good), load_model(good)[0])
    if kind == "hash":
        bad = model_file(CLOUD)
        version, fake.files = model_version(good[:-1] + b"!"), {}
        fake.files[version] = bad                           # the learner sends other bytes than the version names
    else:
        if kind == "pickle":
            out = io.BytesIO()
            np.save(out, np.array([{"os.system": "echo pwned"}], dtype=object), allow_pickle=True)
            bad = out.getvalue()
        elif kind == "garbage":
            bad = b"PK\x03\x04" + pickle.dumps(object) * 3
        else:   # a version trained before p_t: three inputs
            bad = paper_state_model_file()
        version = model_version(bad)
        fake.files = {version: bad}
    fake.offer = version
    robot = fleet(fake, start=False)
    robot.policy.swap(old)
    with caplog.at_level("ERROR"):
        robot.link.start()
        wait_for(lambda: robot.link.models_refused == 1)
        time.sleep(0.2)                                     # later periods do not fetch it again
    robot.close()
    assert robot.policy.model is old and robot.policy.decide(STATE).model_version == model_version(good)
    refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(refused) == 1 and version[:12] in refused[0] and "keeping" in refused[0]
    assert fake.fetches == [version]


def test_no_decision_sees_half_a_swap():
    """A swap mid-decision (here from inside the network's forward pass, the worst moment) leaves that decision
    with the version whose network computed it: the version and its network are one reference, read once."""
    policy = FleetPolicy()

    class Net:
        def __init__(self, action, swap_to=None):
            self.action, self.swap_to = action, swap_to

        def decide(self, *state):
            if self.swap_to is not None:
                policy.swap(self.swap_to)
            return self.action, float(self.action == LOCAL), float(self.action == CLOUD)

    b = DeployedModel("b" * 64, Net(CLOUD))
    a = DeployedModel("a" * 64, Net(LOCAL, swap_to=b))
    policy.swap(a)
    first, second = policy.decide(STATE), policy.decide(STATE)
    assert (first.action, first.model_version) == (LOCAL, "a" * 64)
    assert (second.action, second.model_version) == (CLOUD, "b" * 64)


def test_swaps_under_load_every_decision_names_the_version_that_decided_it():
    files = [model_file(LOCAL), model_file(CLOUD)]
    models = [DeployedModel(model_version(f), load_model(f)[0]) for f in files]
    action_of = {models[0].version: LOCAL, models[1].version: CLOUD}
    policy = FleetPolicy(models[0])
    stop = threading.Event()

    def swapper():
        k = 0
        while not stop.is_set():
            policy.swap(models[k % 2])
            k += 1

    thread = threading.Thread(target=swapper)
    thread.start()
    try:
        # At least 3000 decisions, and on until both versions decided some: on a loaded machine the swapper's
        # thread may not get the GIL during the first 3000 (a 5 ms switch interval), which tests nothing.
        decisions, deadline = [], time.monotonic() + 30.0
        while len(decisions) < 3000 or (len({d.model_version for d in decisions}) < 2 and time.monotonic() < deadline):
            decisions.append(policy.decide(STATE))
    finally:
        stop.set()
        thread.join()
    assert {d.model_version for d in decisions} == set(action_of)
    assert all(d.action == action_of[d.model_version] for d in decisions)


# --- the rollback guard -----------------------------------------------------------------------------------------
def test_a_fleet_robot_never_learns_and_its_learner_cpu_is_inference_level(monkeypatch):
    old, _ = two_models()
    policy = FleetPolicy(old)
    calls = []
    monkeypatch.setattr(FleetPolicy, "learn", lambda self, *a: calls.append(a))
    monkeypatch.setattr(FleetPolicy, "flush", lambda self: calls.append("flush"))
    clock = VirtualClock()
    recorder = Recorder()
    router = wired_router(policy, FakePlanner(clock, 0.03), FakePlanner(clock, 0.05), STATUSES,
                          RouterConfig(probe_rate=0.2, seed=3), on_decision=recorder.decision,
                          on_outcome=recorder.outcome, clock=clock)
    assert not router.learner.learns and not router.learner.needs_both_sides()
    for _ in range(100):
        router.route({"goal": 1}, STATE)
    finish(router)
    assert calls == [] and len(recorder.outcomes) == 100
    assert {o.decision.model_version for o in recorder.outcomes} == {old.version}
    assert all(not o.learned and o.transitions == 0 for o in recorder.outcomes)
    assert any(o.probe for o in recorder.outcomes) and any(o.reward is not None for o in recorder.outcomes)
    assert isinstance(router.learner, OnlineLearner) and router.learner.agent is None


def test_fleet_config_checks():
    with pytest.raises(ValueError, match="keys"):
        FleetConfig(endpoint="tcp://x:1")
    with pytest.raises(ValueError, match="batch"):
        FleetConfig(batch_rows=513)
    with pytest.raises(ValueError, match="guard_requests"):
        GuardConfig(requests=1)
    assert not FleetConfig().enabled and make_fleet_robot(FleetConfig()).link is None
