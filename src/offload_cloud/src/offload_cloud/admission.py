"""Admission to the cloud server's queue and fair share between its clients, as pure logic: no socket, no
thread, a clock that can be injected. The broker asks `admit` for every plan or upload and tells `enqueued`
and `dequeued` what it did with them.

Every request is charged to its client (the allowlist name of its CURVE key, e.g. robot1; in --insecure
mode its connection). A client over its token bucket (rate_per_client plans/s, burst_per_client) gets BUSY
whenever its request would have to wait for a worker; a client's waiting requests are bounded to an equal
share of the queue, in places and in bytes, among the clients that have requests waiting; a newcomer under
its share takes the place of the newest request of the client holding the most, so it is never starved.
"""
import collections
import time
from dataclasses import dataclass, field
from typing import Callable

from offload_cloud.protocol import ProtocolError, Status

# Clients whose counts and token buckets are kept (least recently seen idle ones are forgotten beyond it):
# allowlists are small, but in --insecure mode every connection is a client.
MAX_TRACKED_CLIENTS = 1024


@dataclass
class Client:
    """Counts and token bucket of one client."""
    name: str
    tokens: float
    refilled: float                       # clock time of the last refill
    requests: int = 0                     # plans and uploads received
    rate_limited: int = 0                 # BUSY for being over the rate
    cache_hits: int = 0                   # planned on a map the server held
    cache_misses: int = 0                 # MAP_UNKNOWN
    uploads: int = 0                      # maps it sent (uploads, plans carrying one) that were accepted
    fair_share_refused: int = 0           # BUSY for holding its share of the queue
    waiting: int = 0                      # requests queued or parked now
    waiting_bytes: int = 0                # and their bytes
    replies: collections.Counter = field(default_factory=collections.Counter)   # status name -> count

    def take_token(self, now: float, rate: float, burst: int) -> bool:
        self.tokens = min(float(burst), self.tokens + (now - self.refilled) * rate)
        self.refilled = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass(frozen=True)
class AdmissionConfig:
    workers: int = 2
    max_queued: int = 64                  # requests waiting for a worker
    max_queued_bytes: int = 256 << 20     # and their bytes
    max_wait_s: float = 1.0               # a request expected to wait longer gets BUSY at once
    rate_per_client: float = 50.0         # plans/s a client may have while others wait; 0: no limit
    burst_per_client: int = 100


class Admission:
    """The queue's accounting and the admission rules (the broker's thread only)."""

    def __init__(self, config: AdmissionConfig, clock: Callable[[], float] = time.monotonic):
        self.config, self.clock = config, clock
        self.clients = collections.OrderedDict()   # name -> Client, least recently seen first
        self.waiting = 0                           # requests queued or parked
        self.queued_bytes = 0                      # and their bytes
        self.clients_waiting = 0                   # clients with requests queued or parked
        self.busy = collections.Counter()          # BUSY replies by reason (the broker adds "waited")

    def client(self, name: str) -> Client:
        client = self.clients.get(name)
        if client is None:
            if len(self.clients) >= MAX_TRACKED_CLIENTS:   # forget the least recently seen idle one
                stale = next((key for key, known in self.clients.items() if not known.waiting), None)
                if stale is not None:
                    del self.clients[stale]
            client = Client(name, float(self.config.burst_per_client), self.clock())
            self.clients[name] = client
        else:
            self.clients.move_to_end(name)
        return client

    def enqueued(self, request) -> None:
        """`request` (with .client and .nbytes) now waits for a worker."""
        self.waiting += 1
        self.queued_bytes += request.nbytes
        request.client.waiting += 1
        request.client.waiting_bytes += request.nbytes
        if request.client.waiting == 1:
            self.clients_waiting += 1

    def dequeued(self, request) -> None:
        self.waiting -= 1
        self.queued_bytes -= request.nbytes
        request.client.waiting -= 1
        request.client.waiting_bytes -= request.nbytes
        if request.client.waiting == 0:
            self.clients_waiting -= 1

    def resized(self, request, nbytes: int) -> None:
        """A waiting request shrank (its map was cached meanwhile and dropped from it)."""
        self.queued_bytes -= request.nbytes - nbytes
        request.client.waiting_bytes -= request.nbytes - nbytes
        request.nbytes = nbytes

    def charge_stats(self, client: Client) -> None:
        """STATS cost the broker, which everyone shares: from the client's token bucket, like a plan."""
        rate, burst = self.config.rate_per_client, self.config.burst_per_client
        if rate and not client.take_token(self.clock(), rate, burst):
            client.rate_limited += 1
            self.busy["rate_limit"] += 1
            raise ProtocolError(Status.BUSY, f"client {client.name} is over its rate of {rate:g} requests/s")

    def admit(self, client: Client, total: int, queued, service_s: float, idle_workers: bool,
              displace: Callable[[object, str], None]) -> None:
        """Raises ProtocolError(BUSY) when a request of `total` bytes from `client` may not wait for a
        worker. To make room it may displace the newest waiting request of the client holding the most
        places (`displace(victim, why)` removes it from `queued` and tells its client)."""
        config = self.config
        # An equal share of the queue, in places and in bytes, among the clients with requests waiting,
        # this one included. A client alone may fill the queue.
        sharing = self.clients_waiting + (0 if client.waiting else 1)
        share = max(1, config.max_queued // sharing)
        byte_share = max(total, config.max_queued_bytes // sharing)
        if sharing > 1 and (client.waiting >= share or client.waiting_bytes + total > byte_share):
            client.fair_share_refused += 1
            self.busy["fair_share"] += 1
            raise ProtocolError(Status.BUSY, f"fair share: client {client.name} already has {client.waiting} "
                                             f"requests ({client.waiting_bytes} bytes) queued, its share of the "
                                             f"{config.max_queued} places ({config.max_queued_bytes} bytes) "
                                             f"with {sharing} clients waiting")
        if self.waiting >= config.max_queued or self.queued_bytes + total > config.max_queued_bytes:
            victim = self.displaceable(queued, share, total) if client.waiting < share else None
            if victim is None:
                self.busy["queue_full"] += 1
                raise ProtocolError(Status.BUSY, f"all {config.workers} workers busy and {self.waiting} "
                                                 f"requests ({self.queued_bytes} bytes) queued")
            victim.client.fair_share_refused += 1
            self.busy["displaced"] += 1
            displace(victim, f"fair share: client {victim.client.name} had {victim.client.waiting} of the "
                             f"{config.max_queued} queue places; this one went to client {client.name}")
        expected_wait_s = self.waiting * service_s / config.workers
        if expected_wait_s > config.max_wait_s:
            self.busy["expected_wait"] += 1
            raise ProtocolError(Status.BUSY, f"{self.waiting} requests queued, about {expected_wait_s:.2f} s of "
                                             f"work: over --max-wait-s {config.max_wait_s:g}")
        # Over its rate, a client is still served when a worker is idle and nobody waits: the limit
        # shares a busy server, it does not leave an idle one idle.
        rate, burst = config.rate_per_client, config.burst_per_client
        if rate and not client.take_token(self.clock(), rate, burst) and (self.waiting or not idle_workers):
            client.rate_limited += 1
            self.busy["rate_limit"] += 1
            raise ProtocolError(Status.BUSY, f"rate limit: client {client.name} is over --rate-per-client "
                                             f"{rate:g} plans/s (--burst-per-client {burst}) while the "
                                             f"server is busy")

    def displaceable(self, queued, share: int, total: int):
        """The newest queued request of the client holding the most places, when that is more than `share`
        and removing it makes room for `total` bytes; map carriers others wait for are never displaced."""
        heaviest = max((client for client in self.clients.values() if client.waiting), default=None,
                       key=lambda client: client.waiting)
        if heaviest is None or heaviest.waiting <= share:
            return None
        victim = next((request for request in reversed(queued)
                       if request.client is heaviest and request.uploads is None), None)
        if victim is None or self.queued_bytes - victim.nbytes + total > self.config.max_queued_bytes:
            return None
        return victim

    def client_stats(self, visible: Callable[[str], bool], cache_by_client: dict) -> dict:
        return {name: {"requests": client.requests, "replies": dict(client.replies),
                       "cache_hits": client.cache_hits, "cache_misses": client.cache_misses,
                       "uploads": client.uploads, "rate_limited": client.rate_limited,
                       "fair_share_refused": client.fair_share_refused, "waiting": client.waiting,
                       "waiting_bytes": client.waiting_bytes, "cache_bytes": cache_by_client.get(name, 0)}
                for name, client in self.clients.items() if visible(name)}
