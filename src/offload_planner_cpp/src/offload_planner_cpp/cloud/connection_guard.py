"""The cloud server's guard on its TCP connections. libzmq buffers a multipart message whole, however many
frames, before the application sees any of it, and has no option to bound the frame count; so the guard
watches every connection's received byte count (TCP_INFO) and cuts a connection that has received more
than `limit_bytes` since its last delivered message; when the connections of one client key together hold
more than `key_limit_bytes` undelivered, or all connections more than `total_limit_bytes`, it cuts the
ones holding the most until they are back under it. (A connection's key is known once it delivered a
message; before that only its own bound and the total hold it.)"""
import socket as pysocket
import struct
from dataclasses import dataclass
from typing import Callable, Dict, Optional

import zmq

_TCP_INFO_BYTES_RECEIVED = 128   # offset of tcpi_bytes_received (u64) in Linux's struct tcp_info (>= 4.1)
GUARD_SLACK_BYTES = 1 << 20      # handshake, ZMTP and CURVE framing on top of the messages themselves


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


class ConnectionGuard:
    """fd -> Connection of every open TCP connection, and the bounds on what they hold undelivered."""

    def __init__(self, limit_bytes: int, total_limit_bytes: int, key_limit_bytes: int, log: Callable[..., None],
                 received: Callable[[int], Optional[int]] = tcp_bytes_received,
                 cut: Callable[[int], None] = cut_connection):
        self.limit_bytes, self.total_limit_bytes, self.key_limit_bytes = limit_bytes, total_limit_bytes, key_limit_bytes
        self.log, self.received, self.cut = log, received, cut
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
        return connection

    def forget(self, fd: int) -> None:
        """Cut a connection the broker refuses to hear from (a revoked key)."""
        self.connections.pop(fd, None)
        self.cut(fd)

    def check(self) -> None:
        """Cut each connection over its own bound, then the largest holders while all are over the total."""
        pending = {}
        for fd, connection in list(self.connections.items()):
            received = self.received(fd)
            if received is None:
                continue
            held = received - connection.baseline
            if held > self.limit_bytes:
                self.log("cut the connection from %s: %d bytes received without a complete message (bound %d "
                         "bytes: a message of too many frames)", connection.address, held, self.limit_bytes)
                self.connections.pop(fd, None)
                self.cuts += 1
                self.cut(fd)
            else:
                pending[fd] = held
        by_key = {}
        for fd, held in pending.items():
            user = self.connections[fd].user
            if user is not None:
                by_key.setdefault(user, []).append(fd)
        for user, fds in by_key.items():
            self._cut_largest({fd: pending[fd] for fd in fds}, self.key_limit_bytes, pending,
                              f"client key {user.decode(errors='replace')}'s connections")
        self._cut_largest(dict(pending), self.total_limit_bytes, pending, "all connections")

    def _cut_largest(self, holders: Dict[int, int], bound: int, pending: Dict[int, int], whose: str) -> None:
        """Cut the largest of `holders` (fd -> bytes held) until they hold at most `bound` together."""
        total = sum(holders.values())
        for fd in sorted(holders, key=holders.get, reverse=True):
            if total <= bound:
                break
            connection = self.connections.pop(fd)
            self.log("cut the connection from %s: it held %d of the %d bytes %s held undelivered (bound %d "
                     "bytes)", connection.address, holders[fd], total, whose, bound)
            self.cuts += 1
            self.cut(fd)
            total -= holders[fd]
            pending.pop(fd, None)

    def cut_revoked(self, allowlist) -> None:
        """Revoked robots lose their open connections too."""
        for fd, connection in list(self.connections.items()):
            if connection.user is not None and connection.user not in allowlist:
                self.log("closing the connection of revoked client key %s from %s", connection.user.decode(),
                         connection.address)
                self.cut(fd)
