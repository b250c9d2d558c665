"""The cloud server's guard on its TCP connections. libzmq buffers a multipart message whole, however many
frames, before the application sees any of it, and has no option to bound the frame count; so the guard
watches every connection's received byte count (TCP_INFO) and cuts a connection that has received more
than `limit_bytes` since its last delivered message; when the connections of one client key together hold
more than `key_limit_bytes` undelivered, or all connections more than `total_limit_bytes`, it cuts the
ones holding the most until they are back under it (connections that have not said whose they are first).

A connection's key is known from its first delivered message (its CURVE user id), so the protocol keeps
that message small (protocol.FIRST_MESSAGE_MAX_BYTES: clients ping ahead of a larger one). Until then a
connection may have had only `first_limit_bytes` read by libzmq (received minus what still waits in the
kernel's queue), and all such connections together `unidentified_limit_bytes` (the oldest go first); a key
may have `key_connections` connections, counted as each says whose it is (its least recently active one
makes room for a new one, so a connection whose peer vanished never locks the key out).

A connection is judged unidentified only when its first message cannot be waiting for the broker: the
broker found no message waiting after the counts were read, or it has read a message from every open
connection's turn since libzmq read past that connection's first message (a ROUTER takes one message from
each connection in turn), or FIRST_MESSAGE_WAIT_S have passed since. Every frontend message must pass
through delivered(), with its routing id: a message an earlier connection on the same fd left waiting is
credited to none
(pipe_ledger.py), and a message of a connection that closed is stale: the broker drops it.

The guard needs no descriptor of its own: it reads and shuts connections through libzmq's descriptors
(tcp_socket.py); between checks an epoll set points it at the connections with bytes waiting for libzmq.
Beyond `max_connections` open connections it cuts one (connection_cap.py).
"""
import collections
import time
from dataclasses import dataclass
from typing import Callable, Dict, Optional, Union

from offload_cloud import connection_cap
from offload_cloud.pipe_ledger import DOUBTFUL, FIRST_MESSAGE_WAIT_S, STALE, PipeLedger, newer, pipe_number
from offload_cloud.protocol import FIRST_MESSAGE_MAX_BYTES
from offload_cloud.tcp_socket import ActivityWatch, cut_connection, peer_address, tcp_bytes_received, \
    tcp_bytes_unread

GUARD_SLACK_BYTES = 1 << 20      # handshake, ZMTP and CURVE framing on top of the messages themselves
FIRST_LIMIT_BYTES = FIRST_MESSAGE_MAX_BYTES + GUARD_SLACK_BYTES   # what libzmq may read before a first message
# Read past this, libzmq has read a connection's handshake and at least its first message's start (a CURVE
# handshake is under 1 KiB, a ping under 100 bytes): from then on the broker's turns are counted.
_FIRST_BYTES_READ = 64 << 10
# Read less than this, a connection cannot have a message waiting for the broker: the smallest handshake
# (NULL: a 64-byte greeting and a READY command with its Socket-Type) and an empty message take more. So an
# idle connection (a greeting, a stalled handshake) has no turn in the ROUTER's round robin.
_MIN_BYTES_FOR_A_MESSAGE = 96


@dataclass
class Connection:
    baseline: int                         # bytes received when its last message was delivered
    address: str = "?"
    user: Optional[bytes] = None          # CURVE client key (Z85) once a message came
    identified: bool = False              # a message came (with --insecure there is no key to know)
    accepted_at: float = 0.0              # monotonic seconds
    last_active: float = 0.0              # its last delivered message (or its accept)
    first_read_at: Optional[int] = None   # broker messages read when libzmq was found past its first bytes
    first_read_time: float = 0.0          # and when
    routing_id: Optional[int] = None      # the ROUTER's number for its pipe, from its messages
    received: int = 0                     # bytes received when last looked at
    unread: int = 0                       # of those, not yet read by libzmq
    adopted: bool = False                 # known from a message before libzmq's accept event came
    doubtful: bool = False                # its last message may have been a closed connection's (pipe_ledger.py)


class ConnectionGuard:
    """fd -> Connection of every open TCP connection, and the bounds on what they hold undelivered."""

    def __init__(self, limit_bytes: int, total_limit_bytes: int, key_limit_bytes: int, log: Callable[..., None],
                 received: Callable[[int], Optional[int]] = tcp_bytes_received,
                 cut: Callable[[int], None] = cut_connection, *, key_connections: int = 0,
                 first_limit_bytes: int = FIRST_LIMIT_BYTES, unidentified_limit_bytes: int = 64 << 20,
                 unread: Callable[[int], Optional[int]] = tcp_bytes_unread,
                 clock: Callable[[], float] = time.monotonic, max_connections: int = 0,
                 address: Callable[[int], str] = peer_address, watch: Optional[ActivityWatch] = None,
                 receive_hwm: int = 4):
        self.limit_bytes, self.total_limit_bytes, self.key_limit_bytes = limit_bytes, total_limit_bytes, key_limit_bytes
        self.key_connections, self.first_limit_bytes = key_connections, first_limit_bytes
        self.unidentified_limit_bytes, self.max_connections = unidentified_limit_bytes, max_connections
        self.log, self.received, self.cut, self.unread, self.clock = log, received, cut, unread, clock
        self.address, self.watch = address, watch
        self.connections: Dict[int, Connection] = {}
        self.unidentified: Dict[int, Connection] = {}   # those yet to deliver a message, oldest first
        self.ledger = PipeLedger(clock, receive_hwm)
        self._closed_before_accept = set()   # fds of connections that closed before their accept event came
        self._cutting: Dict[int, Connection] = {}   # connections cut, until libzmq reports them closed
        self._judging = set()  # unidentified fds libzmq read past their first bytes of: looked at between checks
        self.cut_reasons = collections.Counter()   # connections cut, by the bound that cut them
        self.accepts = 0      # connections accepted
        self.held = {"all": 0, "largest_key": 0, "unidentified": 0}   # bytes held undelivered at the last check
        self.messages = 0     # frontend messages the broker has read
        self.turns = 1        # connections that may have a message waiting (a turn in the ROUTER's round robin)

    def accepted(self, fd: int, address: Optional[str] = None) -> None:
        known = self.connections.get(fd)
        if fd in self._closed_before_accept:   # libzmq signals an accept after starting the connection: this
            self._closed_before_accept.discard(fd)   # one closed before its signal came
            return
        if known is not None and known.adopted:   # its messages came first
            known.adopted = False
            return
        if known is not None:   # its close was never reported
            self.ledger.retire(fd, known.routing_id, self.messages)
        now = self.clock()
        if self.watch is not None:
            self.watch.add(fd)
        received = self.received(fd) or 0
        self.unidentified.pop(fd, None)
        self.connections[fd] = self.unidentified[fd] = Connection(
            received, address if address is not None else self.address(fd), accepted_at=now, last_active=now,
            received=received)
        self.accepts += 1
        if self.max_connections:
            connection_cap.enforce(self.connections, self.unidentified, self.max_connections, self._drop_over_cap,
                                   self.log, fd, now)

    @property
    def cuts(self) -> int:
        return sum(self.cut_reasons.values())

    def snapshot(self) -> dict:
        """Connections by state, cuts by reason, bytes held against each bound (STATS, metrics)."""
        return {"connections": {"identified": len(self.connections) - len(self.unidentified),
                                "unidentified": len(self.unidentified), "closing": len(self._cutting)},
                "accepted": self.accepts, "max_connections": self.max_connections, "cuts": dict(self.cut_reasons),
                "held_bytes": dict(self.held), "bounds_bytes": {"all": self.total_limit_bytes,
                                                                "largest_key": self.key_limit_bytes,
                                                                "unidentified": self.unidentified_limit_bytes}}

    def closed(self, fd: int) -> None:
        self.unidentified.pop(fd, None)
        self._judging.discard(fd)
        connection = self.connections.pop(fd, None) or self._cutting.pop(fd, None)
        if connection is None or connection.adopted:
            self._closed_before_accept.add(fd)
        if self.watch is not None:
            self.watch.remove(fd)
        self.ledger.retire(fd, connection.routing_id if connection is not None else None, self.messages)

    def delivered(self, fd: Optional[int], routing_id: Optional[bytes] = None) -> Union[Connection, str, None]:
        """A message of `fd` reached the broker: what it holds undelivered starts again from here. Returns its
        connection; STALE for a message of a connection that closed (an earlier connection on the same fd, told
        by the ROUTER's pipe numbers: nobody to answer); None when it is credited to no connection (no fd, a
        routing id a peer chose). A doubtful one (pipe_ledger.py) counts for the connection's bytes, and
        connection.doubtful says its key names nothing."""
        self.messages += 1
        if fd is None:
            return None
        if fd in self._cutting:
            return STALE
        connection = self.connections.get(fd)
        if routing_id is not None:
            number = pipe_number(routing_id)
            if number is None:
                return None
            current = connection.routing_id if connection is not None else None
            verdict = self.ledger.classify(fd, number, current, self.messages, self.turns)
            if verdict == STALE or (current is not None and newer(current, number)):
                return STALE
            if verdict == DOUBTFUL and connection is None:
                return None
            if connection is None:
                connection = self._adopt(fd)
            connection.doubtful = verdict == DOUBTFUL
            if not connection.doubtful:
                connection.routing_id = number
                self.ledger.credited(fd)
        elif connection is None:
            return None
        received = self.received(fd)
        if received is not None:
            connection.baseline = connection.received = received
        if self.unidentified.pop(fd, None) is not None and self.watch is not None:
            self.watch.remove(fd)   # the watch wakes the broker for connections yet to say whose they are only
        connection.identified, connection.unread = True, 0
        self._judging.discard(fd)
        connection.last_active = self.clock()
        return connection

    def _adopt(self, fd: int) -> Connection:
        """A connection whose message came before libzmq's accept event (libzmq signals the accept after it
        started the connection, so with two I/O threads its handshake and first messages can come first)."""
        now = self.clock()
        received = self.received(fd) or 0
        connection = Connection(received, self.address(fd), accepted_at=now, last_active=now, received=received,
                                adopted=True)
        self.connections[fd] = connection
        if self.max_connections:
            connection_cap.enforce(self.connections, self.unidentified, self.max_connections, self._drop_over_cap,
                                   self.log, fd, now)
        return connection

    def identify(self, fd: int, connection: Connection, user: bytes) -> None:
        """The connection's messages come with client key `user`. When that key has more than
        `key_connections` connections, its least recently active other one is cut (a connection whose peer
        vanished without a word makes room; this one goes on). A doubtful message's key names nothing."""
        if connection.user == user or connection.doubtful:
            return
        connection.user = user
        if not self.key_connections:
            return
        others = [fd_ for fd_, c in self.connections.items() if c.user == user and fd_ != fd]
        while len(others) >= self.key_connections:
            oldest = min(others, key=lambda fd_: self.connections[fd_].last_active)
            others.remove(oldest)
            self.log("cut the connection from %s: client key %s has %d connections (bound %d): its least recently "
                     "active one goes", self.connections[oldest].address, user.decode(errors="replace"),
                     len(others) + 2, self.key_connections)
            self._drop(oldest, "key_connections")

    def forget(self, fd: int) -> None:
        """Cut a connection the broker refuses to hear from (a revoked key)."""
        self.unidentified.pop(fd, None)
        connection = self.connections.pop(fd, None)
        if connection is not None:
            self._cutting[fd] = connection
        self.cut_reasons["revoked"] += 1
        self.cut(fd)

    def check(self, drained: Callable[[], bool] = lambda: True) -> None:
        """Apply every bound once (the broker calls this every 25 ms); `drained()` says whether the broker
        has no frontend message waiting."""
        pending, turns = {}, 0
        for fd, connection in list(self.connections.items()):
            received = self.received(fd)
            if received is None:
                continue
            connection.received = received
            held = received - connection.baseline
            if held > self.limit_bytes:
                self.log("cut the connection from %s: %d bytes received without a complete message (bound %d "
                         "bytes: a message of too many frames)", connection.address, held, self.limit_bytes)
                self._drop(fd, "message_bytes")
                continue
            pending[fd] = held
            if connection.identified:
                turns += 1
            elif held > 0:
                unread = self.unread(fd)
                connection.unread = unread if unread is not None else held
            if not connection.identified and held - connection.unread >= _MIN_BYTES_FOR_A_MESSAGE:
                turns += 1
        self.turns = max(1, turns)
        self.ledger.settle_due(self.messages, self.turns)
        self._check_unidentified(pending, drained)
        by_key = {}
        for fd, held in pending.items():
            user = self.connections[fd].user
            if user is not None:
                by_key.setdefault(user, []).append(fd)
        self.held = {"all": sum(pending.values()),
                     "largest_key": max((sum(pending[fd] for fd in fds) for fds in by_key.values()), default=0),
                     "unidentified": sum(held for fd, held in pending.items() if not self.connections[fd].identified)}
        for user, fds in by_key.items():
            self._cut_largest({fd: pending[fd] for fd in fds}, self.key_limit_bytes, pending,
                              f"client key {user.decode(errors='replace')}'s connections", "key_bytes")
        self._cut_largest(dict(pending), self.total_limit_bytes, pending, "all connections", "all_bytes")

    def _check_unidentified(self, pending: Dict[int, int], drained: Callable[[], bool]) -> None:
        """Cut unidentified connections past the first-message bound, then the oldest while they hold more than
        their budget together; only those whose first message cannot be waiting for the broker (_due)."""
        read = {fd: held - self.connections[fd].unread for fd, held in pending.items()
                if held > 0 and not self.connections[fd].identified}
        if not read:
            return
        now = self.clock()
        judged = {fd: count for fd, count in read.items() if self._due(fd, count, now)}
        if len(judged) < len(read) and drained():
            judged = dict(read)
        for fd, count in list(judged.items()):
            if self._over_first_limit(fd, count):
                pending.pop(fd)
                del judged[fd]
        total = sum(judged.values())
        for fd in sorted(judged, key=lambda fd_: self.connections[fd_].accepted_at):
            if total <= self.unidentified_limit_bytes:
                break
            self.log("cut the connection from %s: the connections that have not said whose they are held %d bytes "
                     "together (bound %d bytes): the oldest goes", self.connections[fd].address, total,
                     self.unidentified_limit_bytes)
            total -= judged[fd]
            self._drop(fd, "unidentified_bytes")
            pending.pop(fd)

    def _due(self, fd: int, read: int, now: float) -> bool:
        """Whether a connection libzmq has read `read` bytes of before its first message can be judged: the
        broker has read a message for every connection's turn since libzmq read past its first bytes (only a
        connection that libzmq read enough of for a message has a turn), or FIRST_MESSAGE_WAIT_S passed."""
        connection = self.connections[fd]
        if connection.first_read_at is None:
            if read > _FIRST_BYTES_READ:
                connection.first_read_at, connection.first_read_time = self.messages, now
                self._judging.add(fd)
            return False
        return self.messages - connection.first_read_at >= self.turns or \
            now - connection.first_read_time >= FIRST_MESSAGE_WAIT_S

    def _over_first_limit(self, fd: int, read: int) -> bool:
        if read <= self.first_limit_bytes:
            return False
        self.log("cut the connection from %s: %d bytes read before its first message (bound %d bytes: a client "
                 "pings ahead of a larger message)", self.connections[fd].address, read, self.first_limit_bytes)
        self._drop(fd, "first_message")
        return True

    def look_between_checks(self, drained: Callable[[], bool]) -> None:
        """The first-message bound between two checks (the broker calls this after every message): the
        connections yet to say whose they are that have bytes waiting for libzmq (epoll: a fast sender) or are
        being judged are looked at at once, so a first message far over its bound is cut within a few of the
        broker's messages rather than two checks (25 ms of a fast sender)."""
        if self.watch is None:
            return
        woken = self.watch.active()
        if not woken and not self._judging:
            return
        now = self.clock()
        for fd in [fd for fd in woken if fd in self.unidentified] + [fd for fd in self._judging if fd not in woken]:
            connection = self.unidentified.get(fd)
            if connection is None:
                self._judging.discard(fd)
                continue
            received, unread = self.received(fd), self.unread(fd)
            if received is None or unread is None:
                continue
            connection.received, connection.unread = received, unread
            read = received - connection.baseline - unread
            if self._due(fd, read, now) or (read > self.first_limit_bytes and drained()):
                self._over_first_limit(fd, read)

    def frontend_drained(self) -> None:
        """The broker found no frontend message waiting (pipe_ledger.py: the closed connections' pipes are
        empty)."""
        self.ledger.drained()

    def _drop(self, fd: int, reason: str) -> None:
        self.unidentified.pop(fd, None)
        connection = self.connections.pop(fd, None)
        if connection is not None:
            self._cutting[fd] = connection   # its messages still on their way are stale
        self.cut_reasons[reason] += 1
        self.cut(fd)

    def _drop_over_cap(self, fd: int) -> None:
        self._drop(fd, "max_connections")

    def _cut_largest(self, holders: Dict[int, int], bound: int, pending: Dict[int, int], whose: str,
                     reason: str) -> None:
        """Cut the largest of `holders` (fd -> bytes held) until they hold at most `bound` together, those that
        have not said whose they are first."""
        total = sum(holders.values())
        order = sorted(holders, key=lambda fd: (self.connections[fd].identified, -holders[fd]))
        for fd in order:
            if total <= bound:
                break
            self.log("cut the connection from %s: it held %d of the %d bytes %s held undelivered (bound %d "
                     "bytes)", self.connections[fd].address, holders[fd], total, whose, bound)
            self._drop(fd, reason)
            total -= holders[fd]
            pending.pop(fd, None)

    def cut_revoked(self, allowlist) -> None:
        """Revoked robots lose their open connections too."""
        for fd, connection in list(self.connections.items()):
            if connection.user is not None and connection.user not in allowlist:
                self.log("closing the connection of revoked client key %s from %s", connection.user.decode(),
                         connection.address)
                self.cut_reasons["revoked"] += 1
                self.cut(fd)
