"""The cloud copy of the planner: a ROS-free ZeroMQ server around the same C++ core as the robot.

    python -m offload_planner_cpp.cloud.server --bind tcp://0.0.0.0:5555 --workers 2 --keys-dir KEYS

A ROUTER frontend faces the robots. The broker thread answers pings itself and hands plan requests to
N worker threads over an inproc ROUTER, one request per idle worker, with a bounded queue in between,
so a slow plan never delays a ping and memory stays bounded. Workers share a bounded LRU map cache
keyed by content hash. The planner releases the GIL, so workers plan in parallel.
"""
import argparse
import collections
import logging
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Optional

import numpy as np
import zmq
import zmq.auth
import zmq.auth.thread

from offload_planner_cpp import PlanStatus, plan_raw
from offload_planner_cpp.cloud import protocol
from offload_planner_cpp.cloud.keys import load_server_keys
from offload_planner_cpp.cloud.map_cache import MapCache
from offload_planner_cpp.cloud.protocol import Kind, ProtocolError, Reply, Status

LOG = logging.getLogger("offload_planner_cpp.cloud.server")
_READY = b"READY"
_BACKEND_POLL_MS = 100   # how often the broker and workers look at the stop flag


@dataclass
class ServerConfig:
    bind: str = "tcp://127.0.0.1:5555"
    workers: int = 2
    keys_dir: Optional[str] = None        # CURVE keys and client allowlist; required unless insecure
    insecure: bool = False                # plaintext, no client authentication
    cache_bytes: int = 1 << 30            # map cache memory cap
    max_message_bytes: int = 64 << 20     # larger messages (or frames) are refused
    max_queued: int = 64                  # plan requests waiting for a worker; more get BUSY
    max_queued_bytes: int = 256 << 20     # and their bytes: a request that would exceed it gets BUSY
    max_frames: int = 8                   # more frames than any valid message: dropped unread


class CloudServer:
    """Serves plan requests until stop(). Construct, then run() in this thread or start() in another."""

    def __init__(self, config: ServerConfig):
        if not config.insecure and not config.keys_dir:
            raise ValueError("a keys dir is required unless --insecure is given")
        if config.workers < 1:
            raise ValueError("at least one worker is needed")
        if config.max_queued < 1 or config.max_queued_bytes < config.max_message_bytes:
            raise ValueError("max queued must be >= 1 and the queued bytes budget at least the max message size")
        self.config = config
        self.cache = MapCache(config.cache_bytes)
        self.max_cells = config.max_message_bytes   # one byte per int8 cell
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._context = zmq.Context()
        self._auth = None
        self._backend_address = f"inproc://workers-{id(self)}"
        self.queued_bytes = 0   # bytes of the requests waiting for a worker (broker thread only)
        self.endpoint = None
        self._thread = None
        self._frontend = self._bind_frontend()

    def _bind_frontend(self) -> zmq.Socket:
        config = self.config
        frontend = self._context.socket(zmq.ROUTER)
        frontend.linger = 0
        frontend.setsockopt(zmq.MAXMSGSIZE, config.max_message_bytes)
        # Incoming messages wait in libzmq until read (per connection); a small high-water mark bounds that
        # memory: at most the queued bytes budget's worth of maximum-size messages, and 2 x max_queued.
        frontend.rcvhwm = self.receive_hwm(config)
        frontend.router_mandatory = False
        if config.insecure:
            LOG.warning("running INSECURE: plaintext and no client authentication (--insecure)")
        else:
            public, secret, allowlist = load_server_keys(config.keys_dir)
            self._auth = zmq.auth.thread.ThreadAuthenticator(self._context, log=LOG)
            self._auth.start()
            self._auth.configure_curve(domain="*", location=str(allowlist))
            frontend.curve_secretkey = secret
            frontend.curve_publickey = public
            frontend.curve_server = True
            LOG.info("CURVE on; client allowlist %s (%d keys)", allowlist, len(list(allowlist.glob("*.key"))))
        try:
            if config.bind.endswith(":0"):
                host = config.bind.rsplit(":", 1)[0]
                port = frontend.bind_to_random_port(host)
                self.endpoint = f"{host}:{port}"
            else:
                frontend.bind(config.bind)
                self.endpoint = frontend.last_endpoint.decode()
        except zmq.ZMQError:
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

    def run(self) -> None:
        backend = self._context.socket(zmq.ROUTER)
        backend.linger = 0
        backend.bind(self._backend_address)
        workers = [threading.Thread(target=self._worker, name=f"planner-{k}", daemon=True)
                   for k in range(self.config.workers)]
        for worker in workers:
            worker.start()
        LOG.info("serving on %s with %d workers, map cache %d MiB, max message %d MiB, queue %d requests / "
                 "%d MiB", self.endpoint, self.config.workers, self.config.cache_bytes >> 20,
                 self.config.max_message_bytes >> 20, self.config.max_queued, self.config.max_queued_bytes >> 20)
        try:
            self._broker(self._frontend, backend)
        finally:
            self._stop.set()
            for worker in workers:
                worker.join(5.0)
            backend.close(0)
            self._frontend.close(0)
            self._close_context()
            LOG.info("stopped; cache hits %d, misses %d, evictions %d", self.cache.hits, self.cache.misses,
                     self.cache.evictions)

    def _close_context(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None
        self._context.term()

    # -- broker --------------------------------------------------------------------------------------

    def _broker(self, frontend: zmq.Socket, backend: zmq.Socket) -> None:
        idle = collections.deque()     # worker identities waiting for a request
        queued = collections.deque()   # (route + payload frames, payload bytes) waiting for a worker
        poller = zmq.Poller()
        poller.register(frontend, zmq.POLLIN)
        poller.register(backend, zmq.POLLIN)
        self._ready.set()
        while not self._stop.is_set():
            events = dict(poller.poll(_BACKEND_POLL_MS))
            if backend in events:
                frames = backend.recv_multipart(copy=False)
                worker, rest = frames[0].bytes, frames[1:]
                if len(rest) > 1:        # a reply: route frames, then the reply itself
                    self._send(frontend, rest)
                idle.append(worker)
            if frontend in events:
                frames = frontend.recv_multipart(copy=False)
                try:
                    self._on_frontend(frontend, frames, queued)
                except Exception:   # a bug must cost one message, never the server
                    LOG.exception("message dropped")
            while idle and queued:
                frames, nbytes = queued.popleft()
                self.queued_bytes -= nbytes
                backend.send_multipart([idle.popleft(), *frames], copy=False)

    def _on_frontend(self, frontend: zmq.Socket, frames, queued) -> None:
        # [identity, (empty delimiter if the client is a REQ socket), envelope, body...]
        if len(frames) > self.config.max_frames + 2:
            LOG.warning("dropped a message of %d frames", len(frames))
            return
        split = 2 if len(frames) > 2 and len(frames[1]) == 0 else 1
        route, payload = frames[:split], frames[split:]
        if not payload:
            return
        request_id = protocol.request_id_of(payload[0].buffer)
        try:
            kind, request_id = protocol.decode_envelope(payload[0].buffer)
            if kind == Kind.PING:
                self._send(frontend, route + protocol.encode_reply(Reply(request_id, Status.OK, "pong")))
                return
            if kind not in (Kind.PLAN, Kind.UPLOAD):
                raise ProtocolError(Status.BAD_REQUEST, f"a client cannot send a {kind.name} message")
            total = sum(len(frame) for frame in payload)
            if total > self.config.max_message_bytes:
                raise ProtocolError(Status.TOO_LARGE, f"message of {total} bytes exceeds "
                                                      f"{self.config.max_message_bytes}")
            if len(queued) >= self.config.max_queued or self.queued_bytes + total > self.config.max_queued_bytes:
                raise ProtocolError(Status.BUSY, f"all {self.config.workers} workers busy and {len(queued)} "
                                                 f"requests ({self.queued_bytes} bytes) queued")
        except ProtocolError as error:
            LOG.warning("request %d refused: %s: %s", request_id, error.status.name, error)
            self._send(frontend, route + protocol.encode_reply(Reply(request_id, error.status, str(error))))
            return
        queued.append((route + payload, total))
        self.queued_bytes += total

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
                frames = socket.recv_multipart(copy=False)
                split = 2 if len(frames) > 2 and len(frames[1]) == 0 else 1
                route, payload = frames[:split], frames[split:]
                socket.send_multipart(route + self.handle(payload), copy=False)
        finally:
            socket.close(0)

    def handle(self, payload) -> list:
        """Reply frames for a PLAN or UPLOAD message (envelope first); never raises."""
        request_id = protocol.request_id_of(payload[0].buffer)
        started = time.perf_counter()
        try:
            kind, request_id = protocol.decode_envelope(payload[0].buffer)
            if kind == Kind.UPLOAD:
                return protocol.encode_reply(self._upload(request_id, payload[1:]))
            return protocol.encode_reply(self._plan(request_id, payload[1:], started))
        except ProtocolError as error:
            LOG.warning("request %d: %s: %s", request_id, error.status.name, error)
            return protocol.encode_reply(Reply(request_id, error.status, str(error)))
        except Exception as error:   # a bug must cost one reply, never the server
            LOG.exception("request %d failed", request_id)
            return protocol.encode_reply(Reply(request_id, Status.SERVER_ERROR, f"server error: {error}"))

    def _store(self, map_hash: bytes, grid: np.ndarray) -> None:
        if self.cache.put(map_hash, grid):
            LOG.info("map %s (%d x %d) cached; %d maps, %.1f MiB", map_hash.hex()[:12], grid.shape[1],
                     grid.shape[0], len(self.cache), self.cache.size_bytes / 2**20)
        else:
            LOG.warning("map %s of %d bytes exceeds the whole cache; served uncached", map_hash.hex()[:12],
                        grid.nbytes)

    def _upload(self, request_id: int, frames) -> Reply:
        if len(frames) != 2:
            raise ProtocolError(Status.BAD_REQUEST, f"upload needs 2 frames after the envelope, got {len(frames)}")
        map_hash, grid = protocol.decode_map(frames[0].buffer, frames[1].buffer, self.max_cells)
        self._store(map_hash, grid)
        return Reply(request_id, Status.OK, map_hash.hex())

    def _plan(self, request_id: int, frames, started: float) -> Reply:
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
            self._store(request.map_hash, grid)
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


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description="Cloud path planner (ROS-free).")
    parser.add_argument("--bind", default="tcp://0.0.0.0:5555",
                        help="ZeroMQ endpoint to listen on; port 0 picks a free one (default tcp://0.0.0.0:5555)")
    parser.add_argument("--workers", type=int, default=2, help="planner threads (default 2)")
    parser.add_argument("--keys-dir", help="server keys dir from offload_planner_cpp.cloud.keys (server.key_secret, clients/)")
    parser.add_argument("--insecure", action="store_true", help="plaintext, no client allowlist (tests, trusted LAN)")
    parser.add_argument("--cache-mib", type=int, default=1024, help="map cache memory cap in MiB (default 1024)")
    parser.add_argument("--max-message-mib", type=int, default=64, help="largest accepted message in MiB (default 64)")
    parser.add_argument("--max-queued", type=int, default=64, help="requests waiting for a worker before BUSY (64)")
    parser.add_argument("--max-queued-mib", type=int, default=256,
                        help="bytes of the requests waiting for a worker, in MiB, before BUSY (default 256)")
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING or ERROR (default INFO)")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(threadName)s: %(message)s")
    if not args.insecure and not args.keys_dir:
        LOG.error("--keys-dir is required (CURVE is on by default); pass --insecure for plaintext")
        return 2
    config = ServerConfig(bind=args.bind, workers=args.workers, keys_dir=args.keys_dir, insecure=args.insecure,
                          cache_bytes=args.cache_mib << 20, max_message_bytes=args.max_message_mib << 20,
                          max_queued=args.max_queued, max_queued_bytes=args.max_queued_mib << 20)
    try:
        server = CloudServer(config)
    except (OSError, ValueError, zmq.ZMQError) as error:
        LOG.error("cannot start: %s", error)
        return 2
    # The handlers only set the stop flag; the broker notices within one poll period and exits cleanly.
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: server.stop())
    print(f"listening on {server.endpoint}", flush=True)
    server.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
