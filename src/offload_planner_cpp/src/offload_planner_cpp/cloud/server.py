"""The cloud copy of the planner: a ROS-free ZeroMQ server around the same C++ core as the robot.

    python -m offload_planner_cpp.cloud.server --bind tcp://0.0.0.0:5555 --workers 2 --keys-dir KEYS

A ROUTER frontend faces the robots. The broker thread answers pings itself and hands plan requests to
N worker threads over an inproc ROUTER, one request per idle worker, with a bounded queue in between,
so a slow plan never delays a ping and memory stays bounded. Workers share a bounded LRU map cache
keyed by content hash. The planner releases the GIL, so workers plan in parallel.

The broker also guards each connection (libzmq buffers a multipart message whole, however many frames,
before the application sees any of it, and has no option to bound the frame count): it watches every
TCP connection's received byte count and cuts a connection that has received more than the
per-connection bound since its last delivered message. It drops queued requests of clients that
disconnected (a Lazy Pirate client that gave up), uploads a map only once when many robots send it at
the same time, and reloads the CURVE allowlist on SIGHUP.

Fair share: every request is charged to its client (the allowlist name of its CURVE key, e.g. robot1; in
--insecure mode its connection). A client over its token bucket (--rate-per-client plans/s, burst
--burst-per-client) gets BUSY naming the limit whenever its request would have to wait for a worker; a
client's waiting requests are bounded to an equal share of the queue among the clients that have requests
waiting; and the map cache evicts the heaviest client's least recently used map first. A STATS request is
answered by the broker from its counters, as a ping is; a summary line is logged every --stats-log-s.
"""
import argparse
import collections
import logging
import pathlib
import signal
import socket as pysocket
import struct
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np
import zmq
import zmq.auth
import zmq.auth.thread
from zmq.utils import z85
from zmq.utils.monitor import parse_monitor_message

from offload_planner_cpp import PlanStatus, plan_raw
from offload_planner_cpp.cli_args import bounded_float, bounded_int
from offload_planner_cpp.cloud import protocol
from offload_planner_cpp.cloud.keys import load_allowlist, load_server_keys, read_key_file
from offload_planner_cpp.cloud.map_cache import MapCache
from offload_planner_cpp.cloud.protocol import Kind, ProtocolError, Reply, Status

LOG = logging.getLogger("offload_planner_cpp.cloud.server")
_READY = b"READY"
_BACKEND_POLL_MS = 25    # how often the broker and workers look at the stop flag and the connection guard
_GUARD_SLACK_BYTES = 1 << 20   # handshake, ZMTP and CURVE framing on top of the messages themselves
_TCP_INFO_BYTES_RECEIVED = 128   # offset of tcpi_bytes_received (u64) in Linux's struct tcp_info (>= 4.1)
# Clients whose counts and token buckets are kept (least recently seen idle ones are forgotten beyond it):
# allowlists are small, but in --insecure mode every connection is a client.
_MAX_TRACKED_CLIENTS = 1024
_MONITORED = (zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_CLOSED | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
              | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_AUTH)


class RateLimitedLog:
    """Logs a line at most once per `period_s` for each key, then says how many were suppressed: a flood
    of BUSY replies or refused handshakes must not flood the log."""

    def __init__(self, logger: logging.Logger, period_s: float = 5.0):
        self.logger = logger
        self.period_s = period_s
        self._last = {}          # key -> (time logged, suppressed since)
        self._lock = threading.Lock()

    def log(self, level: int, key, message: str, *args) -> None:
        now = time.monotonic()
        with self._lock:
            logged_at, suppressed = self._last.get(key, (None, 0))
            if logged_at is not None and now - logged_at < self.period_s:
                self._last[key] = (logged_at, suppressed + 1)
                return
            self._last[key] = (now, 0)
            if len(self._last) > 1024:   # keys are few in practice; never let them grow without bound
                self._last.clear()
        if suppressed:
            message += f" ({suppressed} similar lines suppressed in the last {self.period_s:g} s)"
        self.logger.log(level, message, *args)


class _Authenticator(zmq.auth.thread.ThreadAuthenticator):
    """ZAP handler with an allowlist the server can replace at any time (SIGHUP), logging refused
    handshakes at WARNING with the peer address, rate limited."""

    def __init__(self, context: zmq.Context, allowlist, refusals: RateLimitedLog):
        super().__init__(context, log=LOG)
        self.allowlist = allowlist     # frozenset of Z85 public keys; replaced whole, never mutated
        self._refusals = refusals
        self._address = "?"

    async def handle_zap_message(self, msg):
        self._address = msg[3].decode("utf-8", "replace") if len(msg) > 3 else "?"
        await super().handle_zap_message(msg)

    async def _authenticate_curve(self, domain, client_key):
        key = z85.encode(client_key)
        if key in self.allowlist:
            return True, b"OK"
        self._refusals.log(logging.WARNING, ("refused", self._address),
                           "refused a CURVE handshake from %s: client key %s is not on the allowlist",
                           self._address, key.decode())
        return False, b"Unknown key"


def key_names(clients_dir) -> Dict[bytes, str]:
    """Z85 public key -> allowlist name (the key file's stem, e.g. robot1) of every `*.key` in `clients_dir`."""
    return {read_key_file(path, need_secret=False)[0]: path.stem for path in sorted(pathlib.Path(clients_dir).glob("*.key"))}


def tcp_bytes_received(fd: int) -> Optional[int]:
    """Bytes the kernel has received on a TCP socket (what libzmq may have buffered, and more), or None."""
    try:
        with pysocket.fromfd(fd, pysocket.AF_INET, pysocket.SOCK_STREAM) as sock:
            info = sock.getsockopt(pysocket.IPPROTO_TCP, pysocket.TCP_INFO, 256)
    except OSError:
        return None
    if len(info) < _TCP_INFO_BYTES_RECEIVED + 8:
        return None
    return struct.unpack_from("<Q", info, _TCP_INFO_BYTES_RECEIVED)[0]


def cut_connection(fd: int) -> None:
    """Shuts a TCP connection libzmq owns; libzmq sees the end, closes it and frees its half-received message."""
    try:
        with pysocket.fromfd(fd, pysocket.AF_INET, pysocket.SOCK_STREAM) as sock:
            sock.shutdown(pysocket.SHUT_RDWR)
    except OSError:
        pass


@dataclass
class ServerConfig:
    bind: str = "tcp://127.0.0.1:5555"
    workers: int = 2
    keys_dir: Optional[str] = None        # CURVE keys and client allowlist; required unless insecure
    insecure: bool = False                # plaintext, no client authentication
    cache_bytes: int = 1 << 30            # map cache memory cap (cells + ENTRY_OVERHEAD_BYTES per map)
    max_message_bytes: int = 64 << 20     # larger messages (or frames) are refused
    max_queued: int = 64                  # plan requests waiting for a worker; more get BUSY
    max_queued_bytes: int = 256 << 20     # and their bytes: a request that would exceed it gets BUSY
    max_frames: int = 8                   # more frames than any valid message: dropped unread
    max_wait_s: float = 1.0               # longest a request may wait for a worker; then BUSY, not planned
    rate_per_client: float = 50.0         # plans (and uploads) per second a client may have while others
    burst_per_client: int = 100           # wait; and its bucket's size. rate 0: no rate limit
    stats_log_s: float = 60.0             # period of the stats log line; 0: none
    stats_admins: tuple = ()              # client key names whose STATS show every client; others see
                                          # their own figures only (a local, inproc/ipc, caller sees all)


@dataclass(eq=False)   # compared by identity: removed from the queue as itself
class _Request:
    frames: list                          # route + payload
    nbytes: int                           # payload bytes, counted in queued_bytes while waiting
    fd: Optional[int]                     # the connection it came on (dropped when that closes)
    request_id: int
    route_frames: int
    arrived: float                        # time.monotonic() when the broker admitted it
    client: "_Client" = None              # who sent it (fair share, counts)
    kind: Kind = Kind.PLAN
    uploads: Optional[bytes] = None       # hash of the map it carries and is the one to store
    carries_map: bool = False             # a plan with its map attached


@dataclass
class _Client:
    """Counts and token bucket of one client (broker thread only)."""
    name: str
    tokens: float
    refilled: float                       # time.monotonic() of the last refill
    requests: int = 0                     # plans and uploads received
    rate_limited: int = 0                 # BUSY for being over the rate
    cache_hits: int = 0                   # planned on a map the server held
    cache_misses: int = 0                 # MAP_UNKNOWN
    uploads: int = 0                      # maps it sent (uploads, plans carrying one) that were accepted
    fair_share_refused: int = 0           # BUSY for holding its share of the queue
    waiting: int = 0                      # requests queued or parked now
    replies: collections.Counter = field(default_factory=collections.Counter)   # status name -> count

    def take_token(self, now: float, rate: float, burst: int) -> bool:
        self.tokens = min(float(burst), self.tokens + (now - self.refilled) * rate)
        self.refilled = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass
class _Connection:
    baseline: int                         # bytes received when its last message was delivered
    address: str = "?"
    user: Optional[bytes] = None          # CURVE client key (Z85) once a message came


class CloudServer:
    """Serves plan requests until stop(). Construct, then run() in this thread or start() in another."""

    def __init__(self, config: ServerConfig):
        if not config.insecure and not config.keys_dir:
            raise ValueError("a keys dir is required unless --insecure is given")
        if config.workers < 1:
            raise ValueError("at least one worker is needed")
        if config.max_message_bytes < 1 or config.cache_bytes < 0:
            raise ValueError("the max message size must be >= 1 byte and the cache cap >= 0")
        if not (0 <= config.rate_per_client <= 1e6 and 1 <= config.burst_per_client <= 1e6):
            raise ValueError("the rate per client must be in 0..1e6 plans/s and the burst in 1..1e6")
        if not 0 <= config.stats_log_s <= 86400:
            raise ValueError(f"the stats log period must be in 0..86400 s, got {config.stats_log_s}")
        if not 0 < config.max_wait_s <= 3600:
            raise ValueError(f"the max wait must be in (0, 3600] s, got {config.max_wait_s}")
        if config.max_queued < 1 or config.max_queued_bytes < config.max_message_bytes:
            raise ValueError("max queued must be >= 1 and the queued bytes budget at least the max message size")
        self.config = config
        self.cache = MapCache(config.cache_bytes)
        self.max_cells = config.max_message_bytes   # one byte per int8 cell
        # Bytes a connection may receive beyond its last delivered message: the unread messages libzmq
        # may hold for it (receive HWM), one more being received, and framing.
        self.connection_limit_bytes = (self.receive_hwm(config) + 1) * config.max_message_bytes + _GUARD_SLACK_BYTES
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._ready = threading.Event()
        self._context = zmq.Context()
        self._auth = None
        self._allowlist_dir = None
        self._backend_address = f"inproc://workers-{id(self)}"
        self._log_limited = RateLimitedLog(LOG)
        self.queued_bytes = 0   # bytes of the requests waiting for a worker or parked (broker thread only)
        self.connections_cut = 0        # by the connection guard (for tests)
        self.abandoned_dropped = 0      # queued requests dropped because their client went away
        self.service_s = 0.0            # moving average of a worker's time per request (broker thread only)
        self.started = time.monotonic()
        self.counts = collections.Counter()     # requests, pings, stats (broker thread only)
        self.replies = collections.Counter()    # status name -> replies to plans, uploads and bad messages
        self._clients = collections.OrderedDict()   # name -> _Client, least recently seen first
        self._clients_waiting = 0               # clients with requests queued or parked
        self._key_names = {}                    # Z85 public key -> allowlist name (file stem)
        self._idle = ()                         # the broker's idle workers (for the rate limit)
        self._in_flight = {}                    # the broker's requests being planned
        self._worker_client = threading.local()  # name of the client whose message a worker handles
        self._waiting = 0                       # requests queued or parked (broker thread only)
        self.endpoint = None
        self._thread = None
        self._frontend = self._bind_frontend()
        self._monitor = self._frontend.get_monitor_socket(_MONITORED)

    def _bind_frontend(self) -> zmq.Socket:
        config = self.config
        frontend = self._context.socket(zmq.ROUTER)
        frontend.linger = 0
        frontend.setsockopt(zmq.MAXMSGSIZE, config.max_message_bytes)
        # Incoming messages wait in libzmq until read (per connection); a small high-water mark bounds that
        # memory: at most the queued bytes budget's worth of maximum-size messages, and 2 x max_queued.
        frontend.rcvhwm = self.receive_hwm(config)
        frontend.router_mandatory = False
        try:
            if config.insecure:
                LOG.warning("running INSECURE: plaintext and no client authentication (--insecure)")
            else:
                public, secret, allowlist_dir = load_server_keys(config.keys_dir)
                allowlist = load_allowlist(allowlist_dir)
                self._key_names = key_names(allowlist_dir)
                self._allowlist_dir = allowlist_dir
                self._auth = _Authenticator(self._context, allowlist, self._log_limited)
                self._auth.start()
                frontend.curve_secretkey = secret
                frontend.curve_publickey = public
                frontend.curve_server = True
                LOG.info("CURVE on; client allowlist %s (%d keys; SIGHUP reloads it)", allowlist_dir, len(allowlist))
            if config.bind.endswith(":0"):
                host = config.bind.rsplit(":", 1)[0]
                port = frontend.bind_to_random_port(host)
                self.endpoint = f"{host}:{port}"
            else:
                frontend.bind(config.bind)
                self.endpoint = frontend.last_endpoint.decode()
        except BaseException:
            frontend.close(0)
            self._close_context()
            raise
        return frontend

    @staticmethod
    def receive_hwm(config: ServerConfig) -> int:
        return max(2, min(2 * config.max_queued, config.max_queued_bytes // config.max_message_bytes))

    # -- lifecycle -----------------------------------------------------------------------------------

    def start(self) -> str:
        """Runs the server in a background thread; returns the bound endpoint once it serves."""
        self._thread = threading.Thread(target=self.run, name="cloud-server", daemon=True)
        self._thread.start()
        self._ready.wait(10.0)
        return self.endpoint

    def stop(self, timeout_s: float = 10.0) -> None:
        """Asks the server to stop (safe in a signal handler); waits for it when start() ran it."""
        self._stop.set()
        if self._thread is not None and threading.current_thread() is not self._thread:
            self._thread.join(timeout_s)

    def reload_allowlist(self) -> None:
        """Asks the broker to re-read the allowlist directory (safe in a signal handler: SIGHUP)."""
        self._reload.set()

    def run(self) -> None:
        backend = self._context.socket(zmq.ROUTER)
        backend.linger = 0
        backend.bind(self._backend_address)
        workers = [threading.Thread(target=self._worker, name=f"planner-{k}", daemon=True)
                   for k in range(self.config.workers)]
        for worker in workers:
            worker.start()
        LOG.info("serving on %s with %d workers, map cache %d MiB, max message %d MiB, queue %d requests / "
                 "%d MiB, per-connection bound %d MiB", self.endpoint, self.config.workers,
                 self.config.cache_bytes >> 20, self.config.max_message_bytes >> 20, self.config.max_queued,
                 self.config.max_queued_bytes >> 20, self.connection_limit_bytes >> 20)
        try:
            self._broker(self._frontend, backend)
        finally:
            self._stop.set()
            for worker in workers:
                worker.join(5.0)
            backend.close(0)
            try:
                self._frontend.disable_monitor()
            except zmq.ZMQError:
                pass
            self._monitor.close(0)
            self._frontend.close(0)
            self._close_context()
            LOG.info("stopped; cache hits %d, misses %d, evictions %d; %s", self.cache.hits, self.cache.misses,
                     self.cache.evictions, self.stats_line(self.stats()))

    def _close_context(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        self._context.term()

    def _do_reload(self, connections: Dict[int, _Connection]) -> None:
        if self._auth is None:
            LOG.warning("SIGHUP: no allowlist to reload (--insecure)")
            return
        try:
            allowlist = load_allowlist(self._allowlist_dir)
            names = key_names(self._allowlist_dir)
        except (OSError, ValueError) as error:
            LOG.error("allowlist NOT reloaded, keeping the previous %d keys: %s", len(self._auth.allowlist), error)
            return
        old, self._auth.allowlist = self._auth.allowlist, allowlist
        self._key_names = names
        LOG.warning("allowlist reloaded from %s: %d keys (%d admitted, %d revoked)", self._allowlist_dir,
                    len(allowlist), len(allowlist - old), len(old - allowlist))
        for fd, connection in list(connections.items()):   # revoked robots lose their open connections too
            if connection.user is not None and connection.user not in allowlist:
                LOG.warning("closing the connection of revoked client key %s from %s", connection.user.decode(),
                            connection.address)
                cut_connection(fd)

    # -- broker --------------------------------------------------------------------------------------

    def _broker(self, frontend: zmq.Socket, backend: zmq.Socket) -> None:
        idle = collections.deque()      # worker identities waiting for a request
        queued = collections.deque()    # _Request waiting for a worker
        parked = {}                     # map hash -> [_Request] waiting for the one upload of that map
        in_flight = {}                  # worker identity -> _Request being planned
        connections = {}                # fd -> _Connection
        state = (queued, parked, connections)
        poller = zmq.Poller()
        poller.register(self._monitor, zmq.POLLIN)
        poller.register(frontend, zmq.POLLIN)
        poller.register(backend, zmq.POLLIN)
        guard = self.config.bind.startswith("tcp://")
        checked_at = logged_at = time.monotonic()
        self._idle, self._in_flight = idle, in_flight
        self._ready.set()
        while not self._stop.is_set():
            events = dict(poller.poll(_BACKEND_POLL_MS))
            if self._reload.is_set():
                self._reload.clear()
                self._do_reload(connections)
            while self._monitor.poll(0):   # first: a request of a closed connection must not be queued
                self._on_monitor(parse_monitor_message(self._monitor.recv_multipart()), state)
            if backend in events:
                frames = backend.recv_multipart(copy=False)
                worker, rest = frames[0].bytes, frames[1:]
                done, dispatched_at = in_flight.pop(worker, (None, 0.0))
                if len(rest) > 1:        # a reply: route frames, then the reply itself
                    status = self._reply(frontend, rest, done.client if done is not None else None)
                    if done is not None:
                        _count_cache_use(done, status)
                if done is not None:
                    self.service_s = 0.7 * self.service_s + 0.3 * (time.monotonic() - dispatched_at)
                    if done.uploads is not None:
                        self._release(done.uploads, state)
                idle.append(worker)
            if frontend in events:
                frames = frontend.recv_multipart(copy=False)
                try:
                    self._on_frontend(frontend, frames, state)
                except Exception:   # a bug must cost one message, never the server
                    LOG.exception("message dropped")
            while idle and queued:
                request = queued.popleft()
                self.queued_bytes -= request.nbytes
                self._dequeued(request)
                now = time.monotonic()
                if now - request.arrived > self.config.max_wait_s:
                    # Its client has (nearly) given up: a quick BUSY lets it plan locally now, and the
                    # worker goes to a request that can still be answered in time.
                    self._refuse(frontend, request.frames[:request.route_frames], request.request_id,
                                 ProtocolError(Status.BUSY, f"waited {now - request.arrived:.2f} s for a worker, "
                                                            f"over --max-wait-s {self.config.max_wait_s:g}"),
                                 request.client)
                    if request.uploads is not None:
                        self._release(request.uploads, state)
                    continue
                worker = idle.popleft()
                in_flight[worker] = (request, now)
                # The client's name goes first: the worker stores an uploaded map as that client's.
                backend.send_multipart([worker, request.client.name.encode(), *request.frames], copy=False)
            now = time.monotonic()
            if self.config.stats_log_s and now - logged_at >= self.config.stats_log_s:
                logged_at = now
                LOG.info("%s", self.stats_line(self.stats()))
            if guard and now - checked_at >= _BACKEND_POLL_MS / 1e3:
                checked_at = now
                self._guard(connections)

    def _guard(self, connections: Dict[int, _Connection]) -> None:
        """Cuts every connection that received more than connection_limit_bytes since its last delivered
        message: a message of many frames that libzmq would otherwise buffer whole."""
        for fd, connection in list(connections.items()):
            received = tcp_bytes_received(fd)
            if received is None or received - connection.baseline <= self.connection_limit_bytes:
                continue
            LOG.warning("cut the connection from %s: %d bytes received without a complete message (bound %d "
                        "bytes: a message of too many frames)", connection.address, received - connection.baseline,
                        self.connection_limit_bytes)
            self.connections_cut += 1
            del connections[fd]
            cut_connection(fd)

    def _on_monitor(self, event: dict, state) -> None:
        queued, parked, connections = state
        kind, fd = event["event"], event["value"]
        if kind == zmq.EVENT_ACCEPTED:
            address = "?"
            try:
                with pysocket.fromfd(fd, pysocket.AF_INET, pysocket.SOCK_STREAM) as sock:
                    host, port = sock.getpeername()[:2]
                    address = f"{host}:{port}"
            except OSError:
                pass
            connections[fd] = _Connection(tcp_bytes_received(fd) or 0, address)
        elif kind in (zmq.EVENT_DISCONNECTED, zmq.EVENT_CLOSED):
            connections.pop(fd, None)
            self._drop_requests_of(fd, state)
        else:
            self._log_limited.log(logging.WARNING, ("handshake", kind),
                                  "refused a connection: handshake failed (%s, code %s): a plaintext client, wrong "
                                  "server key or not a ZeroMQ peer", zmq.Event(kind).name, fd)

    def _drop_requests_of(self, fd: int, state) -> None:
        """Forgets the waiting requests of a connection that closed: its client gave up (Lazy Pirate closes
        the socket after a timeout and resends on a new one), so planning them would be wasted work."""
        queued, parked, _ = state
        dropped = [request for request in queued if request.fd == fd]
        if not dropped and not any(request.fd == fd for waiting in parked.values() for request in waiting):
            return
        queued_kept = [request for request in queued if request.fd != fd]
        queued.clear()
        queued.extend(queued_kept)
        for map_hash in list(parked):
            kept = [request for request in parked[map_hash] if request.fd != fd]
            dropped += [request for request in parked[map_hash] if request.fd == fd]
            parked[map_hash] = kept
        for request in dropped:
            self.queued_bytes -= request.nbytes
            self._dequeued(request)
        self.abandoned_dropped += len(dropped)
        LOG.info("dropped %d waiting requests of a closed connection", len(dropped))
        for request in dropped:
            if request.uploads is not None:   # the carrier of a map is gone: the next waiting one carries it
                self._release(request.uploads, state)

    def _release(self, map_hash: bytes, state) -> None:
        """The upload of `map_hash` finished or was dropped: requests parked behind it go to the front of
        the queue, without their copy of the map when it is cached now, else the first one carries it."""
        queued, parked, _ = state
        waiting = parked.pop(map_hash, [])
        if not waiting:
            return
        if map_hash in self.cache:
            for request in waiting:
                if request.carries_map:
                    self._strip_map(request)
        else:
            # The next request that carries the map uploads it; plans that carry only the hash go ahead
            # and get MAP_UNKNOWN (their client uploads); the rest keep waiting for the new carrier.
            carrier = next((request for request in waiting if request.carries_map), None)
            if carrier is not None:
                carrier.uploads = map_hash
                parked[map_hash] = [request for request in waiting if request.carries_map and request is not carrier]
            waiting = [request for request in waiting if request is carrier or not request.carries_map]
        queued.extendleft(reversed(waiting))

    def _strip_map(self, request: _Request) -> None:
        """Turns a plan that carries a map the cache holds into a plan on the cached map."""
        route_frames = len(request.frames) - 4
        kept = request.frames[:route_frames + 2]
        nbytes = sum(len(frame) for frame in kept[route_frames:])
        self.queued_bytes -= request.nbytes - nbytes
        request.frames, request.nbytes, request.uploads, request.carries_map = kept, nbytes, None, False

    def _on_frontend(self, frontend: zmq.Socket, frames, state) -> None:
        queued, parked, connections = state
        # [identity, (empty delimiter if the client is a REQ socket), envelope, body...]
        fd = _source_fd(frames[-1])
        connection = connections.get(fd) if fd is not None else None
        if connection is not None:
            connection.baseline = tcp_bytes_received(fd) or connection.baseline
        user = None
        if self._auth is not None:
            user = _user_of(frames[-1])
            if connection is not None:
                connection.user = user
            if user is None or user not in self._auth.allowlist:   # revoked since its handshake
                self._log_limited.log(logging.WARNING, ("revoked", user),
                                      "dropped a message from revoked client key %s", (user or b"?").decode())
                if fd is not None:
                    connections.pop(fd, None)
                    cut_connection(fd)
                return
        if len(frames) > self.config.max_frames + 2:
            self._log_limited.log(logging.WARNING, "frames", "dropped a message of %d frames", len(frames))
            return
        split = 2 if len(frames) > 2 and len(frames[1]) == 0 else 1
        route, payload = frames[:split], frames[split:]
        if not payload:
            return
        request_id = protocol.request_id_of(payload[0].buffer)
        client = self._client(self._client_name(user, fd, connection))
        try:
            kind, request_id = protocol.decode_envelope(payload[0].buffer)
            if kind == Kind.PING:
                self.counts["pings"] += 1
                self._send(frontend, route + protocol.encode_reply(Reply(request_id, Status.OK, "pong")))
                return
            if kind == Kind.STATS:
                self.counts["stats"] += 1
                # Like a plan, from the client's token bucket: STATS cost the broker, which everyone shares.
                rate, burst = self.config.rate_per_client, self.config.burst_per_client
                if rate and not client.take_token(time.monotonic(), rate, burst):
                    client.rate_limited += 1
                    raise ProtocolError(Status.BUSY, f"client {client.name} is over its rate of {rate:g} "
                                                     "requests/s")
                self._send(frontend, route + protocol.encode_stats_reply(request_id, self.stats(client.name)))
                return
            if kind not in (Kind.PLAN, Kind.UPLOAD):
                raise ProtocolError(Status.BAD_REQUEST, f"a client cannot send a {kind.name} message")
            self.counts["requests"] += 1
            client.requests += 1
            total = sum(len(frame) for frame in payload)
            if total > self.config.max_message_bytes:
                raise ProtocolError(Status.TOO_LARGE, f"message of {total} bytes exceeds "
                                                      f"{self.config.max_message_bytes}")
            # An equal share of the queue among the clients with requests waiting, this one included. A
            # client alone may fill the queue; a newcomer under its share then takes the place of the
            # newest request of the client holding the most (which gets BUSY), so it is never starved.
            sharing = self._clients_waiting + (0 if client.waiting else 1)
            share = max(1, self.config.max_queued // sharing)
            if sharing > 1 and client.waiting >= share:
                client.fair_share_refused += 1
                raise ProtocolError(Status.BUSY, f"fair share: client {client.name} already has {client.waiting} "
                                                 f"requests queued, its share of the {self.config.max_queued} "
                                                 f"places with {sharing} clients waiting")
            waiting = self._waiting
            if waiting >= self.config.max_queued or self.queued_bytes + total > self.config.max_queued_bytes:
                victim = self._displaceable(queued, share, total) if client.waiting < share else None
                if victim is None:
                    raise ProtocolError(Status.BUSY, f"all {self.config.workers} workers busy and {waiting} "
                                                     f"requests ({self.queued_bytes} bytes) queued")
                queued.remove(victim)
                self.queued_bytes -= victim.nbytes
                self._dequeued(victim)
                victim.client.fair_share_refused += 1
                self._refuse(frontend, victim.frames[:victim.route_frames], victim.request_id, ProtocolError(
                    Status.BUSY, f"fair share: client {victim.client.name} had {victim.client.waiting + 1} of the "
                                 f"{self.config.max_queued} queue places; this one went to client {client.name}"),
                    victim.client)
                waiting = self._waiting
            expected_wait_s = waiting * self.service_s / self.config.workers
            if expected_wait_s > self.config.max_wait_s:
                raise ProtocolError(Status.BUSY, f"{waiting} requests queued, about {expected_wait_s:.2f} s of "
                                                 f"work: over --max-wait-s {self.config.max_wait_s:g}")
            # Over its rate, a client is still served when a worker is idle and nobody waits: the limit
            # shares a busy server, it does not leave an idle one idle.
            rate, burst = self.config.rate_per_client, self.config.burst_per_client
            now = time.monotonic()
            if rate and not client.take_token(now, rate, burst) and (waiting or not self._idle):
                client.rate_limited += 1
                raise ProtocolError(Status.BUSY, f"rate limit: client {client.name} is over --rate-per-client "
                                                 f"{rate:g} plans/s (--burst-per-client {burst}) while the "
                                                 f"server is busy")
        except ProtocolError as error:
            self._refuse(frontend, route, request_id, error, client)
            return
        request = _Request(route + payload, total, fd, request_id, len(route), time.monotonic(), client=client,
                           kind=kind)
        self._enqueued(request)
        self.queued_bytes += total
        wanted = _plan_hash(kind, payload)
        if wanted is not None:
            request.carries_map = len(payload) == 4
            if wanted in self.cache:         # cached already: plan on the cached map, skip any upload
                if request.carries_map:
                    self._strip_map(request)
            elif wanted in parked:           # being uploaded by another request: wait for that one
                parked[wanted].append(request)
                return
            elif request.carries_map:        # the one upload of this map
                request.uploads = wanted
                parked[wanted] = []
        queued.append(request)

    def _displaceable(self, queued, share: int, total: int) -> Optional[_Request]:
        """The newest queued request of the client holding the most places, when that is more than `share`
        and removing it makes room for `total` bytes; map carriers others wait for are never displaced."""
        heaviest = max((client for client in self._clients.values() if client.waiting), default=None,
                       key=lambda client: client.waiting)
        if heaviest is None or heaviest.waiting <= share:
            return None
        victim = next((request for request in reversed(queued)
                       if request.client is heaviest and request.uploads is None), None)
        if victim is None or self.queued_bytes - victim.nbytes + total > self.config.max_queued_bytes:
            return None
        return victim

    def _refuse(self, frontend: zmq.Socket, route, request_id: int, error: ProtocolError,
                client: Optional[_Client]) -> None:
        self._log_limited.log(logging.WARNING, ("refused", error.status),
                              "request %d refused: %s: %s", request_id, error.status.name, error)
        self._reply(frontend, route + protocol.encode_reply(Reply(request_id, error.status, str(error))), client)

    def _reply(self, frontend: zmq.Socket, frames, client: Optional[_Client]) -> str:
        """Sends a reply to a plan, an upload or a bad message, counted by status for the server and client;
        returns the status name."""
        try:
            status = Status(bytes(frames[-3])[0]).name   # frames: route, envelope, body, message, path
        except (ValueError, IndexError):
            status = "?"
        self.replies[status] += 1
        if client is not None:
            client.replies[status] += 1
        self._send(frontend, frames)
        return status

    # -- clients and stats (broker thread) -------------------------------------------------------------

    def _client_name(self, user: Optional[bytes], fd: Optional[int], connection: Optional[_Connection]) -> str:
        if user is not None:
            return self._key_names.get(user) or f"key:{user.decode(errors='replace')[:8]}"
        if connection is not None and connection.address != "?":
            return connection.address
        return f"connection:{fd}" if fd is not None else "local"

    def _client(self, name: str) -> _Client:
        client = self._clients.get(name)
        if client is None:
            if len(self._clients) >= _MAX_TRACKED_CLIENTS:   # forget the least recently seen idle one
                stale = next((key for key, known in self._clients.items() if not known.waiting), None)
                if stale is not None:
                    del self._clients[stale]
            client = _Client(name, float(self.config.burst_per_client), time.monotonic())
            self._clients[name] = client
        else:
            self._clients.move_to_end(name)
        return client

    def _enqueued(self, request: _Request) -> None:
        self._waiting += 1
        request.client.waiting += 1
        if request.client.waiting == 1:
            self._clients_waiting += 1

    def _dequeued(self, request: _Request) -> None:
        self._waiting -= 1
        request.client.waiting -= 1
        if request.client.waiting == 0:
            self._clients_waiting -= 1

    def stats(self, viewer: Optional[str] = None) -> dict:
        """The counters STATS answers with (broker thread; cheap: no worker is asked). A `viewer` that is
        neither an admin (--stats-admin) nor local sees its own client figures only: other robots' names,
        counts and map sizes are theirs."""
        cache = self.cache
        cache_by_client = cache.bytes_by_owner()
        return {
            "uptime_s": round(time.monotonic() - self.started, 3),
            "workers": self.config.workers,
            "requests": self.counts["requests"], "pings": self.counts["pings"], "stats": self.counts["stats"],
            "replies": dict(self.replies),
            "cache": {"hits": cache.hits, "misses": cache.misses, "uploads": cache.inserted,
                      "evictions": cache.evictions, "maps": len(cache), "bytes": cache.size_bytes,
                      "capacity_bytes": cache.capacity_bytes},
            "queue": {"depth": self._waiting, "bytes": self.queued_bytes, "in_flight": len(self._in_flight),
                      "max": self.config.max_queued},
            "rate_per_client": self.config.rate_per_client, "burst_per_client": self.config.burst_per_client,
            "clients": {name: {"requests": client.requests, "replies": dict(client.replies),
                               "cache_hits": client.cache_hits, "cache_misses": client.cache_misses,
                               "uploads": client.uploads, "rate_limited": client.rate_limited, "fair_share_refused": client.fair_share_refused,
                               "waiting": client.waiting, "cache_bytes": cache_by_client.get(name, 0)}
                        for name, client in self._clients.items()
                        if viewer is None or viewer == "local" or viewer in self.config.stats_admins
                        or name == viewer},
        }

    @staticmethod
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

    @staticmethod
    def _send(socket: zmq.Socket, frames) -> None:
        try:
            socket.send_multipart(frames, copy=False, flags=zmq.NOBLOCK)
        except zmq.Again:
            LOG.warning("reply dropped: client not reading")
        except zmq.ZMQError as error:   # e.g. the client vanished; never fatal for the server
            LOG.warning("reply dropped: %s", error)

    # -- workers -------------------------------------------------------------------------------------

    def _worker(self) -> None:
        socket = self._context.socket(zmq.DEALER)
        socket.linger = 0
        socket.connect(self._backend_address)
        socket.send(_READY)
        try:
            while not self._stop.is_set():
                if not socket.poll(_BACKEND_POLL_MS):
                    continue
                client, *frames = socket.recv_multipart(copy=False)
                split = 2 if len(frames) > 2 and len(frames[1]) == 0 else 1
                route, payload = frames[:split], frames[split:]
                self._worker_client.name = client.bytes.decode()
                socket.send_multipart(route + self.handle(payload), copy=False)
        finally:
            socket.close(0)

    def handle(self, payload, client: Optional[str] = None) -> list:
        """Reply frames for a PLAN or UPLOAD message (envelope first) of `client` (default: the one this
        worker thread was handed the message for); never raises."""
        if client is None:
            client = getattr(self._worker_client, "name", "")
        request_id = protocol.request_id_of(payload[0].buffer)
        started = time.perf_counter()
        try:
            kind, request_id = protocol.decode_envelope(payload[0].buffer)
            if kind == Kind.UPLOAD:
                return protocol.encode_reply(self._upload(request_id, payload[1:], client))
            return protocol.encode_reply(self._plan(request_id, payload[1:], started, client))
        except ProtocolError as error:
            self._log_limited.log(logging.WARNING, ("request", error.status), "request %d: %s: %s", request_id,
                                  error.status.name, error)
            return protocol.encode_reply(Reply(request_id, error.status, str(error)))
        except Exception as error:   # a bug must cost one reply, never the server
            LOG.exception("request %d failed", request_id)
            return protocol.encode_reply(Reply(request_id, Status.SERVER_ERROR, f"server error: {error}"))

    def _store(self, map_hash: bytes, grid: np.ndarray, client: str) -> None:
        if self.cache.put(map_hash, grid, client):
            LOG.info("map %s (%d x %d) cached; %d maps, %.1f MiB", map_hash.hex()[:12], grid.shape[1],
                     grid.shape[0], len(self.cache), self.cache.size_bytes / 2**20)
        else:
            LOG.warning("map %s of %d bytes exceeds the whole cache; served uncached", map_hash.hex()[:12],
                        grid.nbytes)

    def _upload(self, request_id: int, frames, client: str) -> Reply:
        if len(frames) != 2:
            raise ProtocolError(Status.BAD_REQUEST, f"upload needs 2 frames after the envelope, got {len(frames)}")
        map_hash, grid = protocol.decode_map(frames[0].buffer, frames[1].buffer, self.max_cells)
        self._store(map_hash, grid, client)
        return Reply(request_id, Status.OK, map_hash.hex())

    def _plan(self, request_id: int, frames, started: float, client: str) -> Reply:
        request = protocol.decode_plan(request_id, [frame.buffer for frame in frames], self.max_cells)
        grid = request.grid
        short_hash = request.map_hash.hex()[:12]
        if grid is None:
            grid = self.cache.get(request.map_hash)
            if grid is None:
                LOG.info("request %d: map %s not cached: asking for an upload", request_id, short_hash)
                return Reply(request_id, Status.MAP_UNKNOWN, f"map {request.map_hash.hex()} is not cached: upload it")
            source = "cache hit"
        else:
            self._store(request.map_hash, grid, client)
            source = "uploaded"
        options = request.options
        raw = protocol_plan(grid, request, options)
        status = Status(int(raw["status"]))
        LOG.info("request %d: map %s %s, %s -> %s: %s, plan %.2f ms, %d expansions, %.2f ms in server",
                 request_id, short_hash, source, request.start, request.goal, raw["status"], raw["seconds"] * 1e3,
                 raw["expansions"], (time.perf_counter() - started) * 1e3)
        return Reply(request_id, status, raw["message"], raw["path"], raw["goal"], raw["expansions"],
                     raw["seconds"], raw["cost"])


def protocol_plan(grid: np.ndarray, request: protocol.PlanRequest, options: protocol.PlanOptions) -> dict:
    """plan_raw() with the request's options; malformed option values come back as a status, not a raise."""
    try:
        return plan_raw(grid, request.start, request.goal, lethal_threshold=options.lethal_threshold,
                        unknown_is_obstacle=options.unknown_is_obstacle,
                        goal_tolerance=options.goal_tolerance_cells, stop_at_goal=options.stop_at_goal)
    except ValueError as error:
        return {"status": PlanStatus.INVALID_REQUEST, "message": str(error), "path": np.empty((0, 2), np.int32),
                "goal": request.goal, "expansions": 0, "seconds": 0.0, "cost": 0.0}


def _count_cache_use(request: _Request, status: str) -> None:
    """Per-client cache counts from a worker's reply: the broker knows whether the request carried its map."""
    planned = status in PlanStatus.__members__
    if request.kind == Kind.UPLOAD or request.carries_map:
        request.client.uploads += planned or status == "OK"
    elif status == "MAP_UNKNOWN":
        request.client.cache_misses += 1
    elif planned:
        request.client.cache_hits += 1


def _source_fd(frame) -> Optional[int]:
    try:
        return frame.get(zmq.SRCFD)
    except (zmq.ZMQError, AttributeError):
        return None


def _user_of(frame) -> Optional[bytes]:
    """The CURVE client key (Z85) libzmq attached to a message after its handshake."""
    try:
        user = frame.get("User-Id")
    except (zmq.ZMQError, AttributeError):
        return None
    return user.encode() if isinstance(user, str) else user


def _plan_hash(kind: Kind, payload) -> Optional[bytes]:
    """The map hash a plan names (for one that carries its map, the worker checks the claim), else None."""
    if kind != Kind.PLAN or len(payload) not in (2, 4) or len(payload[1]) != protocol.PLAN_BODY.size:
        return None
    return bytes(payload[1].buffer[:protocol.HASH_SIZE])


def _endpoint(text: str) -> str:
    """tcp://HOST:PORT with PORT 0..65535 (0: a free one), or ipc:// / inproc://."""
    if text.startswith(("ipc://", "inproc://")):
        return text
    host, _, port = text[len("tcp://"):].rpartition(":") if text.startswith("tcp://") else ("", "", "")
    if not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"endpoint must be tcp://HOST:PORT with a port in 0..65535, got {text!r}")
    return text


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description="Cloud path planner (ROS-free).")
    parser.add_argument("--bind", type=_endpoint, default="tcp://0.0.0.0:5555",
                        help="ZeroMQ endpoint to listen on; port 0 picks a free one (default tcp://0.0.0.0:5555)")
    parser.add_argument("--workers", type=bounded_int("--workers", 1, 256), default=2, help="planner threads (default 2)")
    parser.add_argument("--keys-dir", help="server keys dir from offload_planner_cpp.cloud.keys (server.key_secret, clients/)")
    parser.add_argument("--insecure", action="store_true", help="plaintext, no client allowlist (tests, trusted LAN)")
    parser.add_argument("--cache-mib", type=bounded_int("--cache-mib", 0, 1 << 20), default=1024,
                        help="map cache memory cap in MiB, cells plus 1 KiB per map (default 1024)")
    parser.add_argument("--max-message-mib", type=bounded_int("--max-message-mib", 1, 4096), default=64, help="largest accepted message in MiB (default 64)")
    parser.add_argument("--max-queued", type=bounded_int("--max-queued", 1, 1 << 20), default=64, help="requests waiting for a worker before BUSY (64)")
    parser.add_argument("--max-queued-mib", type=bounded_int("--max-queued-mib", 1, 1 << 20), default=256,
                        help="bytes of the requests waiting for a worker, in MiB, before BUSY (default 256)")
    parser.add_argument("--max-wait-s", type=bounded_float("--max-wait-s", 0, 3600, low_open=True), default=1.0,
                        help="longest a request waits for a worker before it gets BUSY instead (default 1.0); "
                             "keep it under the robots' per-attempt timeout")
    parser.add_argument("--rate-per-client", type=bounded_float("--rate-per-client", 0, 1e6), default=50.0,
                        help="plans (and uploads) per second one client (CURVE key; connection if --insecure) may "
                             "have while the server is busy; over it BUSY (default 50; 0: no limit)")
    parser.add_argument("--burst-per-client", type=bounded_int("--burst-per-client", 1, 1000000), default=100,
                        help="token bucket size of --rate-per-client (default 100)")
    parser.add_argument("--stats-admin", action="append", default=[], metavar="KEY_NAME",
                        help="a client key name whose STATS show every client (repeatable); the others see "
                             "their own figures only")
    parser.add_argument("--stats-log-s", type=bounded_float("--stats-log-s", 0, 86400), default=60.0,
                        help="log a line of the STATS counters every this many seconds (default 60; 0: never)")
    parser.add_argument("--log-level", default="INFO", type=str.upper, choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        help="DEBUG, INFO, WARNING or ERROR (default INFO)")
    args = parser.parse_args(argv)
    if args.max_queued_mib < args.max_message_mib:
        parser.error(f"--max-queued-mib ({args.max_queued_mib}) must be >= --max-message-mib ({args.max_message_mib})")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(threadName)s: %(message)s")
    if not args.insecure and not args.keys_dir:
        LOG.error("--keys-dir is required (CURVE is on by default); pass --insecure for plaintext")
        return 2
    config = ServerConfig(bind=args.bind, workers=args.workers, keys_dir=args.keys_dir, insecure=args.insecure,
                          cache_bytes=args.cache_mib << 20, max_message_bytes=args.max_message_mib << 20,
                          max_queued=args.max_queued, max_queued_bytes=args.max_queued_mib << 20,
                          max_wait_s=args.max_wait_s, rate_per_client=args.rate_per_client,
                          burst_per_client=args.burst_per_client, stats_log_s=args.stats_log_s,
                          stats_admins=tuple(args.stats_admin))
    try:
        server = CloudServer(config)
    except (OSError, ValueError, zmq.ZMQError) as error:
        LOG.error("cannot start: %s", error)
        return 2
    except Exception as error:   # never a traceback for bad keys or settings: one line naming the cause
        LOG.error("cannot start: %s: %s", type(error).__name__, error)
        return 2
    # The handlers only set the stop flag; the broker notices within one poll period and exits cleanly.
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: server.stop())
    signal.signal(signal.SIGHUP, lambda *_: server.reload_allowlist())   # as sshd and nginx: re-read keys
    print(f"listening on {server.endpoint}", flush=True)
    server.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
