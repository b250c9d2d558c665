"""The cloud server's STATS: the counters a STATS request is answered with (the broker's own, so cheap), the
log lines made of them, and the per-client cache counts taken from each reply. The Prometheus endpoint
(metrics_server.py) reads the same dict."""
import time
from typing import Optional

from offload_planner_cpp import PlanStatus
from offload_cloud.protocol import Kind


def server_stats(server, viewer: Optional[str] = None) -> dict:
    """The counters STATS answers with (broker thread; cheap: no worker is asked). A `viewer` that is
    neither an admin (--stats-admin) nor local sees its own client figures only: other robots' names,
    counts and map sizes are theirs."""
    cache, admins = server.cache, server.config.stats_admins
    everyone = viewer is None or viewer == "local" or viewer in admins
    return {
        "uptime_s": round(time.monotonic() - server.started, 3),
        "workers": server.config.workers,
        "requests": server.counts["requests"], "pings": server.counts["pings"], "stats": server.counts["stats"],
        "replies": dict(server.replies),
        "cache": {"hits": cache.hits, "misses": cache.misses, "uploads": cache.inserted,
                  "evictions": cache.evictions, "maps": len(cache), "bytes": cache.size_bytes,
                  "capacity_bytes": cache.capacity_bytes},
        "queue": {"depth": server.admission.waiting, "bytes": server.queued_bytes, "in_flight": len(server.in_flight),
                  "max": server.config.max_queued, "max_bytes": server.config.max_queued_bytes},
        "busy": dict(server.admission.busy), "refused": dict(server.refused),
        "dropped": {"abandoned": server.abandoned_dropped, "stale": server.stale_dropped},
        "seconds": {"plan": server.plan_seconds.to_dict(), "queue": server.queue_seconds.to_dict()},
        "guard": server.guard.snapshot(),
        "rate_per_client": server.config.rate_per_client, "burst_per_client": server.config.burst_per_client,
        "clients": server.admission.client_stats(lambda name: everyone or name == viewer, cache.bytes_by_owner()),
    }


def stats_line(stats: dict) -> str:
    """One log line of the counters."""
    cache, queue = stats["cache"], stats["queue"]
    replies = ", ".join(f"{name} {count}" for name, count in sorted(stats["replies"].items())) or "none"
    limited = sum(client["rate_limited"] + client["fair_share_refused"] for client in stats["clients"].values())
    return (f"stats: up {stats['uptime_s']:.0f} s, {stats['requests']} requests, {stats['pings']} pings; "
            f"replies {replies}; cache hits {cache['hits']}, misses {cache['misses']}, uploads "
            f"{cache['uploads']}, evictions {cache['evictions']} ({cache['maps']} maps, "
            f"{cache['bytes'] / 2**20:.1f} MiB); queue {queue['depth']}, in flight {queue['in_flight']}; "
            f"{len(stats['clients'])} clients, {limited} BUSY for fair share (rate or queue share)")


def count_cache_use(request, status: str) -> None:
    """Per-client cache counts from a worker's reply: the broker knows whether the request carried its map."""
    planned = status in PlanStatus.__members__
    if request.kind == Kind.UPLOAD or request.carries_map:
        request.client.uploads += planned or status == "OK"
    elif status == "MAP_UNKNOWN":
        request.client.cache_misses += 1
    elif planned:
        request.client.cache_hits += 1


def serving_line(server) -> str:
    """The line logged when the server starts serving: its bounds."""
    config = server.config
    return (f"serving on {server.endpoint} with {config.workers} workers, map cache {config.cache_bytes >> 20} MiB, "
            f"max message {config.max_message_bytes >> 20} MiB, queue {config.max_queued} requests / "
            f"{config.max_queued_bytes >> 20} MiB, pending bytes per connection {server.connection_limit_bytes >> 20} "
            f"MiB and in all {config.max_pending_bytes >> 20} MiB, at most {server.guard.max_connections} "
            f"connections (descriptor limit {server.descriptor_limit})"
            + (f"; metrics on http://{server.metrics.address}/metrics" if server.metrics is not None else ""))
