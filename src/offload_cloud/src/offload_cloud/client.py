"""Robot-side client of the cloud planner: Lazy Pirate request/reply over a DEALER socket.

Each call has a deadline (`timeout_s`). Within it the request is sent up to `retries + 1` times, each
attempt polling for an equal share of the deadline; after an unanswered attempt the socket is closed
with LINGER 0 and reopened, so nothing stale survives and a restarted server is found again. Replies
are matched to the request id and anything else is dropped. When the deadline passes, CloudTimeout is
raised at once so the caller can plan locally.

Health check:
    python -m offload_cloud.client tcp://HOST:5555 --ping --keys-dir ROBOT_KEYS
exits 0 and prints the round trip when the server answers, 1 with the reason otherwise; with --stats
(instead of or besides --ping) it prints the server's counters (STATS) as JSON.
"""
import argparse
import itertools
import json
import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import numpy as np
import zmq

from offload_planner_cpp import inflate
from offload_cloud import protocol
from offload_cloud.keys import load_client_keys
from offload_cloud.reply_check import PathRows, reply_problem
from offload_cloud.protocol import PlanOptions, ProtocolError, Reply, Status
from offload_cloud.zmq_frames import NOBLOCK, recv_frames, send_frames


class CloudTimeout(RuntimeError):
    """The cloud did not answer within the deadline."""


# Largest reply accepted by default: a path of 8 million cells. libzmq drops a connection that sends a
# larger frame (so a lying server cannot make the robot buffer gigabytes); the request then times out.
DEFAULT_MAX_REPLY_BYTES = 64 << 20
_CURVE_FRAME_OVERHEAD_BYTES = 4096   # MAXMSGSIZE counts the encrypted frame: room for the CURVE box
_POLLIN = int(zmq.POLLIN)
# A new socket's first message up to this size (a ping, a plan on a cached map) says whose the connection is
# at once; a larger one (a map) goes after a ping, so its bytes already count against the key's bound.
_TINY_FIRST_MESSAGE_BYTES = 1024


class KnownMaps:
    """Hashes of maps the server has acknowledged, shared by every client of one robot so a map is
    uploaded once. Kept small: only the robot's recent map versions matter."""

    def __init__(self, capacity: int = 8):
        self._hashes = []
        self._capacity = capacity
        self._lock = threading.Lock()

    def add(self, map_hash: bytes) -> None:
        with self._lock:
            if self._hashes and self._hashes[-1] == map_hash:   # the newest already: every plan on one map
                return
            if map_hash in self._hashes:
                self._hashes.remove(map_hash)
            self._hashes.append(map_hash)
            del self._hashes[:-self._capacity]

    def discard(self, map_hash: bytes) -> None:
        with self._lock:
            if map_hash in self._hashes:
                self._hashes.remove(map_hash)

    def __contains__(self, map_hash: bytes) -> bool:
        with self._lock:
            return map_hash in self._hashes


class PlannedGrids:
    """The grid a request was planned on: the robot's map, or for options that inflate it (a robot radius or
    an inflation radius) that map inflated by the planner's own rule, made once per map and options. A reply
    is checked against it: against the raw map, a path through the inflated band passed (#31). Shared by the
    clients of one robot, like KnownMaps; it holds the last `capacity` inflated maps."""

    def __init__(self, capacity: int = 2):
        self._grids = {}
        self._capacity = capacity
        self._lock = threading.Lock()

    def get(self, grid: np.ndarray, map_hash: bytes, options: PlanOptions) -> np.ndarray:
        if not (options.robot_radius_cells > 0 or options.inflation_radius_cells > 0):
            return grid
        key = (map_hash, options.robot_radius_cells, options.inflation_radius_cells, options.inflation_decay,
               options.lethal_threshold, options.unknown_is_obstacle)
        with self._lock:
            inflated = self._grids.pop(key, None)
            if inflated is None:
                inflated = inflate(grid, options.robot_radius_cells, options.inflation_radius_cells,
                                   options.inflation_decay, options.lethal_threshold, options.unknown_is_obstacle)
            self._grids[key] = inflated   # newest last
            while len(self._grids) > self._capacity:
                del self._grids[next(iter(self._grids))]
            return inflated


@dataclass(frozen=True)
class PlanOutcome:
    reply: Reply
    round_trip_s: float    # send of the first attempt to the matched reply, uploads included
    uploaded: bool         # the map travelled with this call


class CloudClient:
    """Not thread safe: one client per thread (they can share `known_maps` and `context`)."""

    def __init__(self, endpoint: str, *, keys_dir: Optional[str] = None, insecure: bool = False,
                 timeout_s: float = 5.0, retries: int = 1, known_maps: Optional[KnownMaps] = None,
                 context: Optional[zmq.Context] = None, max_reply_bytes: int = DEFAULT_MAX_REPLY_BYTES,
                 planned_grids: Optional[PlannedGrids] = None):
        if not insecure and not keys_dir:
            raise ValueError("a keys dir is required unless insecure is set")
        if not timeout_s > 0 or retries < 0:
            raise ValueError("timeout_s must be > 0 and retries >= 0")
        if max_reply_bytes < 1024:
            raise ValueError(f"max_reply_bytes must be >= 1024, got {max_reply_bytes}")
        self.max_reply_bytes = int(max_reply_bytes)
        self.endpoint = endpoint
        self.timeout_s = timeout_s
        self.retries = retries
        self.known_maps = known_maps if known_maps is not None else KnownMaps()
        self.planned_grids = planned_grids if planned_grids is not None else PlannedGrids()
        self._keys = None if insecure else load_client_keys(keys_dir)
        self._own_context = context is None
        self._context = context if context is not None else zmq.Context()
        # Ids start at a random point so a reply meant for an earlier process is never taken as ours.
        self._ids = itertools.count(int.from_bytes(os.urandom(6), "little"))
        self._socket = None
        # Payload bytes this client put on and took off the link (ZMTP framing and CURVE add a few dozen
        # bytes a message), for the robot's per-request link accounting.
        self.bytes_sent = 0
        self.bytes_received = 0

    def _open(self) -> zmq.Socket:
        socket = self._context.socket(zmq.DEALER)
        socket.linger = 0
        socket.setsockopt(zmq.MAXMSGSIZE, self.max_reply_bytes + _CURVE_FRAME_OVERHEAD_BYTES)
        socket.rcvhwm = 4   # replies are read as they come; a flooding server cannot queue more than these
        if self._keys is not None:
            public, secret, server_public = self._keys
            socket.curve_publickey = public
            socket.curve_secretkey = secret
            socket.curve_serverkey = server_public
        socket.connect(self.endpoint)
        return socket

    def _reset(self) -> None:
        if self._socket is not None:
            self._socket.close(0)
            self._socket = None

    def close(self) -> None:
        self._reset()
        if self._own_context:
            self._context.term()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def request(self, build_frames, deadline: Optional[float] = None, decode=protocol.decode_reply):
        """Sends build_frames(request_id) Lazy-Pirate style; returns the matched reply (decode(frames): a Reply,
        or a tuple whose first item is one) or raises CloudTimeout at `deadline` (time.monotonic(); default now +
        timeout_s)."""
        if deadline is None:
            deadline = time.monotonic() + self.timeout_s
        attempts = self.retries + 1
        for attempt in range(attempts):
            remaining_s = deadline - time.monotonic()
            if remaining_s <= 0:
                break
            attempt_deadline = time.monotonic() + remaining_s / (attempts - attempt)
            fresh = self._socket is None
            if fresh:
                self._socket = self._open()
            request_id = next(self._ids) & 0xFFFFFFFFFFFFFFFF
            frames = build_frames(request_id)
            size = 0
            for frame in frames:   # a loop, not sum() over a generator: one call fewer per request
                size += memoryview(frame).nbytes
            try:
                if size > protocol.FIRST_MESSAGE_MAX_BYTES or (fresh and size > _TINY_FIRST_MESSAGE_BYTES):
                    # A ping goes first on a new socket and ahead of a large message, so the connection has
                    # said whose it is before the message arrives (the server cuts a connection whose first
                    # message is larger, and counts a key's bytes from its first message on; libzmq may have
                    # reconnected the socket since); its pong is dropped below as a reply to another request.
                    hello = protocol.encode_ping(next(self._ids) & 0xFFFFFFFFFFFFFFFF)
                    send_frames(self._socket, hello, NOBLOCK)
                    size += sum(len(frame) for frame in hello)
                send_frames(self._socket, frames, NOBLOCK)
            except zmq.Again:
                self._reset()
                continue
            self.bytes_sent += size
            reply = self._await(request_id, attempt_deadline, decode)
            if reply is not None:
                return reply
            self._reset()   # Lazy Pirate: the old socket may hold a dead connection or a stale reply
        raise CloudTimeout(f"no reply from {self.endpoint} within {self.timeout_s:g} s")

    def _await(self, request_id: int, deadline: float, decode=protocol.decode_reply):
        while True:
            wait_ms = int(max(0.0, deadline - time.monotonic()) * 1000) + 1
            if not zmq.zmq_poll([(self._socket, _POLLIN)], wait_ms):   # Socket.poll would build a Poller
                if time.monotonic() >= deadline:
                    return None
                continue
            frames = recv_frames(self._socket)
            self.bytes_received += sum(map(len, frames))   # zmq Frames: len is bytes
            try:
                reply = decode(frames)   # Frames are buffers: no memoryview of each made first
            except ProtocolError:
                continue   # garbage from a confused server: keep waiting for ours
            if (reply[0] if isinstance(reply, tuple) else reply).request_id == request_id:
                return reply
            # a stale reply to an earlier request: dropped

    def ping_reply(self, timeout_s: Optional[float] = None) -> Tuple[Reply, float]:
        """The server's answer to one ping, whatever its status, and the measured round trip in seconds;
        CloudTimeout when unanswered."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        started = time.perf_counter()
        reply = self.request(protocol.encode_ping, deadline)
        return reply, time.perf_counter() - started

    def ping(self, timeout_s: Optional[float] = None) -> float:
        """Round trip of one ping in seconds; CloudTimeout when unanswered, RuntimeError when the answer
        is not a pong."""
        reply, round_trip_s = self.ping_reply(timeout_s)
        if reply.status != Status.OK:
            raise RuntimeError(f"ping answered {reply.status.name}: {reply.message}")
        return round_trip_s

    def stats(self, timeout_s: Optional[float] = None) -> dict:
        """The server's counters (a STATS request); CloudTimeout when unanswered, ProtocolError when the
        answer is an error or not a JSON object."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        return protocol.decode_stats(self.request(protocol.encode_stats, deadline))

    def upload(self, grid: np.ndarray, map_hash: Optional[bytes] = None, timeout_s: Optional[float] = None) -> Reply:
        """Puts `grid` in the server's cache without planning."""
        map_hash = protocol.grid_hash(grid) if map_hash is None else map_hash
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        reply = self.request(lambda request_id: protocol.encode_upload(request_id, grid), deadline)
        if reply.status == Status.OK:
            self.known_maps.add(map_hash)
        return reply

    def plan(self, grid: np.ndarray, start: Sequence[int], goal: Sequence[int],
             options: PlanOptions = PlanOptions(), map_hash: Optional[bytes] = None,
             rows: Optional[PathRows] = None) -> PlanOutcome:
        """Plans on `grid` in the cloud: only the hash travels when the server acknowledged this map,
        else the map goes along; a cache-miss reply makes it upload once and retry, within the deadline. With
        `rows`, a good path's poses are written into it as the reply is checked."""
        map_hash = protocol.grid_hash(grid) if map_hash is None else map_hash
        deadline = time.monotonic() + self.timeout_s
        started = time.perf_counter()
        attach = [map_hash not in self.known_maps]
        sent_map = False
        uploads_left = 2   # after MAP_UNKNOWN; the deadline bounds it too
        while True:
            def build(request_id):
                nonlocal sent_map
                with_map = attach[0]
                # A resend after an unanswered attempt carries only the hash: the server most likely has
                # the map by then (a fleet retrying with 4 MB each was what kept it from answering); if
                # not, its MAP_UNKNOWN brings the map once more.
                attach[0] = False
                sent_map = sent_map or with_map
                return protocol.encode_plan(request_id, map_hash, start, goal, options, grid if with_map else None)
            reply = self.request(build, deadline)
            if reply.status == Status.MAP_UNKNOWN and uploads_left > 0:
                self.known_maps.discard(map_hash)
                attach[0] = True
                uploads_left -= 1
                continue
            upload = sent_map
            round_trip_s = time.perf_counter() - started
            try:   # only a path needs the grid it was planned on
                planned = self.planned_grids.get(grid, map_hash, options) if reply.status == Status.OK else grid
                why = reply_problem(reply, planned, start, goal, options, round_trip_s, rows)
            except ValueError as error:   # options the planner itself refuses, answered with a path
                why = f"a path for options the planner refuses ({error})"
            if why:   # a confused or hostile server: never hand its answer on as a plan
                reply = Reply(reply.request_id, Status.SERVER_ERROR, f"invalid reply from {self.endpoint}: {why}")
            elif protocol.is_planner_status(reply.status):   # it planned, so it holds the map
                self.known_maps.add(map_hash)
            return PlanOutcome(reply, round_trip_s, upload)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="Cloud planner client: health check.")
    parser.add_argument("endpoint", help="server endpoint, e.g. tcp://cloud.example.org:5555")
    parser.add_argument("--ping", action="store_true", help="ping the server and print the round trip")
    parser.add_argument("--stats", action="store_true", help="print the server's counters (STATS) as JSON")
    parser.add_argument("--count", type=int, default=1, help="pings to send (default 1)")
    parser.add_argument("--keys-dir", help="this robot's keys dir (client.key_secret, server.key)")
    parser.add_argument("--insecure", action="store_true", help="plaintext, for a server run with --insecure")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for each answer (default 5)")
    args = parser.parse_args(argv)
    if not args.ping and not args.stats:
        parser.error("nothing to do: pass --ping or --stats")
    if not args.insecure and not args.keys_dir:
        print("error: pass --keys-dir (the server uses CURVE by default) or --insecure", file=sys.stderr)
        return 2
    try:
        client = CloudClient(args.endpoint, keys_dir=args.keys_dir, insecure=args.insecure,
                             timeout_s=args.timeout, retries=0)
    except (OSError, ValueError, zmq.ZMQError) as error:   # KeyFileError names the file
        print(f"error: {error}", file=sys.stderr)
        return 2
    unanswered = (f"error: no answer from {args.endpoint} within {args.timeout:g} s: server down, wrong endpoint, "
                  f"blocked port, or this client's key is not on the server's allowlist")
    calls = [(client.ping, lambda rtt: f"pong from {args.endpoint}: round trip {rtt * 1e3:.3f} ms")] * \
        (max(1, args.count) if args.ping else 0)
    if args.stats:
        calls.append((client.stats, lambda stats: json.dumps(stats, indent=2, sort_keys=True)))
    with client:
        for call, show in calls:
            try:
                print(show(call()))
            except CloudTimeout:
                print(unanswered, file=sys.stderr)
                return 1
            except (RuntimeError, ProtocolError, zmq.ZMQError) as error:
                print(f"error: {error}", file=sys.stderr)
                return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
