"""The fleet learner's socket loop and trainer thread.

One ROUTER socket (CURVE with auth.py's allowlist, like the planner server; plaintext only with insecure) answers
PING, STATS and the fleet kinds: ROWS into the pool (a resent batch, same bytes from the same key, is answered as
before and not written twice), MODEL_QUERY from the store's state (re-read when an operator changed it), MODEL_FETCH
from the store's files. A trainer thread runs a training round every `train_every_rows` new rows or every
`train_every_s` seconds with new rows, whichever comes first. libzmq bounds each frame (MAXMSGSIZE, the largest
ROWS message) and the messages waiting per connection (receive high-water mark)."""
import hashlib
import logging
import os
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Optional

import zmq

from offload_cloud import protocol, protocol_fleet
from offload_cloud.auth import RateLimitedLog, curve_server, user_of
from offload_cloud.frontend import bind
from offload_cloud.metrics import MetricsEndpoint
from offload_cloud.learner.metrics import LearnerCollector
from offload_cloud.learner.pool import ExperiencePool, PoolLimits
from offload_cloud.learner.store import ModelStore
from offload_cloud.learner.training import TrainingConfig, training_round
from offload_cloud.protocol import Kind, ProtocolError, Reply, Status

LOG = logging.getLogger("offload_cloud.learner")
INSECURE_ROBOT = "insecure"   # every robot's name on a plaintext learner
_RESENDS_KEPT = 4


@dataclass
class LearnerConfig:
    bind: str = "tcp://127.0.0.1:0"
    store: str = "fleet-store"
    pool: str = ""                    # default STORE/pool
    keys_dir: Optional[str] = None
    insecure: bool = False
    seed_bag: Optional[str] = None
    train_every_rows: int = 200
    train_every_s: float = 300.0
    limits: PoolLimits = field(default_factory=PoolLimits)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    metrics_bind: Optional[str] = None    # HOST:PORT of the Prometheus endpoint (GET /metrics); None: off


class FleetLearner:
    def __init__(self, config: LearnerConfig):
        if not config.insecure and not config.keys_dir:
            raise ValueError("a keys dir is required unless insecure is set")
        self.config = config
        self.store = ModelStore(config.store)
        self.pool = ExperiencePool(config.pool or os.path.join(config.store, "pool"), config.limits)
        self.rounds = 0
        self.round_errors = 0
        self._new_rows = 0
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._resends = {}
        self._threads = []
        self._context = zmq.Context()
        self._auth = None
        self._log_limited = RateLimitedLog(LOG)
        self.endpoint = None
        self.metrics = None   # the Prometheus endpoint, when config.metrics_bind

    # --- life ------------------------------------------------------------------------------------------------
    def start(self) -> str:
        if self.config.seed_bag and self.pool.add_seed_bag(self.config.seed_bag):
            LOG.info("seeded the pool with %s", self.config.seed_bag)
            self._new_rows += self.config.train_every_rows
        if self.config.metrics_bind:   # first: a taken port fails the start before the robots' socket opens
            self.metrics = MetricsEndpoint(self.config.metrics_bind, LearnerCollector(self.stats))
        socket = self._context.socket(zmq.ROUTER)
        socket.linger = 0
        socket.setsockopt(zmq.MAXMSGSIZE, protocol.MAX_ROWS_BYTES + 4096)
        socket.rcvhwm = 8
        try:
            if not self.config.insecure:
                self._auth = curve_server(self._context, socket, self.config.keys_dir, self._log_limited)
            self.endpoint = bind(socket, self.config.bind)
        except BaseException:   # bad keys, a taken port: nothing of this start stays open
            socket.close(0)
            if self._auth is not None:
                self._auth.stop()
            if self.metrics is not None:
                self.metrics.close()
            raise
        self._socket = socket
        for target in (self._serve, self._train):
            thread = threading.Thread(target=target, daemon=True, name=f"learner-{target.__name__}")
            thread.start()
            self._threads.append(thread)
        LOG.info("fleet learner listening on %s, store %s", self.endpoint, self.config.store)
        return self.endpoint

    def reload_keys(self) -> None:
        if self._auth is not None:
            self._auth.reload()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        for thread in self._threads:
            thread.join(timeout=60)
        if self.metrics is not None:
            self.metrics.close()
        self.pool.close()
        if self._auth is not None:
            self._auth.stop()
        self._context.term()

    # --- serving ---------------------------------------------------------------------------------------------
    def _serve(self) -> None:
        socket = self._socket
        try:
            while not self._stop.is_set():
                if not socket.poll(100, zmq.POLLIN):
                    continue
                frames = socket.recv_multipart(copy=False)
                if len(frames) < 2:
                    continue
                reply = self._answer(self._robot(frames[1]), frames[1:])
                socket.send_multipart([frames[0]] + reply, copy=False)
        finally:
            socket.close(0)

    def _robot(self, frame) -> str:
        if self._auth is None:
            return INSECURE_ROBOT
        key = user_of(frame)
        return self._auth.names.get(key, key.decode() if key else "?")

    def _answer(self, robot: str, frames) -> list:
        request_id = protocol.request_id_of(frames[0])
        try:
            kind, request_id = protocol.decode_envelope(frames[0])
            body = [frame.buffer for frame in frames[1:]]
            if kind == Kind.PING:
                return protocol.encode_reply(Reply(request_id, Status.OK))
            if kind == Kind.STATS:
                return protocol.encode_json_reply(request_id, self.stats(robot))
            if kind == Kind.ROWS:
                return self._rows(robot, request_id, body)
            if kind in (Kind.MODEL_QUERY, Kind.MODEL_FETCH):
                version, rolled_back = protocol_fleet.decode_model_request(kind, body)
                if kind == Kind.MODEL_QUERY:
                    answer = self.store.version_for(robot, version, rolled_back)
                    data = self.store.get(answer) if answer else b""
                    return protocol.encode_json_reply(request_id, {"version": answer, "bytes": len(data or b"")})
                data = self.store.get(version)
                if data is None:
                    raise ProtocolError(Status.BAD_REQUEST, f"no model version {version} on this learner")
                return protocol.encode_blob_reply(request_id, data)
            raise ProtocolError(Status.BAD_REQUEST, f"the fleet learner does not answer {kind.name}")
        except ProtocolError as error:
            return protocol.encode_reply(Reply(request_id, error.status, str(error)))
        except Exception as error:   # never let one request end the service
            LOG.exception("request from %s failed", robot)
            return protocol.encode_reply(Reply(request_id, Status.SERVER_ERROR, f"{type(error).__name__}: {error}"))

    def _rows(self, robot: str, request_id: int, body) -> list:
        digest = hashlib.sha256(b"".join(bytes(f) for f in body)).digest()
        seen = self._resends.setdefault(robot, OrderedDict())
        if digest in seen:   # the Lazy Pirate resent a batch whose answer was lost: the same answer, no new rows
            return protocol.encode_json_reply(request_id, seen[digest])
        definitions, md5, rows = protocol_fleet.decode_rows(body)
        busy, accepted, refused = self.pool.add(robot, definitions, md5, rows)
        if busy:
            self._log_limited.log(logging.WARNING, ("busy", robot), "BUSY to %s: %s", robot, busy)
            return protocol.encode_reply(Reply(request_id, Status.BUSY, busy))
        answer = {"accepted": accepted, "refused": refused}
        seen[digest] = answer
        while len(seen) > _RESENDS_KEPT:
            seen.popitem(last=False)
        if refused:
            self._log_limited.log(logging.WARNING, ("refused", robot), "refused %d of %d rows from %s", refused,
                                  len(rows), robot)
        self._new_rows += accepted
        if self._new_rows >= self.config.train_every_rows:
            self._wake.set()
        return protocol.encode_json_reply(request_id, answer)

    def stats(self, robot: Optional[str] = None) -> dict:
        """The counters STATS answers with and the metrics endpoint serves (from its own thread: list() copies the
        robots while the service thread may add one)."""
        keys = {name: counts.to_dict() for name, counts in list(self.pool.counts.items())}
        by_robot, limits = self.pool.disk_bytes_by_robot(), self.config.limits
        return {"robots": keys, "pool_bytes": sum(by_robot.values()), "pool_bytes_by_robot": by_robot,
                "pool_budget_bytes": limits.total_bytes, "robot_budget_bytes": limits.robot_bytes,
                "evicted_bags": self.pool.evicted_bags, "evicted_bytes": self.pool.evicted_bytes, "rounds": self.rounds,
                "round_errors": self.round_errors, "new_rows": self._new_rows, "store": self.store.summary()}

    # --- training --------------------------------------------------------------------------------------------
    def _train(self) -> None:
        last = time.monotonic()
        while not self._stop.is_set():
            self._wake.wait(timeout=min(1.0, self.config.train_every_s))
            self._wake.clear()
            due = self._new_rows >= self.config.train_every_rows or \
                (self._new_rows > 0 and time.monotonic() - last >= self.config.train_every_s)
            if self._stop.is_set() or not due:
                continue
            self._new_rows = 0
            last = time.monotonic()
            self.train_once()

    def train_once(self) -> Optional[dict]:
        try:
            entry = training_round(self.pool, self.store, self.config.training)
        except Exception:
            self.round_errors += 1
            LOG.exception("training round failed")
            return None
        self.rounds += entry is not None
        return entry
