"""The cloud server's Prometheus metrics: its STATS counters (stats.server_stats, taken by the broker thread between
two messages) as metric families at scrape time. Client names appear only as metrics.client_id hashes."""
from typing import Callable, Iterator, Optional, Tuple

from prometheus_client.core import CounterMetricFamily as Counter, GaugeMetricFamily as Gauge

from offload_cloud.metrics import MetricsEndpoint, Snapshots, by_label, client_id, counter, gauge, histogram, \
    labelled
from offload_cloud.protocol import Status

SNAPSHOT_TIMEOUT_S = 2.0   # the broker answers within one poll period (25 ms) while it runs
# Every reason the server counts, shown from 0: a series that first appears at 1 is taken by Prometheus' rate() to
# have started there, so the first BUSY or cut would not show. Counted in admission.py and server.py (BUSY),
# server.py (refused) and connection_guard.py (cuts); test_cloud_metrics.py checks these against those modules.
BUSY_REASONS = ("rate_limit", "fair_share", "displaced", "queue_full", "expected_wait", "waited")
REFUSALS = ("unknown_key", "handshake_failed", "revoked_key", "too_many_frames")
CUT_REASONS = ("message_bytes", "first_message", "unidentified_bytes", "key_bytes", "all_bytes", "key_connections",
               "max_connections", "revoked")
# A client's counters: STATS field -> (metric, help).
_CLIENT_COUNTERS = {
    "requests": ("offload_cloud_client_requests", "PLAN and UPLOAD messages of a client (hashed name)"),
    "cache_hits": ("offload_cloud_client_cache_hits", "plans of a client on a map the server held"),
    "cache_misses": ("offload_cloud_client_cache_misses", "MAP_UNKNOWN replies to a client"),
    "uploads": ("offload_cloud_client_uploads", "maps a client sent that the server accepted"),
}
_CLIENT_GAUGES = {
    "waiting": ("offload_cloud_client_waiting_requests", "requests of a client waiting for a worker now"),
    "waiting_bytes": ("offload_cloud_client_waiting_bytes", "bytes of a client's waiting requests"),
    "cache_bytes": ("offload_cloud_client_cache_bytes", "bytes of a client's maps in the cache"),
}


def open_endpoint(bind: Optional[str]) -> Tuple[Snapshots, Optional[MetricsEndpoint]]:
    """Where the broker hands its counters, and the endpoint on `bind` that reads them (None: off, the default)."""
    snapshots = Snapshots()
    return snapshots, MetricsEndpoint(bind, ServerCollector(lambda: snapshots.take(SNAPSHOT_TIMEOUT_S))) if bind \
        else None


class ServerCollector:
    """A prometheus_client collector over `snapshot()`: the server's STATS dict, or None when it does not run."""

    def __init__(self, snapshot: Callable[[], Optional[dict]]):
        self.snapshot = snapshot

    def collect(self) -> Iterator:
        stats = self.snapshot()
        yield gauge("offload_cloud_up", "1 when the broker answered this scrape", 0 if stats is None else 1)
        if stats is not None:
            yield from server_families(stats)


def server_families(stats: dict) -> Iterator:
    cache, queue, guard = stats["cache"], stats["queue"], stats["guard"]
    yield gauge("offload_cloud_uptime_seconds", "seconds since the server started", stats["uptime_s"])
    yield gauge("offload_cloud_workers", "planner threads", stats["workers"])
    yield counter("offload_cloud_requests", "PLAN and UPLOAD messages received, refused ones included",
                  stats["requests"])
    yield counter("offload_cloud_pings", "PING messages answered", stats["pings"])
    yield counter("offload_cloud_stats_requests", "STATS messages received", stats["stats"])
    yield by_label(Counter, "offload_cloud_replies", "replies to plans, uploads and malformed messages by status",
                   "status", from_zero(Status.__members__, stats["replies"]))
    yield by_label(Counter, "offload_cloud_busy", "BUSY replies by reason (rate_limit, fair_share, displaced, "
                   "queue_full, expected_wait, waited)", "reason", from_zero(BUSY_REASONS, stats["busy"]))
    yield by_label(Counter, "offload_cloud_refused", "connections and messages refused without a reply, by reason "
                   "(unknown_key, handshake_failed, revoked_key, too_many_frames)", "reason",
                   from_zero(REFUSALS, stats["refused"]))
    yield by_label(Counter, "offload_cloud_dropped_requests", "requests dropped unanswered: their connection had "
                   "closed (abandoned while queued, stale when read)", "reason", stats["dropped"])
    yield histogram("offload_cloud_plan_seconds", "a worker's time on a PLAN, from the broker's dispatch to its "
                    "reply (planning plus the in-process handoff)", stats["seconds"]["plan"])
    yield histogram("offload_cloud_queue_wait_seconds", "time a plan or upload waited for a worker",
                    stats["seconds"]["queue"])
    yield gauge("offload_cloud_queue_depth", "requests waiting for a worker or their map's upload", queue["depth"])
    yield gauge("offload_cloud_queue_max", "requests that may wait (--max-queued)", queue["max"])
    yield gauge("offload_cloud_in_flight", "requests being planned", queue["in_flight"])
    yield gauge("offload_cloud_map_cache_maps", "maps in the cache", cache["maps"])
    yield counter("offload_cloud_map_cache_hits", "plans on a cached map", cache["hits"])
    yield counter("offload_cloud_map_cache_misses", "plans on a map the cache did not hold (MAP_UNKNOWN)",
                  cache["misses"])
    yield counter("offload_cloud_map_cache_uploads", "maps stored", cache["uploads"])
    yield counter("offload_cloud_map_cache_evictions", "maps evicted", cache["evictions"])
    yield from budgets(cache, queue, guard)
    yield by_label(Gauge, "offload_cloud_connections", "open TCP connections by state (identified: said whose they "
                   "are; closing: cut, not yet closed)", "state", guard["connections"])
    yield gauge("offload_cloud_connections_max", "the connection cap (--max-connections or the descriptor limit's)",
                guard["max_connections"])
    yield counter("offload_cloud_connections_accepted", "TCP connections accepted", guard["accepted"])
    yield by_label(Counter, "offload_cloud_guard_cuts", "connections the guard cut, by the bound", "reason",
                   from_zero(CUT_REASONS, guard["cuts"]))
    yield from client_families(stats["clients"])


def from_zero(names, counts: dict) -> dict:
    return {**dict.fromkeys(names, 0), **counts}


def budgets(cache: dict, queue: dict, guard: dict) -> Iterator:
    held = {"map_cache": cache["bytes"], "queue": queue["bytes"],
            **{f"pending_{name}": value for name, value in guard["held_bytes"].items()}}
    bound = {"map_cache": cache["capacity_bytes"], "queue": queue["max_bytes"],
             **{f"pending_{name}": value for name, value in guard["bounds_bytes"].items()}}
    yield by_label(Gauge, "offload_cloud_held_bytes", "bytes held against each budget (pending: received, not yet "
                   "delivered, at the guard's last check; largest_key: the key holding the most)", "budget", held)
    yield by_label(Gauge, "offload_cloud_budget_bytes", "each budget's bound in bytes", "budget", bound)


def client_families(clients: dict) -> Iterator:
    ids = {name: client_id(name) for name in clients}
    for field, (name, doc) in _CLIENT_COUNTERS.items():
        yield labelled(Counter, name, doc, ["client"], (([ids[c]], figures[field]) for c, figures in clients.items()))
    yield labelled(Counter, "offload_cloud_client_replies", "replies to a client by status", ["client", "status"],
                   (([ids[c], status], count) for c, figures in clients.items()
                    for status, count in sorted(figures["replies"].items())))
    yield labelled(Counter, "offload_cloud_client_busy", "BUSY replies to a client for its fair share",
                   ["client", "reason"],
                   (([ids[c], reason], figures[field]) for c, figures in clients.items()
                    for reason, field in (("rate_limit", "rate_limited"), ("fair_share", "fair_share_refused"))))
    for field, (name, doc) in _CLIENT_GAUGES.items():
        yield labelled(Gauge, name, doc, ["client"], (([ids[c]], figures[field]) for c, figures in clients.items()))
