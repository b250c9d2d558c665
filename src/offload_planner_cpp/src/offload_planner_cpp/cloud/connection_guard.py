"""The cloud server's guard on its TCP connections. libzmq buffers a multipart message whole, however many
frames, before the application sees any of it, and has no option to bound the frame count; so the guard
watches every connection's received byte count (TCP_INFO) and cuts a connection that has received more
than `limit_bytes` since its last delivered message; when the connections of one client key together hold
more than `key_limit_bytes` undelivered, or all connections more than `total_limit_bytes`, it cuts the
ones holding the most until they are back under it.

A connection's key is known from its first delivered message (its CURVE user id), so the protocol keeps
that message small (protocol.FIRST_MESSAGE_MAX_BYTES: clients ping ahead of a larger one). Until then the
guard allows a connection only `first_limit_bytes` read by libzmq (received minus what still waits in the
kernel's queue), so every byte a key holds beyond that counts against its own bound; and a key may have at
most `key_connections` connections, counted as each says whose it is."""
import array
import fcntl
import socket as pysocket
import struct
import termios
from dataclasses import dataclass
from typing import Callable, Dict, Optional

import zmq

from offload_planner_cpp.cloud.protocol import FIRST_MESSAGE_MAX_BYTES

_TCP_INFO_BYTES_RECEIVED = 128   # offset of tcpi_bytes_received (u64) in Linux's struct tcp_info (>= 4.1)
GUARD_SLACK_BYTES = 1 << 20      # handshake, ZMTP and CURVE framing on top of the messages themselves
FIRST_LIMIT_BYTES = FIRST_MESSAGE_MAX_BYTES + GUARD_SLACK_BYTES   # what libzmq may read before a first message


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


class ConnectionGuard:
    """fd -> Connection of every open TCP connection, and the bounds on what they hold undelivered."""

    def __init__(self, limit_bytes: int, total_limit_bytes: int, key_limit_bytes: int, log: Callable[..., None],
                 received: Callable[[int], Optional[int]] = tcp_bytes_received,
                 cut: Callable[[int], None] = cut_connection, *, key_connections: int = 0,
                 first_limit_bytes: int = FIRST_LIMIT_BYTES,
                 unread: Callable[[int], Optional[int]] = tcp_bytes_unread):
        self.limit_bytes, self.total_limit_bytes, self.key_limit_bytes = limit_bytes, total_limit_bytes, key_limit_bytes
        self.key_connections, self.first_limit_bytes = key_connections, first_limit_bytes
        self.log, self.received, self.cut, self.unread = log, received, cut, unread
        self.connections: Dict[int, Connection] = {}
        self.cuts = 0

    def accepted(self, fd: int, address: str = "?") -> None:
        self.connections[fd] = Connection(self.received(fd) or 0, address)

    def closed(self, fd: int) -> None:
        self.connections.pop(fd, None)

    def delivered(self, fd: Optional[int]) -> Optional[Connection]:
        """A message of `fd` reached the broker: what it holds undelivered starts again from here."""
        connection = self.connections.get(fd) if fd is not None else None
        if connection is not None:
            connection.baseline = self.received(fd) or connection.baseline
            connection.identified = True
        return connection

    def identify(self, fd: int, connection: Connection, user: bytes) -> bool:
        """The connection's messages come with client key `user`; False (and the connection cut) when that
        key already has `key_connections` other connections."""
        if connection.user == user:
            return True
        connection.user = user
        if self.key_connections and sum(c.user == user for c in self.connections.values()) > self.key_connections:
            self.log("cut the connection from %s: client key %s already has %d connections (bound %d)",
                     connection.address, user.decode(errors="replace"), self.key_connections, self.key_connections)
            self._drop(fd)
            return False
        return True

    def forget(self, fd: int) -> None:
        """Cut a connection the broker refuses to hear from (a revoked key)."""
        self.connections.pop(fd, None)
        self.cut(fd)

    def check(self, drained: Callable[[], bool] = lambda: True) -> None:
        """Cut each connection over its own bound (before its first message: over `first_limit_bytes` read,
        judged only when `drained()` says the broker has read every message libzmq delivered), then the
        largest holders while a key's or all connections are over their bound."""
        pending, first = {}, {}
        for fd, connection in list(self.connections.items()):
            received = self.received(fd)
            if received is None:
                continue
            held = received - connection.baseline
            if held > self.limit_bytes:
                self.log("cut the connection from %s: %d bytes received without a complete message (bound %d "
                         "bytes: a message of too many frames)", connection.address, held, self.limit_bytes)
                self._drop(fd)
                continue
            pending[fd] = held
            if not connection.identified and held > self.first_limit_bytes:
                unread = self.unread(fd)
                if unread is not None:
                    first[fd] = held - unread
        # A first message sampled above and not yet read by the broker shows now as a message waiting: then
        # the connection may have said whose it is already, and is judged at the next check.
        if first and drained():
            for fd, read in first.items():
                if read > self.first_limit_bytes:
                    self.log("cut the connection from %s: %d bytes read before its first message (bound %d bytes: a "
                             "client pings ahead of a larger message)", self.connections[fd].address, read,
                             self.first_limit_bytes)
                    self._drop(fd)
                    pending.pop(fd)
        by_key = {}
        for fd, held in pending.items():
            user = self.connections[fd].user
            if user is not None:
                by_key.setdefault(user, []).append(fd)
        for user, fds in by_key.items():
            self._cut_largest({fd: pending[fd] for fd in fds}, self.key_limit_bytes, pending,
                              f"client key {user.decode(errors='replace')}'s connections")
        self._cut_largest(dict(pending), self.total_limit_bytes, pending, "all connections")

    def _drop(self, fd: int) -> None:
        self.connections.pop(fd, None)
        self.cuts += 1
        self.cut(fd)

    def _cut_largest(self, holders: Dict[int, int], bound: int, pending: Dict[int, int], whose: str) -> None:
        """Cut the largest of `holders` (fd -> bytes held) until they hold at most `bound` together."""
        total = sum(holders.values())
        for fd in sorted(holders, key=holders.get, reverse=True):
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
