"""The cloud server's Prometheus endpoint (--metrics-bind): off by default; scraped over HTTP before and after a
burst of plans, a BUSY and a refused key, each counter moved by exactly that much; client names and keys appear
only hashed; the figures are the STATS counters (one snapshot, taken by the broker)."""
import re
import time
from pathlib import Path

import pytest
import zmq

from offload_cloud import protocol
from offload_cloud.client import CloudClient
from offload_cloud.keys import load_client_keys
from offload_cloud.metrics import client_id, parse_bind
from offload_cloud.server_cli import parse_args
from offload_cloud.server_config import ServerConfig

from cloud_test_helpers import make_keys, random_map, start_server
from metrics_helpers import moved, samples, scrape, scrape_text, value

pytestmark = pytest.mark.timeout(120)
PLANS = 6


@pytest.fixture(scope="module")
def key_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("keys")
    server_keys = make_keys(root, ["robot", "robot2"])
    return server_keys, root / "robot"


@pytest.fixture(scope="module")
def server(key_dirs):
    # A bucket of exactly PLANS tokens that practically never refills: the burst takes them all, and the STATS
    # request after it (charged to the same bucket, never let through by an idle worker) gets BUSY.
    server = start_server(key_dirs[0], workers=1, metrics_bind="127.0.0.1:0", rate_per_client=1e-6,
                          burst_per_client=PLANS)
    yield server
    server.stop()


def refused_handshake(robot_dir, endpoint: str) -> None:
    """One CURVE handshake with the right server key but a client key the allowlist lacks, and no reconnect after
    the server refuses it."""
    context = zmq.Context()
    dealer = context.socket(zmq.DEALER)
    dealer.linger = 0
    dealer.reconnect_ivl = -1
    dealer.curve_publickey, dealer.curve_secretkey = zmq.curve_keypair()
    dealer.curve_serverkey = load_client_keys(robot_dir)[2]
    dealer.connect(endpoint)
    dealer.send_multipart(protocol.encode_ping(1))
    assert not dealer.poll(1000)   # no answer: the handshake was refused
    dealer.close(0)
    context.term()


def wait_for(address: str, name: str, target: float, **labels) -> dict:
    deadline = time.monotonic() + 10
    while True:
        figures = scrape(address)
        if value(figures, name, **labels) >= target or time.monotonic() > deadline:
            return figures
        time.sleep(0.05)


def test_each_counter_moves_by_exactly_a_burst_a_busy_and_a_refused_key(server, key_dirs):
    address = server.metrics.address
    robot = client_id("robot")
    before = scrape(address)
    assert value(before, "offload_cloud_up") == 1
    grid = random_map(40, 30, 0.2, seed=3)
    with CloudClient(server.endpoint, keys_dir=str(key_dirs[1]), timeout_s=5.0) as client:
        outcomes = [client.plan(grid, (0, 0), (39, 29)) for _ in range(PLANS)]
        assert [o.reply.status for o in outcomes] == [protocol.Status.OK] * PLANS
        with pytest.raises(protocol.ProtocolError) as busy:
            client.stats()
        assert busy.value.status == protocol.Status.BUSY
    refused_handshake(key_dirs[1], server.endpoint)
    after = wait_for(address, "offload_cloud_refused_total", value(before, "offload_cloud_refused_total",
                                                                   reason="unknown_key") + 1, reason="unknown_key")
    time.sleep(0.3)   # anything counted late would show in a second scrape
    after = scrape(address)
    expected = {
        ("offload_cloud_requests_total", ()): PLANS,
        ("offload_cloud_replies_total", (("status", "OK"),)): PLANS,
        ("offload_cloud_replies_total", (("status", "BUSY"),)): 1,
        ("offload_cloud_busy_total", (("reason", "rate_limit"),)): 1,
        ("offload_cloud_refused_total", (("reason", "unknown_key"),)): 1,
        ("offload_cloud_stats_requests_total", ()): 1,
        ("offload_cloud_pings_total", ()): 1,   # the client pings ahead of its first message carrying a map
        ("offload_cloud_plan_seconds_count", ()): PLANS,
        ("offload_cloud_queue_wait_seconds_count", ()): PLANS,
        ("offload_cloud_map_cache_uploads_total", ()): 1,
        ("offload_cloud_map_cache_hits_total", ()): PLANS - 1,
        ("offload_cloud_map_cache_misses_total", ()): 0,
        ("offload_cloud_client_requests_total", (("client", robot),)): PLANS,
        ("offload_cloud_client_replies_total", (("client", robot), ("status", "OK"))): PLANS,
        ("offload_cloud_client_replies_total", (("client", robot), ("status", "BUSY"))): 1,
        ("offload_cloud_client_busy_total", (("client", robot), ("reason", "rate_limit"))): 1,
        ("offload_cloud_client_cache_hits_total", (("client", robot),)): PLANS - 1,
        ("offload_cloud_client_uploads_total", (("client", robot),)): 1,
    }
    assert {key: moved(before, after, key[0], **dict(key[1])) for key in expected} == expected
    # Every BUSY has one reason; the guard cut nothing.
    busy_reasons = sum(v for (name, _), v in after.items() if name == "offload_cloud_busy_total")
    assert busy_reasons == value(after, "offload_cloud_replies_total", status="BUSY") == 1
    assert sum(v for (name, _), v in after.items() if name == "offload_cloud_guard_cuts_total") == 0
    plan_sum = value(after, "offload_cloud_plan_seconds_sum")
    assert 0 < plan_sum < 5 and value(after, "offload_cloud_plan_seconds_bucket", le="+Inf") == PLANS
    assert value(after, "offload_cloud_map_cache_maps") == 1
    assert value(after, "offload_cloud_held_bytes", budget="map_cache") == server.cache.size_bytes > 0
    assert value(after, "offload_cloud_budget_bytes", budget="map_cache") == server.config.cache_bytes
    assert value(after, "offload_cloud_budget_bytes", budget="pending_all") == server.config.max_pending_bytes


def test_the_metrics_are_the_stats_counters(server, key_dirs):
    """One source: the broker's STATS dict; what STATS says, the endpoint says (no traffic in between)."""
    with CloudClient(server.endpoint, keys_dir=str(key_dirs[1].parent / "robot2"), timeout_s=5.0) as client:
        client.ping()
        stats = client.stats()
        figures = scrape(server.metrics.address)   # while its connection is open
    assert value(figures, "offload_cloud_requests_total") == stats["requests"]
    assert value(figures, "offload_cloud_pings_total") == stats["pings"]
    assert value(figures, "offload_cloud_stats_requests_total") == stats["stats"]
    for status, count in stats["replies"].items():
        assert value(figures, "offload_cloud_replies_total", status=status) == count
    assert value(figures, "offload_cloud_plan_seconds_count") == sum(stats["seconds"]["plan"]["counts"])
    assert value(figures, "offload_cloud_connections", state="identified") == \
        stats["guard"]["connections"]["identified"] >= 1


def test_client_names_and_keys_appear_only_hashed(server, key_dirs):
    with CloudClient(server.endpoint, keys_dir=str(key_dirs[1]), timeout_s=5.0) as client:
        client.ping()
    text = scrape_text(server.metrics.address)
    public_key = load_client_keys(key_dirs[1])[0].decode()
    assert public_key not in text and public_key[:8] not in text and '"robot' not in text
    labels = {value for (_, items) in samples(text) for name, value in items if name == "client"}
    assert {client_id("robot"), client_id("robot2")} <= labels
    assert all(re.fullmatch("[0-9a-f]{16}", label) for label in labels), labels


def test_endpoint_is_off_by_default_and_its_address_is_checked(tmp_path):
    assert ServerConfig(insecure=True).metrics_bind is None
    assert parse_args(["--insecure"]).metrics_bind is None
    assert parse_args(["--insecure", "--metrics-bind", "127.0.0.1:9464"]).metrics_bind == "127.0.0.1:9464"
    assert parse_bind("[::1]:9464") == ("::1", 9464)
    for bad in ("9464", "127.0.0.1", "127.0.0.1:http", "127.0.0.1:70000", ":9464"):
        with pytest.raises(ValueError):
            parse_bind(bad)
        with pytest.raises(SystemExit):
            parse_args(["--insecure", "--metrics-bind", bad])
    server = start_server()
    try:
        assert server.metrics is None and server.snapshots.wanted is False
    finally:
        server.stop()


def test_a_stopped_server_scrapes_as_down(key_dirs):
    """A scrape the broker does not answer says up 0 (and nothing else of the server) instead of hanging."""
    from offload_cloud.metrics import Snapshots
    from offload_cloud.metrics_server import ServerCollector

    snapshots = Snapshots()
    families = list(ServerCollector(lambda: snapshots.take(0.05)).collect())
    assert [(f.name, f.samples[0].value) for f in families] == [("offload_cloud_up", 0)]


def test_every_reason_counted_is_shown_from_zero():
    """A reason series that first appears at 1 hides its first rise from rate(): each reason the code counts is
    in the lists the endpoint shows at 0 (read from the modules that count them)."""
    from offload_cloud import metrics_server

    source = Path(__file__).resolve().parents[1] / "src" / "offload_cloud"
    admission, server, guard = ((source / name).read_text()
                                for name in ("admission.py", "server.py", "connection_guard.py"))
    busy = set(re.findall(r'busy\["(\w+)"\]', admission + server))
    refused = set(re.findall(r'refused\["(\w+)"\]', server)) | \
        set(re.search(r'_HANDSHAKE_REFUSALS = \{.*"(\w+)"\}\s+# else "(\w+)"', server).groups())
    cuts = set(re.findall(r'_drop\(\w+, "(\w+)"\)', guard) + re.findall(r'cut_reasons\["(\w+)"\]', guard)
               + re.findall(r'connections"\s*,\s*"(\w+)"\)', guard))
    assert busy == set(metrics_server.BUSY_REASONS)
    assert refused == set(metrics_server.REFUSALS)
    assert cuts == set(metrics_server.CUT_REASONS)


def test_histogram_buckets_follow_prometheus_le():
    """A value equal to a bound counts in that bound's bucket (Prometheus' "le"); buckets come out cumulative, +Inf
    last, with the sum; bounds must increase."""
    from offload_cloud.histogram import Histogram
    from offload_cloud.metrics import histogram

    seconds = Histogram((0.001, 0.01, 0.1))
    for observed in (0.0005, 0.001, 0.001, 0.005, 0.1, 3.0):
        seconds.observe(observed)
    family = histogram("x_seconds", "x", seconds.to_dict())
    assert {s.labels["le"]: s.value for s in family.samples if s.name == "x_seconds_bucket"} == \
        {"0.001": 3, "0.01": 4, "0.1": 5, "+Inf": 6}
    assert [s.value for s in family.samples if s.name == "x_seconds_sum"] == [pytest.approx(3.1075)]
    with pytest.raises(ValueError):
        Histogram((0.1, 0.01))


def test_a_taken_metrics_port_fails_the_start_and_a_failed_start_leaves_it_free(tmp_path):
    import socket

    from cloud_test_helpers import free_port
    from offload_cloud.server import CloudServer
    from offload_cloud.server_cli import main

    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen()
    port = taken.getsockname()[1]
    try:
        with pytest.raises(OSError):
            CloudServer(ServerConfig(bind="tcp://127.0.0.1:0", insecure=True, metrics_bind=f"127.0.0.1:{port}"))
        assert main(["--insecure", "--bind", "tcp://127.0.0.1:0", "--metrics-bind", f"127.0.0.1:{port}"]) == 2
    finally:
        taken.close()
    # The robots' port is taken: the endpoint opened first is closed again, its port free for the next start.
    metrics_port = free_port()
    with zmq.Context() as context, context.socket(zmq.ROUTER) as squatter:
        squatter.bind(f"tcp://127.0.0.1:{free_port()}")
        endpoint = squatter.last_endpoint.decode()
        with pytest.raises(zmq.ZMQError):
            CloudServer(ServerConfig(bind=endpoint, insecure=True, metrics_bind=f"127.0.0.1:{metrics_port}"))
        squatter.close(0)
    server = start_server(metrics_bind=f"127.0.0.1:{metrics_port}")
    try:
        assert value(scrape(server.metrics.address), "offload_cloud_up") == 1
    finally:
        server.stop()
