"""The fleet learner's Prometheus endpoint (serve --metrics-bind): off by default; scraped before and after rows
accepted and refused, a BUSY batch and a training round, each counter moved by exactly that much; robot names
appear only hashed; the pool's bytes against its budgets."""
import pytest

import fleet_helpers as h
from offload_cloud.fleet_client import FleetBusy, FleetClient
from offload_cloud.learner import cli
from offload_cloud.learner.pool import PoolLimits
from offload_cloud.learner.service import FleetLearner, LearnerConfig
from offload_cloud.learner.training import TrainingConfig
from offload_cloud.metrics import client_id

from metrics_helpers import moved, scrape, scrape_text, value

pytestmark = pytest.mark.timeout(180)
DEFS, MD5 = h.definitions()


@pytest.fixture
def learner(tmp_path):
    config = LearnerConfig(insecure=True, store=str(tmp_path / "store"), train_every_rows=10 ** 6,
                           training=TrainingConfig(epochs=5, dqn={"hidden_sizes": [16, 16]}),
                           limits=PoolLimits(rows_per_s=1e-6, rows_burst=200, bytes_per_s=0),
                           metrics_bind="127.0.0.1:0")
    service = FleetLearner(config)
    service.start()
    client = FleetClient(service.endpoint, insecure=True, timeout_s=10, retries=0)
    yield service, client
    client.close()
    service.stop()


def test_rows_busy_and_rounds_move_their_counters_by_exactly_that_much(learner):
    service, client = learner
    robot = client_id("insecure")
    before = scrape(service.metrics.address)
    hostile = [h.nan_row(1001, cpu_availability=float("nan")), h.nan_row(1002, action_propensity=1.5)]
    assert client.send_rows(DEFS, MD5, h.rows(150, seed=2) + hostile) == (150, 2)
    with pytest.raises(FleetBusy):   # 152 of the 200 tokens taken; the bucket does not refill
        client.send_rows(DEFS, MD5, h.rows(60, start_id=500))
    entry = service.train_once()
    assert entry is not None
    after = scrape(service.metrics.address)
    published = int(entry["published"])
    refused_rows = {reason: count for reason, count in service.stats()["robots"]["insecure"]["refused"].items()}
    assert sum(refused_rows.values()) == 2
    expected = {
        ("offload_learner_rows_accepted_total", (("robot", robot),)): 150,
        ("offload_learner_busy_batches_total", (("robot", robot),)): 1,
        ("offload_learner_training_rounds_total", ()): 1,
        ("offload_learner_versions_published_total", ()): published,
        ("offload_learner_versions_refused_total", ()): 1 - published,
        ("offload_learner_training_round_errors_total", ()): 0,
        **{("offload_learner_rows_refused_total", (("reason", reason), ("robot", robot))): count
           for reason, count in refused_rows.items()},
    }
    assert {key: moved(before, after, key[0], **dict(key[1])) for key in expected} == expected
    assert moved(before, after, "offload_learner_accepted_bytes_total", robot=robot) == \
        sum(len(d) + len(o) for d, o in h.rows(150, seed=2))
    pool = value(after, "offload_learner_pool_bytes")
    assert pool == value(after, "offload_learner_robot_pool_bytes", robot=robot) > 0
    assert value(after, "offload_learner_pool_budget_bytes") == service.config.limits.total_bytes
    assert value(after, "offload_learner_robot_pool_budget_bytes") == service.config.limits.robot_bytes


def test_robot_names_appear_only_hashed(learner):
    service, client = learner
    client.send_rows(DEFS, MD5, h.rows(5, seed=4))
    text = scrape_text(service.metrics.address)
    assert f'robot="{client_id("insecure")}"' in text and '"insecure"' not in text


def test_the_learner_endpoint_is_off_by_default():
    assert LearnerConfig().metrics_bind is None
    args = cli.parse_args(["serve", "--insecure", "--store", "s"])
    assert args.metrics_bind is None and cli.learner_config(args).metrics_bind is None
    args = cli.parse_args(["serve", "--insecure", "--store", "s", "--metrics-bind", "0.0.0.0:9465"])
    assert cli.learner_config(args).metrics_bind == "0.0.0.0:9465"
    with pytest.raises(SystemExit):
        cli.parse_args(["serve", "--insecure", "--store", "s", "--metrics-bind", "9465"])


def test_versions_refused_are_the_rounds_not_published():
    from offload_cloud.learner.metrics import learner_families

    stats = {"robots": {}, "pool_bytes_by_robot": {}, "pool_bytes": 0, "pool_budget_bytes": 1, "robot_budget_bytes": 1,
             "evicted_bags": 0, "evicted_bytes": 0, "round_errors": 1, "new_rows": 7,
             "store": {"rounds": 5, "versions": 3, "fleet_pinned": True, "pins": {"a": "v"}}}
    figures = {s.name: s.value for family in learner_families(stats) for s in family.samples}
    assert figures["offload_learner_training_rounds_total"] == 5
    assert figures["offload_learner_versions_published_total"] == 3
    assert figures["offload_learner_versions_refused_total"] == 2
    assert figures["offload_learner_training_round_errors_total"] == 1
    assert figures["offload_learner_fleet_pinned"] == 1 and figures["offload_learner_robots_pinned"] == 1


def test_a_failed_start_leaves_the_metrics_port_free(tmp_path):
    import zmq

    from cloud_test_helpers import free_port

    metrics_port = free_port()
    with zmq.Context() as context, context.socket(zmq.ROUTER) as squatter:
        squatter.bind(f"tcp://127.0.0.1:{free_port()}")
        config = LearnerConfig(bind=squatter.last_endpoint.decode(), insecure=True, store=str(tmp_path / "store"),
                               metrics_bind=f"127.0.0.1:{metrics_port}")
        with pytest.raises(zmq.ZMQError):
            FleetLearner(config).start()
        squatter.close(0)
    config.bind = "tcp://127.0.0.1:0"
    service = FleetLearner(config)
    service.start()
    try:
        assert service.metrics.address == f"127.0.0.1:{metrics_port}"
        assert value(scrape(service.metrics.address), "offload_learner_pool_bytes") == 0
    finally:
        service.stop()
