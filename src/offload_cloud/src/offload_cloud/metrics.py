"""The Prometheus endpoint shared by the cloud server and the fleet learner (prometheus_client): the bind address,
the HTTP server on its own registry, hashed client ids and the metric families built from a counters dict.

Off unless a bind address is given (`--metrics-bind HOST:PORT`). Nothing is counted here: a collector turns the
process's own STATS counters into metric families at scrape time (metrics_server.py, learner/metrics.py), so the
request path pays nothing for the endpoint and the figures are the ones STATS and the log line show."""
import hashlib
import logging
import threading
from typing import Callable, Iterable, Mapping, Optional, Sequence, Tuple

from prometheus_client import CollectorRegistry, GCCollector, ProcessCollector, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

LOG = logging.getLogger("offload_cloud.metrics")


def parse_bind(text: str) -> Tuple[str, int]:
    """HOST:PORT (an IPv6 host in brackets, [::1]:9464) with a port in 0..65535 (0: a free one); ValueError."""
    host, _, port = text.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"a metrics bind address must be HOST:PORT with a port in 0..65535, got {text!r}")
    return host, int(port)


def client_id(name: str) -> str:
    """The label a client (a key's allowlist name, a key prefix, an address) gets on the unauthenticated endpoint:
    the first 16 hex digits of its SHA-256, never the name or key itself. An operator who knows the name can
    compute it (README_cloud)."""
    return hashlib.sha256(name.encode()).hexdigest()[:16]


class Snapshots:
    """Hands counters that one thread writes (the server's broker) to a scrape thread: the scrape asks (`take`),
    the owner answers between two messages (`serve` when `wanted`), so nothing on the request path is locked."""

    def __init__(self):
        self.wanted = False                 # read by the owner thread every turn: a plain attribute is cheapest
        self._answered = threading.Event()
        self._lock = threading.Lock()       # one scrape at a time
        self._value = None

    def take(self, timeout_s: float) -> Optional[dict]:
        """The owner's counters, or None when it did not answer within `timeout_s` (not running)."""
        with self._lock:
            self._answered.clear()
            self._value = None
            self.wanted = True
            answered = self._answered.wait(timeout_s)
            self.wanted = False
            return self._value if answered else None

    def serve(self, make: Callable[[], dict]) -> None:
        """The owner thread: answer the waiting scrape with `make()` (an error costs that scrape, not the owner)."""
        self.wanted = False
        try:
            self._value = make()
        except Exception:
            LOG.exception("metrics snapshot failed")
        finally:
            self._answered.set()


class MetricsEndpoint:
    """`GET /metrics` on its own thread and registry: `collector` plus the process's CPU, memory, descriptors
    and garbage collections."""

    def __init__(self, bind: str, collector):
        host, port = parse_bind(bind)
        self.registry = CollectorRegistry(auto_describe=False)
        ProcessCollector(registry=self.registry)
        GCCollector(registry=self.registry)
        self.registry.register(collector)
        self._httpd, self._thread = start_http_server(port, host, self.registry)
        bound = self._httpd.server_address
        self.address = f"[{bound[0]}]:{bound[1]}" if ":" in bound[0] else f"{bound[0]}:{bound[1]}"

    def close(self) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(5.0)


def gauge(name: str, doc: str, value: float) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, doc, value=value)


def counter(name: str, doc: str, value: float) -> CounterMetricFamily:
    return CounterMetricFamily(name, doc, value=value)


def labelled(family, name: str, doc: str, labels: Sequence[str], samples: Iterable[Tuple[Sequence[str], float]]):
    """A CounterMetricFamily or GaugeMetricFamily with a sample per label tuple."""
    metric = family(name, doc, labels=list(labels))
    for values, value in samples:
        metric.add_metric(list(values), value)
    return metric


def by_label(family, name: str, doc: str, label: str, counts: Mapping[str, float]):
    """One label from a dict of counts (e.g. reason -> count)."""
    return labelled(family, name, doc, [label], (([key], value) for key, value in sorted(counts.items())))


def histogram(name: str, doc: str, figures: dict) -> HistogramMetricFamily:
    """From histogram.Histogram.to_dict(): Prometheus' cumulative buckets, +Inf last."""
    buckets, total = [], 0
    for bound, count in zip(figures["le"] + [float("inf")], figures["counts"]):
        total += count
        buckets.append(("+Inf" if bound == float("inf") else repr(float(bound)), total))
    return HistogramMetricFamily(name, doc, buckets=buckets, sum_value=figures["sum"])
