"""The metric names others rely on are the ones exported: the Grafana dashboard in deploy/grafana (a valid dashboard
model whose every query names a metric the cloud server or the fleet learner exports; HAProxy's names are checked
against its exporter in test_deploy.py) and the `curl .../metrics` output README_cloud shows."""
import json
import re
from pathlib import Path

import pytest

from offload_cloud.learner.metrics import learner_families
from offload_cloud.learner.service import FleetLearner, LearnerConfig
from offload_cloud.metrics_server import server_families

from cloud_test_helpers import start_server

PACKAGE = Path(__file__).resolve().parents[1]
DASHBOARD = PACKAGE / "deploy" / "grafana" / "offload-cloud.json"
_SUFFIXES = {"counter": ("_total",), "gauge": ("",), "histogram": ("_bucket", "_sum", "_count")}


def dashboard() -> dict:
    return json.loads(DASHBOARD.read_text())


def queries(model: dict):
    return [target["expr"] for panel in model["panels"] for target in panel.get("targets", [])]


def exported_names(families) -> set:
    return {family.name + suffix for family in families for suffix in _SUFFIXES[family.type]}


@pytest.fixture(scope="module")
def offload_names(tmp_path_factory):
    server = start_server()
    try:
        stats = server.snapshots.take(5.0)
    finally:
        server.stop()
    learner = FleetLearner(LearnerConfig(insecure=True, store=str(tmp_path_factory.mktemp("store"))))
    learner.start()
    try:
        learner_stats = learner.stats()
    finally:
        learner.stop()
    return exported_names(server_families(stats)) | exported_names(learner_families(learner_stats)) | \
        {"offload_cloud_up"}


def test_dashboard_is_a_grafana_model_over_one_prometheus_datasource():
    model = dashboard()
    assert model["uid"] and model["title"] and model["schemaVersion"] >= 30
    assert [v["type"] for v in model["templating"]["list"]] == ["datasource"]
    ids = [panel["id"] for panel in model["panels"]]
    assert len(ids) == len(set(ids))
    for panel in model["panels"]:
        grid = panel["gridPos"]
        assert 0 <= grid["x"] and grid["x"] + grid["w"] <= 24 and grid["h"] > 0, panel["title"]
        if panel["type"] != "row":
            assert panel["targets"] and panel["datasource"]["uid"] == "${datasource}", panel["title"]
    for expr in queries(model):
        assert expr.count("(") == expr.count(")") and expr.count("{") == expr.count("}"), expr


def test_every_query_names_an_exported_metric(offload_names):
    used = {name for expr in queries(dashboard()) for name in re.findall(r"\b(offload_[a-z_]+)", expr)}
    assert used and used <= offload_names, used - offload_names
    # The bar's figures each have a panel: requests by status, BUSY and refusals by reason, both histograms,
    # budgets, cache, connections, guard cuts, per-client rates, the learner's rows, versions and pool.
    for name in ("offload_cloud_replies_total", "offload_cloud_busy_total", "offload_cloud_refused_total",
                 "offload_cloud_plan_seconds_bucket", "offload_cloud_queue_wait_seconds_bucket",
                 "offload_cloud_held_bytes", "offload_cloud_map_cache_hits_total", "offload_cloud_connections",
                 "offload_cloud_guard_cuts_total", "offload_cloud_client_requests_total",
                 "offload_learner_rows_refused_total", "offload_learner_versions_published_total",
                 "offload_learner_pool_bytes"):
        assert name in used, name


def test_the_check_catches_a_misspelt_metric(offload_names):
    assert "offload_cloud_replys_total" not in offload_names and "offload_cloud_replies_total" in offload_names


def test_the_readme_shows_exported_metrics_with_their_labels(offload_names):
    text = (PACKAGE / "README.md").read_text()
    section = text.split("## Prometheus metrics (`--metrics-bind`)\n", 1)[1].split("\n## ", 1)[0]
    shown = [line for block in re.findall(r"```\n(.*?)```", section, re.S) for line in block.splitlines()
             if line.startswith("offload_")]
    assert len(shown) > 40
    for line in shown:
        name = re.match(r"(offload_\w+)(\{[^}]*\})? [-+.e\d]+$", line)
        assert name and name.group(1) in offload_names, line
        labels = re.findall(r'(client|robot)="([^"]*)"', line)
        assert all(re.fullmatch("[0-9a-f]{16}", value) for _, value in labels), line
