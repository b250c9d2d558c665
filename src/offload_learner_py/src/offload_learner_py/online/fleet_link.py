"""The robot's link to the fleet learner (no ROS): its rows out, its models in, on one background thread.

Rows. Each finished request's decision and outcome (the node's published messages) are `enqueue`d into a
bounded buffer: the request's thread only appends (a full buffer drops its oldest row and counts it). The
link's thread encodes them (`encode(row) -> (decision bytes, outcome bytes)`, genpy's serialize in the node)
and sends batches of at most `batch_rows` with FleetClient.send_rows. A batch the learner cannot take now
(CloudTimeout: unreachable; FleetBusy: over its rate or disk) goes back to the front of the buffer and is sent
when the link returns, with a backoff from 1 s doubling up to `period_s`; what the bound pushes out meanwhile is
counted as dropped. A batch refused as malformed (FleetError) and rows the learner refused are counted too.

Models. At start and every `period_s` (and at once after a rollback) the thread asks current_version (telling
the learner this robot's rolled-back versions, which it never offers again), fetches a version it does not run,
loads it weights-only with core/model_file.load_model (the SHA-256 against the version, no pickle, shapes and
values checked) and hands the loaded model to `on_model(version, fast_decision)`, which swaps it in between
requests. A file that fails (FleetError: the hash; ModelFileError: anything else) is one error line; the model
in use stays, and the version is not fetched again until the learner offers another.

Nothing here runs on a request's path except `enqueue`; nothing blocks the node: `close` waits at most
`close_timeout_s` for a last send."""
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, List, Optional, Sequence, Tuple

from offload_learner_py.core.model_file import ModelFileError, load_model

LOG = logging.getLogger("offload_learner_py.online.fleet_link")
Row = Tuple[bytes, bytes]


@dataclass(frozen=True)
class FleetConfig:
    endpoint: str = ""
    """the fleet learner (`offload-cloud-learner`), e.g. tcp://cloud:5557; "": no fleet, the robot learns alone."""
    keys_dir: str = ""
    """the robot's CURVE keys for the learner (client.key_secret, server.key); required unless insecure."""
    insecure: bool = False
    period_s: float = 30.0
    """how often the robot asks for the current model version (also the longest wait between send attempts)."""
    timeout_s: float = 5.0
    """deadline of one call to the learner."""
    buffer_rows: int = 5000
    """rows kept while the learner is unreachable; beyond it the oldest are dropped and counted."""
    batch_rows: int = 256
    """rows per send (at most the wire's 512)."""
    send_every_s: float = 1.0
    """a partial batch waits at most this long."""
    warmup_requests: int = 60
    """the robot's first requests probe both sides (a DQN learning alone warms up as long: learning_starts), so
    the fleet learner has its rows to train and judge on; less the requests a learner checkpoint given as ~model
    learned from (the robot's learning run, which measured both sides); 0: probes at the probe rate only."""

    def __post_init__(self):
        if self.period_s <= 0 or self.timeout_s <= 0 or self.send_every_s <= 0:
            raise ValueError("~fleet_period_s, ~fleet_timeout_s and ~fleet_send_every_s must be positive")
        if not 0 <= self.warmup_requests <= 100000:
            raise ValueError(f"~fleet_warmup_requests must be in [0, 100000], got {self.warmup_requests}")
        if not 1 <= self.batch_rows <= 512:
            raise ValueError(f"~fleet_batch_rows must be in [1, 512], got {self.batch_rows}")
        if self.buffer_rows < self.batch_rows:
            raise ValueError(f"~fleet_buffer_rows must be at least ~fleet_batch_rows, got {self.buffer_rows}")
        if self.endpoint and not (self.keys_dir or self.insecure):
            raise ValueError("~fleet_endpoint needs ~fleet_keys_dir (or ~fleet_insecure)")

    @property
    def enabled(self) -> bool:
        return bool(self.endpoint)


class RowBuffer:
    """A bounded FIFO of rows; a full buffer drops its oldest row and counts it. Thread-safe."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._rows: deque = deque()
        self._lock = threading.Lock()
        self.dropped = 0

    def __len__(self) -> int:
        return len(self._rows)

    def put(self, row: Any) -> None:
        with self._lock:
            self._rows.append(row)
            while len(self._rows) > self.capacity:
                self._rows.popleft()
                self.dropped += 1

    def take(self, n: int) -> List[Any]:
        with self._lock:
            return [self._rows.popleft() for _ in range(min(n, len(self._rows)))]

    def put_back(self, rows: Sequence[Any]) -> None:
        """Rows a send could not deliver, back at the front (oldest first); the bound still holds."""
        with self._lock:
            self._rows.extendleft(reversed(rows))
            while len(self._rows) > self.capacity:
                self._rows.popleft()
                self.dropped += 1


class FleetLink:
    """`client_factory()` -> a FleetClient (made on the link's thread: one client per thread); `definitions`,
    `md5`: the two message types' definitions for send_rows; `errors`: the exception classes (timeout, busy,
    refused) FleetClient raises; `current()` -> the version in use; `rolled_back()` -> versions never to run."""

    def __init__(self, config: FleetConfig, client_factory: Callable[[], Any], definitions: dict, md5: dict,
                 errors: Tuple[type, type, type], on_model: Callable, current: Callable[[], str],
                 rolled_back: Callable[[], Sequence[str]], encode: Callable[[Any], Row] = lambda row: row,
                 log: logging.Logger = LOG, clock: Callable[[], float] = time.monotonic,
                 close_timeout_s: float = 2.0):
        self.config, self.log, self.clock = config, log, clock
        self.client_factory, self.definitions, self.md5 = client_factory, definitions, md5
        self.timeout_error, self.busy_error, self.refused_error = errors
        self.on_model, self.current, self.rolled_back, self.encode = on_model, current, rolled_back, encode
        self.close_timeout_s = close_timeout_s
        self.buffer = RowBuffer(config.buffer_rows)
        self.sent = self.refused = self.unencodable = self.send_failures = 0
        self.models_loaded = self.models_refused = 0
        self._refused_versions = set()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._poll_now = True
        self._link_down = False
        self._backoff_s = 1.0
        self._thread: Optional[threading.Thread] = None
        self._client = None

    # --- the request's side: one append --------------------------------------------------------------------
    def enqueue(self, row: Any) -> None:
        self.buffer.put(row)
        if len(self.buffer) >= self.config.batch_rows:
            self._wake.set()

    def poll_soon(self) -> None:
        """Ask for the current version at once (after a rollback, so the learner hears of it)."""
        self._poll_now = True
        self._wake.set()

    @property
    def dropped(self) -> int:
        """Rows lost on the robot: pushed out of the full buffer, refused by the learner, or not encodable."""
        return self.buffer.dropped + self.refused + self.unencodable

    # --- the link's thread ---------------------------------------------------------------------------------
    def start(self) -> "FleetLink":
        self._thread = threading.Thread(target=self._run, name="offload-fleet-link", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(self.close_timeout_s + self.config.timeout_s)

    def _run(self) -> None:
        next_poll = next_send = self.clock()
        try:
            self._client = self.client_factory()
            while not self._stop.is_set():
                now = self.clock()
                if self._poll_now or now >= next_poll:
                    self._poll_now = False
                    self.poll_version()
                    next_poll = self.clock() + self.config.period_s
                full = not self._link_down and len(self.buffer) >= self.config.batch_rows
                if not len(self.buffer):
                    next_send = max(next_send, now + self.config.send_every_s)   # a first row waits at most that
                elif now >= next_send or full:
                    delivered = self.flush()
                    self._backoff_s = 1.0 if delivered else min(2 * self._backoff_s, self.config.period_s)
                    next_send = self.clock() + (self.config.send_every_s if delivered else self._backoff_s)
                self._wake.wait(max(0.0, min(next_poll, next_send) - self.clock()))
                self._wake.clear()
            self.flush(deadline_s=self.close_timeout_s)
        except Exception as error:   # a broken client or callback must not end the robot's decisions
            self.log.error("the fleet link stopped: %s: %s", type(error).__name__, error)
        finally:
            if self._client is not None:
                self._client.close()

    def flush(self, deadline_s: Optional[float] = None) -> bool:
        """Send the buffer in batches until it is empty or the learner cannot take more; whether all went."""
        end = None if deadline_s is None else self.clock() + deadline_s
        while len(self.buffer) and (end is None or self.clock() < end):
            batch = self.buffer.take(self.config.batch_rows)
            kept, rows = [], []   # the buffer's rows (encoded again when resent) and their bytes
            for row in batch:
                try:
                    rows.append(self.encode(row))
                    kept.append(row)
                except Exception as error:
                    self.unencodable += 1
                    self.log.error("a row could not be encoded for the fleet learner: %s", error)
            if not rows:
                continue
            try:
                accepted, refused = self._client.send_rows(self.definitions, self.md5, rows)
            except (self.timeout_error, self.busy_error) as error:
                self.buffer.put_back(kept)
                self.send_failures += 1
                if not self._link_down:
                    self.log.warning("fleet learner %s cannot take rows now (%s): %d kept, sent when it returns",
                                     self.config.endpoint, type(error).__name__, len(self.buffer))
                self._link_down = True
                return False
            except self.refused_error as error:
                self.refused += len(rows)
                self.log.error("fleet learner refused a batch of %d rows: %s", len(rows), error)
                continue
            if self._link_down:
                self.log.info("fleet learner %s takes rows again", self.config.endpoint)
            self._link_down = False
            self.sent += accepted
            self.refused += refused
            if refused:
                self.log.warning("fleet learner refused %d of %d rows", refused, len(rows))
        return not len(self.buffer)

    def poll_version(self) -> None:
        """Ask for the version to run; fetch, check and hand over a new one. Failures keep the model in use."""
        current, rolled_back = self.current(), tuple(self.rolled_back())
        try:
            version, _ = self._client.current_version(current, rolled_back)
        except (self.timeout_error, self.busy_error) as error:
            self.log.debug("fleet learner: no version answer (%s)", type(error).__name__)
            return
        except self.refused_error as error:
            self.log.error("fleet learner's version answer refused: %s", error)
            return
        if not version or version == current or version in rolled_back or version in self._refused_versions:
            return
        try:
            data = self._client.fetch(version)
            fast, _ = load_model(data, expected_version=version)
        except (self.timeout_error, self.busy_error) as error:
            self.log.warning("model %s not fetched (%s): tried again in %g s", version[:12], type(error).__name__,
                             self.config.period_s)
            return
        except (self.refused_error, ModelFileError) as error:
            self._refused_versions.add(version)
            self.models_refused += 1
            self.log.error("model %s refused, keeping %s: %s", version[:12], current[:12] or "the model in use",
                           error)
            return
        self.models_loaded += 1
        self.on_model(version, fast)
