"""The fleet learner end to end on loopback: rows in -> bags on disk -> read back by the learner's bag reader,
hostile rows refused and counted, the disk budget, the gate, versions, pins and rollbacks, a restart."""
import json
import os
import time

import numpy as np
import pytest

import fleet_helpers as h
from offload_cloud import protocol, protocol_fleet
from offload_cloud.client import CloudClient
from offload_cloud.fleet_client import FleetBusy, FleetClient
from offload_cloud.learner import cli
from offload_cloud.learner.gate import gate
from offload_cloud.learner.pool import PoolLimits
from offload_cloud.learner.service import FleetLearner, LearnerConfig
from offload_cloud.learner.store import ModelStore
from offload_cloud.learner.training import TrainingConfig, published_by
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.model_file import agent_model_bytes, load_model, model_version
from offload_learner_py.data.bags import read_bags
from offload_learner_py.offline.off_policy_steps import LoggedSteps
from offload_learner_py.data.records import pair_records

# 20 epochs (about 130 minibatch steps on 300 rows): at 5, two of eight network seeds had not yet learned the
# rows' CPU rule and their candidates were refused by the gate.
SMALL = TrainingConfig(epochs=20, dqn={"hidden_sizes": [16, 16]})
DEFS, MD5 = h.definitions()


@pytest.fixture
def learner(tmp_path):
    started = []

    def start(**changes):
        config = LearnerConfig(insecure=True, store=str(tmp_path / "store"), train_every_rows=10 ** 6,
                               training=SMALL, **changes)
        service = FleetLearner(config)
        service.start()
        started.append(service)
        return service, FleetClient(service.endpoint, insecure=True, timeout_s=10, retries=0)
    yield start
    for service in started:
        if not service._stop.is_set():
            service.stop()


def test_rows_become_a_bag_that_the_bag_reader_reads_back_unchanged(learner):
    service, client = learner()
    sent = h.rows(40, seed=1)
    assert client.send_rows(DEFS, MD5, sent) == (40, 0)
    assert client.send_rows(DEFS, MD5, sent) == (40, 0)   # a resend (Lazy Pirate): answered, not pooled twice
    client.close()
    service.stop()   # closes the bag: indexed, renamed .bag
    bags = service.pool.bag_paths("insecure")
    assert len(bags) == 1 and bags[0].endswith(".bag")
    from rosbags.rosbag1 import Reader
    with Reader(bags[0]) as reader:
        raw = [data for _, _, data in reader.messages()]
        assert {c.topic for c in reader.connections} == {"/offload_learner/decision", "/offload_learner/outcome"}
    assert raw == [part for row in sent for part in row]   # the robot's bytes, as they came
    data = read_bags(bags, workers=1)
    expected = h.requests(40, seed=1)
    assert list(data.log["request_id"]) == [d["request_id"] for d, _ in expected]
    np.testing.assert_allclose(data.log["cpu_availability"], [d["cpu_availability"] for d, _ in expected])
    assert len(data.transition_table()) == 40


def test_hostile_rows_are_refused_counted_and_the_service_keeps_running(learner):
    service, client = learner(limits=PoolLimits(rows_per_s=10, rows_burst=60, bytes_per_s=0))
    hostile = [h.nan_row(1001, cpu_availability=float("nan")), h.nan_row(1002, action_propensity=1.5),
               h.nan_row(1003, input_size=float("inf")), (b"garbage", b"\x00" * 3)]
    assert client.send_rows(DEFS, MD5, hostile + h.rows(2, start_id=5)) == (2, 4)
    bomb = {name: text + "\n" + "".join(f"float64 f{i}\n" for i in range(300)) for name, text in DEFS.items()}
    assert client.send_rows(bomb, MD5, h.rows(3, start_id=20)) == (0, 3)   # over the reader's definition caps
    broken = {name: "this is not a message definition !!" for name in DEFS}
    assert client.send_rows(broken, MD5, h.rows(3, start_id=30)) == (0, 3)
    with pytest.raises(ValueError):
        client.send_rows(DEFS, MD5, h.rows(1, start_id=40) * 513)   # the client batches; the wire refuses:
    raw = CloudClient(service.endpoint, insecure=True, timeout_s=10)
    reply = raw.request(lambda i: protocol_fleet.encode_rows(i, DEFS, MD5, [(b"d", b"o")] * 513))
    assert reply.status == protocol.Status.TOO_LARGE
    raw.close()
    with pytest.raises(FleetBusy):   # 60 tokens: 2 + 3 + 3 + 10 rows taken so far, 50 more cannot fit
        client.send_rows(DEFS, MD5, h.rows(10, start_id=50)) and client.send_rows(DEFS, MD5, h.rows(50, start_id=70))
    counts = service.stats()["robots"]["insecure"]
    assert counts["accepted"] == 12 and counts["busy"] == 1
    assert counts["refused"]["invalid"] == 3 and counts["refused"]["definitions"] == 6
    assert counts["refused_rows"] >= 10
    assert CloudClient(service.endpoint, insecure=True).ping() > 0


def test_disk_budget_evicts_the_oldest_bags_first(learner):
    service, client = learner(limits=PoolLimits(bag_bytes=8 << 10, total_bytes=40 << 10, robot_bytes=40 << 10,
                                                rows_per_s=0))
    for batch in range(12):
        assert client.send_rows(DEFS, MD5, h.rows(20, start_id=1 + 20 * batch))[0] == 20
    assert service.pool.evicted_bags > 0 and service.pool.disk_bytes() <= 40 << 10
    data = read_bags(service.pool.bag_paths("insecure"), workers=1)
    ids = data.log["request_id"]
    assert ids.max() == 240 and ids.min() > 1   # the newest kept, the oldest gone


def _steps(n=400, seed=3, probe=True):
    from types import SimpleNamespace
    pairs = h.requests(n, seed=seed, probe=probe)
    log = pair_records([SimpleNamespace(**d) for d, _ in pairs], [SimpleNamespace(**o) for _, o in pairs])
    return LoggedSteps.from_log(log)


def test_gate_accepts_a_better_policy_and_refuses_a_worse_one():
    steps = _steps()
    best = np.where(steps.states[:, 1] >= 0.5, 0, 1)   # the known truth: local when the CPU is free
    worst = 1 - best
    local = np.zeros(len(steps), dtype=np.int64)
    ok, difference = gate(steps, best, local)
    assert ok and difference.high < 0
    ok, difference = gate(steps, worst, local)
    assert not ok and difference.low > 0
    assert gate(steps, local, local)[0]   # the same policy: exactly no difference
    assert not gate(steps.slice(np.arange(0)), best, local)[0]


def _model(seed):
    return agent_model_bytes(DQNAgent(DQNConfig.from_dict({"hidden_sizes": [4], "seed": seed})))


def test_a_trained_version_is_published_only_past_the_gate(learner, monkeypatch):
    service, client = learner()
    client.send_rows(DEFS, MD5, h.rows(300, seed=4))
    entry = service.train_once()
    assert entry["published"] and entry["gate"]["insecure"]["accepted"]
    version, size = client.current_version()
    assert version == entry["version"] and size > 0
    data = client.fetch(version)
    assert model_version(data) == version and load_model(data, version)
    from offload_cloud.learner import training   # a candidate the gate refuses stays unpublished
    monkeypatch.setattr(training, "gate", lambda *args, **kwargs: (False, gate(*args, **kwargs)[1]))
    client.send_rows(DEFS, MD5, h.rows(100, seed=5, start_id=1000))
    refused = service.train_once()
    assert refused["parent"] == version and not refused["published"]
    assert client.current_version(version) == (version, size)
    assert [e["published"] for e in service.store.history("trained")] == [True, False]


def test_a_robot_whose_rows_cannot_judge_abstains_and_the_ones_that_can_decide(learner, capsys):
    """A deployed robot that always planned locally and probed 1 request in 20 cannot say what a candidate that
    offloads half its requests would cost it (n/a): it abstains, and the robot whose rows explore both sides
    decides. Before, its n/a vetoed every version for the whole fleet."""
    service, _ = learner()
    assert service.pool.add("explorer", DEFS, MD5, h.rows(300, seed=4))[1] == 300
    assert service.pool.add("greedy", DEFS, MD5, h.rows(300, seed=5, start_id=2000, greedy_local_probe_every=20))[1]
    entry = service.train_once()
    greedy, explorer = entry["gate"]["greedy"], entry["gate"]["explorer"]
    assert not greedy["judged"] and greedy["disagree"] > 0 and greedy["reason"]
    assert explorer["judged"] and explorer["accepted"]
    assert entry["published"] and service.store.state()["current"] == entry["version"]
    assert cli.main(["list", "--store", service.config.store]) == 0     # the operator sees who abstained
    assert "explorer:ok greedy:n/a" in capsys.readouterr().out


def test_a_version_passes_only_when_a_robot_judged_it_and_none_that_judged_refused():
    judged = {"judged": True, "accepted": True}
    refused = {"judged": True, "accepted": False}
    abstained = {"judged": False, "accepted": False}
    assert published_by({"a": judged, "b": abstained})
    assert not published_by({"a": judged, "b": refused, "c": abstained})
    assert not published_by({"a": abstained, "b": abstained})
    assert not published_by({})


def test_pins_rollbacks_and_never_a_rolled_back_version(learner, tmp_path, capsys):
    service, client = learner()
    store = service.store
    first, second = _model(1), _model(2)
    assert store.record_round({"version": model_version(first), "parent": "", "rows": {}, "gate": {}}, first)
    v1, v2 = model_version(first), model_version(second)
    assert store.record_round({"version": v2, "parent": v1, "rows": {}, "gate": {}}, second)
    assert client.current_version(v1)[0] == v2
    # the robot rolled v2 back: it is offered v1 and pinned there, whatever the fleet runs
    assert client.current_version(v1, [v2])[0] == v1
    assert client.current_version(v1)[0] == v1 and store.state()["pins"]["insecure"] == v1
    store_dir = str(tmp_path / "store")
    assert cli.main(["unpin", "--robot", "insecure", "--store", store_dir]) == 0
    assert client.current_version(v1)[0] == v2
    assert client.current_version(v1, [v2])[0] == v1   # the robot's own list still rules out v2
    assert cli.main(["rollback", "--store", store_dir]) == 0   # the operator rolls the fleet back to v1
    assert store.state()["current"] == v1 and store.state()["fleet_pinned"]
    assert client.current_version("")[0] == v1
    assert cli.main(["pin", v2, "--robot", "insecure", "--store", store_dir]) == 0
    assert client.current_version("")[0] == v2
    assert cli.main(["pin", "0" * 64, "--store", store_dir]) == 1
    assert cli.main(["list", "--store", store_dir]) == 0 and v2[:16] in capsys.readouterr().out
    with pytest.raises(Exception):
        client.fetch("0" * 64)
    assert client.fetch(v2) == second


def test_killed_and_restarted_the_store_and_pool_are_intact(learner, tmp_path):
    service, client = learner()
    client.send_rows(DEFS, MD5, h.rows(300, seed=6))
    version = service.train_once()["version"]
    client.send_rows(DEFS, MD5, h.rows(30, seed=7, start_id=5000))
    client.close()
    service._stop.set()   # as a kill: no orderly close of the open bag
    time.sleep(0.3)
    again, client = learner()
    assert client.current_version()[0] == version
    assert len(read_bags(again.pool.bag_paths("insecure"), workers=1).log) == 330
    assert json.loads(open(os.path.join(str(tmp_path / "store"), "state.json")).read())["current"] == version
    assert len(ModelStore(str(tmp_path / "store")).history("trained")) == 1


def test_gate_judges_the_interval_not_the_point():
    """A policy better than the current one on 20 rows where only the taken side was measured (no probes): too
    little to bound the difference, so it is refused (n/a, an unbounded interval); on 40 such rows it is accepted."""
    steps = _steps(400, seed=8, probe=False)
    local = np.zeros(len(steps), dtype=np.int64)
    best = np.where(steps.states[:, 1] >= 0.5, 0, 1)
    few = local.copy()
    differs = np.flatnonzero(best != local)[:20]   # better where it differs, on 20 rows (about 10 explored)
    few[differs] = 1
    ok, difference = gate(steps, few, local)
    assert not ok and not difference.high <= 0
    more = local.copy()
    more[np.flatnonzero(best != local)[:40]] = 1
    ok, difference = gate(steps, more, local)
    assert ok and difference.high < 0


def test_a_robots_rolled_back_version_is_never_offered_even_without_a_pin(tmp_path):
    store = ModelStore(str(tmp_path / "store"))
    first, second = _model(1), _model(2)
    v1, v2 = model_version(first), model_version(second)
    store.record_round({"version": v1, "parent": "", "rows": {}, "gate": {}}, first)
    store.record_round({"version": v2, "parent": v1, "rows": {}, "gate": {}}, second)
    assert store.version_for("r1", "", [v2]) == ""   # nothing it may run: it keeps what it has
    assert store.version_for("r2", "", []) == v2


def test_the_client_refuses_a_file_that_is_not_the_version_asked_for():
    import threading
    import zmq

    context = zmq.Context()
    socket = context.socket(zmq.ROUTER)
    port = socket.bind_to_random_port("tcp://127.0.0.1")

    def lie():
        frames = socket.recv_multipart()
        socket.send_multipart([frames[0]] + [bytes(f) for f in protocol.encode_blob_reply(
            protocol.request_id_of(frames[1]), b"not the model")])
    threading.Thread(target=lie, daemon=True).start()
    client = FleetClient(f"tcp://127.0.0.1:{port}", insecure=True, timeout_s=5, retries=0)
    with pytest.raises(Exception, match="SHA-256"):
        client.fetch("0" * 64)
    client.close()
    socket.close(0)
    context.term()


def test_a_robots_rollback_pin_gives_way_to_the_next_published_version_but_not_an_operators_pin(tmp_path):
    """bench-fleet-learning: robots that rolled a version back stayed pinned for the rest of the run and never
    received the fleet's later versions. The pin a rollback sets lapses when the gate publishes a newer one."""
    store = ModelStore(str(tmp_path / "store"))
    v1, v2, v3, v4 = (model_version(_model(i)) for i in (1, 2, 3, 4))
    store.record_round({"version": v1, "parent": "", "rows": {}, "gate": {}}, _model(1))
    store.record_round({"version": v2, "parent": v1, "rows": {}, "gate": {}}, _model(2))
    assert store.version_for("r1", v1, [v2]) == v1 and store.version_for("r1", v1, [v2]) == v1   # pinned at v1
    store.record_round({"version": v3, "parent": v2, "rows": {}, "gate": {}}, _model(3))
    assert store.version_for("r1", v1, [v2]) == v3          # the next published version reaches it
    assert "r1" not in store.state()["pins"] and store.history("trained")[-1]["rollback_pins_lapsed"] == ["r1"]
    assert store.version_for("r1", v1, [v2, v3]) == v1      # it rolled v3 back too: pinned at v1 again
    assert store.state()["pins"]["r1"] == v1 and store.version_for("r1", v1, [v2, v3]) == v1
    store.pin(v1, robot="r2")                                # an operator's pin holds through publications
    store.record_round({"version": v4, "parent": v3, "rows": {}, "gate": {}}, _model(4))
    assert store.version_for("r2", v1, []) == v1


def test_a_robots_rollback_report_does_not_replace_an_operators_pin(tmp_path):
    """bench-fleet-learning: the bad model pinned for a robot never reached it, because the robot reported a
    rollback of an older version 0.8 s later and that report replaced the operator's pin with its own."""
    store = ModelStore(str(tmp_path / "store"))
    v1, v2, v3 = (model_version(_model(i)) for i in (1, 2, 3))
    for version, parent, seed in ((v1, "", 1), (v2, v1, 2), (v3, v2, 3)):
        store.record_round({"version": version, "parent": parent, "rows": {}, "gate": {}}, _model(seed))
    store.pin(v1, robot="r1")                                  # the operator's word
    assert store.version_for("r1", v3, [v2]) == v1             # a rollback of another version: the pin stays
    assert store.state()["pins"]["r1"] == v1 and "r1" not in store.state()["rollback_pins"]
    assert store.version_for("r1", v3, [v2, v1]) == v3         # it rolled the pinned one back: it keeps its own
    assert store.state()["pins"]["r1"] == v1                   # and the operator's pin is the operator's to lift
