"""The cloud copy of the planner: a ROS-free ZeroMQ server around the same C++ core as the robot.

    python -m offload_cloud --bind tcp://0.0.0.0:5555 --workers 2 --keys-dir KEYS

A ROUTER frontend faces the robots. The broker thread answers pings and STATS itself and hands plan
requests to N worker threads over an inproc ROUTER, one request per idle worker, with a bounded queue in
between, so a slow plan never delays a ping and memory stays bounded. Workers share a bounded LRU map
cache keyed by content hash (the heaviest client's least recently used map goes first). The planner
releases the GIL, so workers plan in parallel. The broker drops queued requests of clients that
disconnected (a Lazy Pirate client that gave up), uploads a map only once when many robots send it at the
same time, and reloads the CURVE allowlist on SIGHUP.

This module is the broker and the workers; the rest by job: admission.py (who may wait for a worker: fair
share, rate limits), connection_guard.py (bounds on what connections hold undelivered), auth.py (CURVE
allowlist), server_cli.py (the command line). A summary line of the STATS counters is logged every
--stats-log-s; with --metrics-bind the same counters are served to Prometheus (metrics_server.py).
"""
import collections
import logging
import threading
import time
from typing import Optional

import zmq
from zmq.utils.monitor import parse_monitor_message

from offload_cloud import connection_cap, protocol
from offload_cloud.admission import Admission, AdmissionConfig, Client
from offload_cloud.auth import RateLimitedLog, user_of
from offload_cloud.connection_guard import GUARD_SLACK_BYTES, STALE, Connection, ConnectionGuard
from offload_cloud.frontend import monitor_socket, open_frontend
from offload_cloud.histogram import Histogram
from offload_cloud.map_cache import MapCache
from offload_cloud.metrics_server import open_endpoint
from offload_cloud.planning import Planning
from offload_cloud.protocol import Kind, ProtocolError, Reply, Status
from offload_cloud.request_queue import Request, RequestQueue
from offload_cloud.server_config import ServerConfig
from offload_cloud.stats import count_cache_use, serving_line, server_stats, stats_line
from offload_cloud.tcp_socket import ActivityWatch, peer_address, source_fd
from offload_cloud.zmq_frames import readable, recv_frames, send_frames, send_or_drop

LOG = logging.getLogger("offload_cloud.server")
_READY = b"READY"
_STATUS_NAMES = {bytes([status]): status.name for status in Status}   # a lookup, not an enum call, per reply
_BACKEND_POLL_MS = 25    # how often the broker and workers look at the stop flag and the connection guard
# Every connection libzmq accepts ends with EVENT_DISCONNECTED (EVENT_CLOSED is the listener's own descriptor).
_MONITORED = (zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
              | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_AUTH)
_HANDSHAKE_REFUSALS = {zmq.EVENT_HANDSHAKE_FAILED_AUTH: "unknown_key"}   # else "handshake_failed"


class CloudServer:
    """Serves plan requests until stop(). Construct, then run() in this thread or start() in another."""

    def __init__(self, config: ServerConfig):
        config.check()
        self.config = config
        self.descriptor_limit = connection_cap.raise_descriptor_limit()   # a systemd unit starts at 1024
        self.cache = MapCache(config.cache_bytes)
        self.max_cells = config.max_message_bytes   # one byte per int8 cell
        self.planning = Planning(self.cache, self.max_cells, lambda *args: self._log_limited.log(*args))
        # Bytes a connection may receive beyond its last delivered message: the unread messages libzmq
        # may hold for it (receive HWM), one more being received, and framing.
        self.connection_limit_bytes = (config.receive_hwm + 1) * config.max_message_bytes + GUARD_SLACK_BYTES
        # The broker hands its counters to a metrics scrape; no endpoint (None) unless --metrics-bind. First: a
        # taken port fails here, before anything else is open.
        self.snapshots, self.metrics = open_endpoint(config.metrics_bind)
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._ready = threading.Event()
        self._context = zmq.Context(io_threads=config.io_threads)
        self._auth = None
        self._backend_address = f"inproc://workers-{id(self)}"
        self._log_limited = RateLimitedLog(LOG)
        self.admission = Admission(AdmissionConfig(config.workers, config.max_queued, config.max_queued_bytes,
                                                   config.max_wait_s, config.rate_per_client,
                                                   config.burst_per_client))
        # Cuts are logged at most every 5 s per kind: one key can make many.
        self.guard = ConnectionGuard(self.connection_limit_bytes, config.max_pending_bytes,
                                     config.max_pending_bytes_per_key,
                                     lambda message, *args: self._log_limited.log(logging.WARNING, ("guard", message),
                                                                                  message, *args),
                                     key_connections=config.max_connections_per_key,
                                     first_limit_bytes=config.max_first_message_bytes + GUARD_SLACK_BYTES,
                                     unidentified_limit_bytes=config.max_pending_unidentified_bytes,
                                     watch=ActivityWatch(), receive_hwm=config.receive_hwm)
        self.abandoned_dropped = 0      # queued requests dropped because their client went away
        self.stale_dropped = 0          # messages of connections that had closed when the broker read them
        self.service_s = 0.0            # moving average of a worker's time per request (broker thread only)
        self.started = time.monotonic()
        self.counts = collections.Counter()     # requests, pings, stats (broker thread only)
        self.refused = collections.Counter()    # connections and messages refused without a reply, by reason
        self.plan_seconds, self.queue_seconds = Histogram(), Histogram()   # dispatch to reply; arrival to dispatch
        self.replies = collections.Counter()    # status name -> replies to plans, uploads and bad messages
        self._key_names = {}                    # Z85 public key -> allowlist name (file stem)
        self._idle = ()                         # the broker's idle workers (for the rate limit)
        self.in_flight = {}                    # the broker's requests being planned
        self._worker_client = threading.local()  # name of the client whose message a worker handles
        self.endpoint = None
        self._thread = None
        self._frontend = self._bind_frontend()
        self._monitor = monitor_socket(self._context, self._frontend, _MONITORED)
        self.guard.max_connections = connection_cap.cap_for(   # each worker holds a socket too
            self.descriptor_limit, connection_cap.descriptors_open() + 2 * config.workers, config.max_connections,
            LOG.warning)

    @property
    def queued_bytes(self) -> int:
        """Bytes of the requests waiting for a worker or parked (broker thread only)."""
        return self.admission.queued_bytes

    def _bind_frontend(self) -> zmq.Socket:
        try:
            frontend, self._auth, self.endpoint = open_frontend(self._context, self.config, self._log_limited, LOG)
        except BaseException:
            self._close_context()
            raise
        if self._auth is not None:
            self._key_names = self._auth.names
        return frontend

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
        LOG.info("%s", serving_line(self))
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
            self.guard.watch.close()
            self._close_context()
            LOG.info("stopped; cache hits %d, misses %d, evictions %d; %s", self.cache.hits, self.cache.misses,
                     self.cache.evictions, self.stats_line(self.stats()))

    def _close_context(self) -> None:
        """Closes what the sockets share: the authenticator, the context, the metrics endpoint."""
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        self._context.term()
        if self.metrics is not None:
            self.metrics.close()

    def _do_reload(self) -> None:
        if self._auth is None:
            LOG.warning("SIGHUP: no allowlist to reload (--insecure)")
        elif self._auth.reload():
            self._key_names = self._auth.names
            self.guard.cut_revoked(self._auth.allowlist)

    def _broker(self, frontend: zmq.Socket, backend: zmq.Socket) -> None:
        idle = collections.deque()      # worker identities waiting for a request
        queue = RequestQueue(self.admission, self.cache)
        in_flight = {}                  # worker identity -> Request being planned
        poller = zmq.Poller()
        poller.register(self._monitor, zmq.POLLIN)
        poller.register(frontend, zmq.POLLIN)
        poller.register(backend, zmq.POLLIN)
        poller.register(self.guard.watch.fileno(), zmq.POLLIN)   # bytes for a connection yet to say whose it is
        guard = self.config.bind.startswith("tcp://")
        checked_at = logged_at = time.monotonic()
        check_period = _BACKEND_POLL_MS / 1e3
        self._idle, self.in_flight = idle, in_flight
        self._ready.set()
        while not self._stop.is_set():
            events = dict(poller.poll(_BACKEND_POLL_MS))
            if self._reload.is_set():
                self._reload.clear()
                self._do_reload()
            if self.snapshots.wanted:
                self.snapshots.serve(self.stats)
            while readable(self._monitor):   # first: a request of a closed connection must not be queued
                self._on_monitor(parse_monitor_message(self._monitor.recv_multipart()), queue)
            if self.guard.ledger.unsettled and not readable(frontend):
                self.guard.frontend_drained()   # no message of a connection closed before now is left
            if backend in events:
                frames = recv_frames(backend)
                worker, rest = frames[0].bytes, frames[1:]
                done, dispatched_at = in_flight.pop(worker, (None, 0.0))
                if len(rest) > 1:        # a reply: route frames, then the reply itself
                    status = self._reply(frontend, rest, done.client if done is not None else None)
                    if done is not None:
                        count_cache_use(done, status)
                if done is not None:
                    elapsed = time.monotonic() - dispatched_at
                    self.service_s = 0.7 * self.service_s + 0.3 * elapsed
                    if done.kind == Kind.PLAN:
                        self.plan_seconds.observe(elapsed)
                    if done.uploads is not None:
                        queue.release(done.uploads)
                idle.append(worker)
            if frontend in events:
                frames = recv_frames(frontend)
                try:
                    self._on_frontend(frontend, frames, queue)
                except Exception:   # a bug must cost one message, never the server
                    LOG.exception("message dropped")
            now = time.monotonic()
            if self.config.stats_log_s and now - logged_at >= self.config.stats_log_s:
                logged_at = now
                LOG.info("%s", self.stats_line(self.stats()))
            if guard and now - checked_at >= check_period:
                checked_at = now
                self.guard.check(lambda: not readable(frontend))
                # Every 25 ms, or less often when there are so many connections that a check takes over 1/4 of that
                # (about 2 us a connection): the guard never takes more than a fifth of the broker.
                check_period = max(_BACKEND_POLL_MS / 1e3, 4 * (time.monotonic() - now))
            elif guard:
                self.guard.look_between_checks(lambda: not readable(frontend))
            # Last, right before the poll: a woken worker finds the GIL free, not held by the broker's bookkeeping.
            while idle and queue.queued:
                request = queue.pop()
                now = time.monotonic()
                self.queue_seconds.observe(now - request.arrived)
                if now - request.arrived > self.config.max_wait_s:
                    self.admission.busy["waited"] += 1
                    # Its client has (nearly) given up: a quick BUSY lets it plan locally now, and the
                    # worker goes to a request that can still be answered in time.
                    self._refuse(frontend, request.frames[:request.route_frames], request.request_id,
                                 ProtocolError(Status.BUSY, f"waited {now - request.arrived:.2f} s for a worker, "
                                                            f"over --max-wait-s {self.config.max_wait_s:g}"),
                                 request.client)
                    if request.uploads is not None:
                        queue.release(request.uploads)
                    continue
                worker = idle.popleft()
                in_flight[worker] = (request, now)
                # The client's name goes first: the worker stores an uploaded map as that client's.
                send_frames(backend, [worker, request.client.name.encode(), *request.frames])

    def _on_monitor(self, event: dict, queue: RequestQueue) -> None:
        kind, fd = event["event"], int(event["value"])
        if kind == zmq.EVENT_ACCEPTED:
            self.guard.accepted(fd, peer_address(fd))
        elif kind == zmq.EVENT_DISCONNECTED:
            self.guard.closed(fd)
            self._drop_requests_of(fd, queue)
        else:
            self.refused[_HANDSHAKE_REFUSALS.get(kind, "handshake_failed")] += 1
            self._log_limited.log(logging.WARNING, ("handshake", kind),
                                  "refused a connection: handshake failed (%s, code %s): a plaintext client, wrong "
                                  "server key or not a ZeroMQ peer", zmq.Event(kind).name, fd)

    def _drop_requests_of(self, fd: int, queue: RequestQueue) -> None:
        dropped = queue.drop_connection(fd)
        if dropped:
            self.abandoned_dropped += len(dropped)
            LOG.info("dropped %d waiting requests of a closed connection", len(dropped))

    def _on_frontend(self, frontend: zmq.Socket, frames, queue: RequestQueue) -> None:
        # [identity, (empty delimiter if the client is a REQ socket), envelope, body...]
        fd = source_fd(frames[-1])
        connection = self.guard.delivered(fd, frames[0].bytes)
        if connection is STALE:   # its connection closed: nobody to answer, and no queue place for nobody
            self.stale_dropped += 1
            return
        user = None
        if self._auth is not None:
            user = user_of(frames[-1])
            if user is None or user not in self._auth.allowlist:   # revoked since its handshake
                self.refused["revoked_key"] += 1
                self._log_limited.log(logging.WARNING, ("revoked", user),
                                      "dropped a message from revoked client key %s", (user or b"?").decode())
                if fd is not None:
                    self.guard.forget(fd)
                return
            if connection is not None:
                self.guard.identify(fd, connection, user)
        if len(frames) > self.config.max_frames + 2:
            self.refused["too_many_frames"] += 1
            self._log_limited.log(logging.WARNING, "frames", "dropped a message of %d frames", len(frames))
            return
        split = 2 if len(frames) > 2 and len(frames[1]) == 0 else 1
        route, payload = frames[:split], frames[split:]
        if not payload:
            return
        request_id = None
        client = self.admission.client(self._client_name(user, fd, connection))
        try:
            kind, request_id = protocol.decode_envelope(payload[0].buffer)
            if kind == Kind.PING:
                self.counts["pings"] += 1
                send_or_drop(frontend, route + protocol.encode_reply(Reply(request_id, Status.OK, "pong")), LOG)
                return
            if kind == Kind.STATS:
                self.counts["stats"] += 1
                self.admission.charge_stats(client)
                send_or_drop(frontend, route + protocol.encode_stats_reply(request_id, self.stats(client.name)), LOG)
                return
            if kind not in (Kind.PLAN, Kind.UPLOAD):
                raise ProtocolError(Status.BAD_REQUEST, f"a client cannot send a {kind.name} message")
            self.counts["requests"] += 1
            client.requests += 1
            total = sum(len(frame) for frame in payload)
            if total > self.config.max_message_bytes:
                raise ProtocolError(Status.TOO_LARGE, f"message of {total} bytes exceeds the server's "
                                                      f"--max-message-mib ({self.config.max_message_bytes} bytes)")

            def displace(victim, why: str) -> None:
                queue.remove(victim)
                self._refuse(frontend, victim.frames[:victim.route_frames], victim.request_id,
                             ProtocolError(Status.BUSY, why), victim.client)
            self.admission.admit(client, total, queue.queued, self.service_s, bool(self._idle), displace)
        except ProtocolError as error:
            request_id = protocol.request_id_of(payload[0].buffer) if request_id is None else request_id
            self._refuse(frontend, route, request_id, error, client)
            return
        request = Request(route + payload, total, fd, request_id, len(route), time.monotonic(), client=client,
                           kind=kind)
        queue.add(request, payload)

    def _refuse(self, frontend: zmq.Socket, route, request_id: int, error: ProtocolError,
                client: Optional[Client]) -> None:
        self._log_limited.log(logging.WARNING, ("refused", error.status),
                              "request %d refused: %s: %s", request_id, error.status.name, error)
        self._reply(frontend, route + protocol.encode_reply(Reply(request_id, error.status, str(error))), client)

    def _reply(self, frontend: zmq.Socket, frames, client: Optional[Client]) -> str:
        """Sends a reply to a plan, an upload or a bad message, counted by status for the server and client;
        returns the status name."""
        # frames: route, envelope, body (its first byte the status), message, path
        status = _STATUS_NAMES.get(bytes(frames[-3])[:1], "?") if len(frames) >= 3 else "?"
        self.replies[status] += 1
        if client is not None:
            client.replies[status] += 1
        send_or_drop(frontend, frames, LOG)
        return status

    def _client_name(self, user: Optional[bytes], fd: Optional[int], connection: Optional[Connection]) -> str:
        """The client a message is charged to: its key's allowlist name, else (--insecure) its connection."""
        if user is not None:
            return self._key_names.get(user) or f"key:{user.decode(errors='replace')[:8]}"
        return connection.address if connection is not None and connection.address != "?" else \
            (f"connection:{fd}" if fd is not None else "local")

    def stats(self, viewer: Optional[str] = None) -> dict:
        """The counters STATS answers with; a viewer that is neither an admin nor local sees its own only."""
        return server_stats(self, viewer)

    stats_line = staticmethod(stats_line)

    def _worker(self) -> None:
        socket = self._context.socket(zmq.DEALER)
        socket.linger = 0
        socket.connect(self._backend_address)
        socket.rcvtimeo = _BACKEND_POLL_MS   # a blocking receive, not a poll and a receive: one call a request
        socket.send(_READY)
        try:
            while not self._stop.is_set():
                try:
                    client, *frames = recv_frames(socket)
                except zmq.Again:
                    continue
                split = 2 if len(frames) > 2 and len(frames[1]) == 0 else 1
                route, payload = frames[:split], frames[split:]
                self._worker_client.name = client.bytes.decode()
                send_frames(socket, route + self.handle(payload))
        finally:
            socket.close(0)

    def handle(self, payload, client: Optional[str] = None) -> list:
        """Reply frames for a PLAN or UPLOAD message (envelope first) of `client` (default: the one this
        worker thread was handed the message for); never raises."""
        if client is None:
            client = getattr(self._worker_client, "name", "")
        return self.planning.handle(payload, client)

