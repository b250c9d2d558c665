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
credited to none."""
import array
import fcntl
import socket as pysocket
import struct
import termios
import time
from dataclasses import dataclass
from typing import Callable, Dict, Optional

import zmq

from offload_cloud.protocol import FIRST_MESSAGE_MAX_BYTES

_TCP_INFO_BYTES_RECEIVED = 128   # offset of tcpi_bytes_received (u64) in Linux's struct tcp_info (>= 4.1)
GUARD_SLACK_BYTES = 1 << 20      # handshake, ZMTP and CURVE framing on top of the messages themselves
FIRST_LIMIT_BYTES = FIRST_MESSAGE_MAX_BYTES + GUARD_SLACK_BYTES   # what libzmq may read before a first message
# Read past this, libzmq has read a connection's handshake and at least its first message's start (a CURVE
# handshake is under 1 KiB, a ping under 100 bytes): from then on the broker's turns are counted.
_FIRST_BYTES_READ = 64 << 10
# However many connections wait their turn, a first message waits for the broker no longer than this (a
# broker that far behind answers BUSY, --max-wait-s); so many idle connections cannot put the judgement off.
FIRST_MESSAGE_WAIT_S = 2.0


def _pipe_number(routing_id: bytes) -> Optional[int]:
    """The number libzmq's ROUTER gave a pipe (its routing id: a zero byte and a 32-bit counter), or None for a
    routing id a peer chose itself (this project's clients never do)."""
    if len(routing_id) != 5 or routing_id[0] != 0:
        return None
    return int.from_bytes(routing_id[1:], "big")


def _serial_not_before(number: int, other: int) -> bool:
    """`number` was given at or after `other` (32-bit serial arithmetic: the counter starts at random and wraps)."""
    return (number - other) % (1 << 32) < (1 << 31)


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


def tcp_bytes_unread(fd: int) -> Optional[int]:
    """Bytes received on a TCP socket that its reader (libzmq) has not read yet (FIONREAD), or None."""
    count = array.array("i", [0])
    try:
        fcntl.ioctl(fd, termios.FIONREAD, count)
    except OSError:
        return None
    return count[0]


def cut_connection(fd: int) -> None:
    """Shuts a TCP connection libzmq owns; libzmq sees the end, closes it and frees its half-received message."""
    try:
        with pysocket.fromfd(fd, pysocket.AF_INET, pysocket.SOCK_STREAM) as sock:
            sock.shutdown(pysocket.SHUT_RDWR)
    except OSError:
        pass


def source_fd(frame) -> Optional[int]:
    """The fd of the TCP connection a message came on (libzmq's SRCFD), or None."""
    try:
        return frame.get(zmq.SRCFD)
    except (zmq.ZMQError, AttributeError):
        return None


def peer_address(fd: int) -> str:
    try:
        with pysocket.fromfd(fd, pysocket.AF_INET, pysocket.SOCK_STREAM) as sock:
            host, port = sock.getpeername()[:2]
            return f"{host}:{port}"
    except OSError:
        return "?"


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


class ConnectionGuard:
    """fd -> Connection of every open TCP connection, and the bounds on what they hold undelivered."""

    def __init__(self, limit_bytes: int, total_limit_bytes: int, key_limit_bytes: int, log: Callable[..., None],
                 received: Callable[[int], Optional[int]] = tcp_bytes_received,
                 cut: Callable[[int], None] = cut_connection, *, key_connections: int = 0,
                 first_limit_bytes: int = FIRST_LIMIT_BYTES, unidentified_limit_bytes: int = 64 << 20,
                 unread: Callable[[int], Optional[int]] = tcp_bytes_unread,
                 clock: Callable[[], float] = time.monotonic):
        self.limit_bytes, self.total_limit_bytes, self.key_limit_bytes = limit_bytes, total_limit_bytes, key_limit_bytes
        self.key_connections, self.first_limit_bytes = key_connections, first_limit_bytes
        self.unidentified_limit_bytes = unidentified_limit_bytes
        self.log, self.received, self.cut, self.unread, self.clock = log, received, cut, unread, clock
        self.connections: Dict[int, Connection] = {}
        self.cuts = 0
        self.messages = 0     # frontend messages the broker has read

    def accepted(self, fd: int, address: str = "?") -> None:
        now = self.clock()
        self.connections[fd] = Connection(self.received(fd) or 0, address, accepted_at=now, last_active=now)

    def closed(self, fd: int) -> None:
        self.connections.pop(fd, None)

    def delivered(self, fd: Optional[int], routing_id: Optional[bytes] = None) -> Optional[Connection]:
        """A message of `fd` reached the broker: what it holds undelivered starts again from here. None when it
        is no connection's the guard knows, such as a message an earlier connection on the same fd left waiting
        (the ROUTER numbers its pipes in order: an older number is an older connection's)."""
        self.messages += 1
        connection = self.connections.get(fd) if fd is not None else None
        if connection is not None and routing_id is not None:
            number = _pipe_number(routing_id)
            if number is None or (connection.routing_id is not None
                                  and not _serial_not_before(number, connection.routing_id)):
                return None
            connection.routing_id = number
        if connection is not None:
            connection.baseline = self.received(fd) or connection.baseline
            connection.identified = True
            connection.last_active = self.clock()
        return connection

    def identify(self, fd: int, connection: Connection, user: bytes) -> None:
        """The connection's messages come with client key `user`. When that key has more than
        `key_connections` connections, its least recently active other one is cut (a connection whose peer
        vanished without a word makes room; this one goes on)."""
        if connection.user == user:
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
            self._drop(oldest)

    def forget(self, fd: int) -> None:
        """Cut a connection the broker refuses to hear from (a revoked key)."""
        self.connections.pop(fd, None)
        self.cut(fd)

    def check(self, drained: Callable[[], bool] = lambda: True) -> None:
        """Apply every bound once (the broker calls this every 25 ms); `drained()` says whether the broker
        has no frontend message waiting."""
        pending = {}
        for fd, connection in list(self.connections.items()):
            received = self.received(fd)
            if received is None:
                continue
            held = received - connection.baseline
            if held > self.limit_bytes:
                self.log("cut the connection from %s: %d bytes received without a complete message (bound %d "
                         "bytes: a message of too many frames)", connection.address, held, self.limit_bytes)
                self._drop(fd)
            else:
                pending[fd] = held
        self._check_unidentified(pending, drained)
        by_key = {}
        for fd, held in pending.items():
            user = self.connections[fd].user
            if user is not None:
                by_key.setdefault(user, []).append(fd)
        for user, fds in by_key.items():
            self._cut_largest({fd: pending[fd] for fd in fds}, self.key_limit_bytes, pending,
                              f"client key {user.decode(errors='replace')}'s connections")
        self._cut_largest(dict(pending), self.total_limit_bytes, pending, "all connections")

    def _check_unidentified(self, pending: Dict[int, int], drained: Callable[[], bool]) -> None:
        """Cut unidentified connections past the first-message bound, then the oldest while they hold more than
        their budget together; only those whose first message cannot be waiting for the broker."""
        read = {}
        for fd, held in pending.items():
            connection = self.connections[fd]
            if connection.identified or held <= 0:
                continue
            unread = self.unread(fd)
            if unread is not None:
                read[fd] = held - unread
        if not read:
            return
        judged = dict(read) if drained() else {}
        turns, now = len(self.connections), self.clock()
        for fd, count in read.items():
            connection = self.connections[fd]
            if connection.first_read_at is not None and (self.messages - connection.first_read_at >= turns
                                                         or now - connection.first_read_time >= FIRST_MESSAGE_WAIT_S):
                judged[fd] = count
            elif connection.first_read_at is None and count > _FIRST_BYTES_READ:
                connection.first_read_at, connection.first_read_time = self.messages, now
        for fd, count in list(judged.items()):
            if count > self.first_limit_bytes:
                self.log("cut the connection from %s: %d bytes read before its first message (bound %d bytes: a "
                         "client pings ahead of a larger message)", self.connections[fd].address, count,
                         self.first_limit_bytes)
                self._drop(fd)
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
            self._drop(fd)
            pending.pop(fd)

    def _drop(self, fd: int) -> None:
        self.connections.pop(fd, None)
        self.cuts += 1
        self.cut(fd)

    def _cut_largest(self, holders: Dict[int, int], bound: int, pending: Dict[int, int], whose: str) -> None:
        """Cut the largest of `holders` (fd -> bytes held) until they hold at most `bound` together, those that
        have not said whose they are first."""
        total = sum(holders.values())
        order = sorted(holders, key=lambda fd: (self.connections[fd].identified, -holders[fd]))
        for fd in order:
            if total <= bound:
                break
            self.log("cut the connection from %s: it held %d of the %d bytes %s held undelivered (bound %d "
                     "bytes)", self.connections[fd].address, holders[fd], total, whose, bound)
            self._drop(fd)
            total -= holders[fd]
            pending.pop(fd, None)

    def cut_revoked(self, allowlist) -> None:
        """Revoked robots lose their open connections too."""
        for fd, connection in list(self.connections.items()):
            if connection.user is not None and connection.user not in allowlist:
                self.log("closing the connection of revoked client key %s from %s", connection.user.decode(),
                         connection.address)
                self.cut(fd)
