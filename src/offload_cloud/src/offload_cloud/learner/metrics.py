"""The fleet learner's Prometheus metrics: its STATS counters (FleetLearner.stats) as metric families at scrape
time. Robot names (their keys' allowlist names) appear only as metrics.client_id hashes."""
from typing import Callable, Iterator

from prometheus_client.core import CounterMetricFamily as Counter, GaugeMetricFamily as Gauge

from offload_cloud.metrics import client_id, counter, gauge, labelled


class LearnerCollector:
    """A prometheus_client collector over `stats()`, the learner's STATS dict."""

    def __init__(self, stats: Callable[[], dict]):
        self.stats = stats

    def collect(self) -> Iterator:
        yield from learner_families(self.stats())


def learner_families(stats: dict) -> Iterator:
    robots, store = stats["robots"], stats["store"]
    ids = {name: client_id(name) for name in set(robots) | set(stats["pool_bytes_by_robot"])}
    yield labelled(Counter, "offload_learner_rows_accepted", "rows a robot sent that joined the pool", ["robot"],
                   (([ids[name]], figures["accepted"]) for name, figures in robots.items()))
    yield labelled(Counter, "offload_learner_rows_refused", "rows a robot sent that the bag reader refused, by reason",
                   ["robot", "reason"], (([ids[name], reason], count) for name, figures in robots.items()
                                         for reason, count in sorted(figures["refused"].items())))
    yield labelled(Counter, "offload_learner_busy_batches", "ROWS batches answered BUSY (rate or disk budget)",
                   ["robot"], (([ids[name]], figures["busy"]) for name, figures in robots.items()))
    yield labelled(Counter, "offload_learner_accepted_bytes", "bytes of the rows a robot sent that joined the pool",
                   ["robot"], (([ids[name]], figures["bytes"]) for name, figures in robots.items()))
    yield gauge("offload_learner_pool_bytes", "bytes of the experience pool's bags on disk", stats["pool_bytes"])
    yield gauge("offload_learner_pool_budget_bytes", "the pool's disk budget (--disk-mib)", stats["pool_budget_bytes"])
    yield labelled(Gauge, "offload_learner_robot_pool_bytes", "bytes of one robot's bags on disk", ["robot"],
                   (([ids[name]], size) for name, size in stats["pool_bytes_by_robot"].items()))
    yield gauge("offload_learner_robot_pool_budget_bytes", "one robot's share of the pool (--robot-disk-mib)",
                stats["robot_budget_bytes"])
    yield counter("offload_learner_evicted_bags", "closed bags deleted to keep the disk budget", stats["evicted_bags"])
    yield counter("offload_learner_evicted_bytes", "bytes of the bags deleted", stats["evicted_bytes"])
    # From the store's history: every round this store has seen, so the counts survive a restart.
    yield counter("offload_learner_training_rounds", "training rounds recorded in the store", store["rounds"])
    yield counter("offload_learner_versions_published", "model versions the gate published", store["versions"])
    yield counter("offload_learner_versions_refused", "candidates the gate refused (or an operator's pin held "
                  "back)", store["rounds"] - store["versions"])
    yield counter("offload_learner_training_round_errors", "training rounds that failed (this process)",
                  stats["round_errors"])
    yield gauge("offload_learner_rows_since_round", "rows accepted since the last training round", stats["new_rows"])
    yield gauge("offload_learner_fleet_pinned", "1 while an operator pins the fleet's version",
                int(bool(store.get("fleet_pinned"))))
    yield gauge("offload_learner_robots_pinned", "robots pinned to a version (by an operator or a rollback)",
                len(store.get("pins") or {}))
