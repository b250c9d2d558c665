"""What the connection guard reads from and does to a TCP connection libzmq owns, through libzmq's own
descriptor number and without a new descriptor: the kernel's byte counts (TCP_INFO, FIONREAD), the peer's
address, a shutdown. socket.fromfd would dup the descriptor, and a process at its descriptor limit cannot dup:
the guard would go blind exactly when an attacker holds every descriptor."""
import array
import ctypes
import fcntl
import select
import socket as pysocket
import struct
import termios
import threading
from contextlib import contextmanager
from typing import Optional, Set

import zmq

_TCP_INFO_BYTES_RECEIVED = 128   # offset of tcpi_bytes_received (u64) in Linux's struct tcp_info (>= 4.1)
_TCP_INFO_SIZE = 256
try:   # getsockopt(2) itself: half the cost of a Python socket object per look, which matters at 40 looks/s
    _getsockopt = ctypes.CDLL(None, use_errno=True).getsockopt
    _getsockopt.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint32)]
except (OSError, AttributeError):
    _getsockopt = None
_buffers = threading.local()


@contextmanager
def _borrowed(fd: int, family: int = pysocket.AF_INET):
    """A socket object on descriptor `fd` itself (no dup), detached again on exit so the descriptor stays
    libzmq's. With a family given, Python asks the kernel nothing to build it."""
    sock = pysocket.socket(family, pysocket.SOCK_STREAM, 0, fileno=fd) if family != -1 else \
        pysocket.socket(fileno=fd)
    try:
        yield sock
    finally:
        sock.detach()


def tcp_bytes_received(fd: int) -> Optional[int]:
    """Bytes the kernel has received on a TCP socket (what libzmq may have buffered, and more), or None."""
    if _getsockopt is not None:
        if not hasattr(_buffers, "info"):
            _buffers.info, _buffers.size = ctypes.create_string_buffer(_TCP_INFO_SIZE), ctypes.c_uint32()
        _buffers.size.value = _TCP_INFO_SIZE
        if _getsockopt(fd, pysocket.IPPROTO_TCP, pysocket.TCP_INFO, _buffers.info, ctypes.byref(_buffers.size)) != 0 \
                or _buffers.size.value < _TCP_INFO_BYTES_RECEIVED + 8:
            return None
        return struct.unpack_from("<Q", _buffers.info, _TCP_INFO_BYTES_RECEIVED)[0]
    try:
        with _borrowed(fd) as sock:
            info = sock.getsockopt(pysocket.IPPROTO_TCP, pysocket.TCP_INFO, 256)
    except (OSError, ValueError):
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
        with _borrowed(fd) as sock:
            sock.shutdown(pysocket.SHUT_RDWR)
    except (OSError, ValueError):
        pass


def peer_address(fd: int) -> str:
    """HOST:PORT of the peer of a connected socket, or "?"."""
    try:
        with _borrowed(fd, family=-1) as sock:   # the family decides how the address reads
            host, port = sock.getpeername()[:2]
            return f"{host}:{port}"
    except (OSError, ValueError):
        return "?"


class ActivityWatch:
    """Which connections received bytes since the last look that libzmq has not read yet (a sender faster than
    libzmq): an epoll set of their descriptors, edge-triggered on input (one descriptor for the set, none per
    connection; libzmq's own epoll is not disturbed; the kernel drops a descriptor from the set when libzmq
    closes it). Bytes libzmq read at once are not reported: epoll tells what is readable when asked."""

    def __init__(self):
        self._epoll = select.epoll()

    def add(self, fd: int) -> bool:
        """Watches `fd`; False when it cannot be watched (then it must be looked at every time)."""
        try:
            self._epoll.register(fd, select.EPOLLIN | select.EPOLLET)
        except FileExistsError:
            try:
                self._epoll.modify(fd, select.EPOLLIN | select.EPOLLET)
            except OSError:
                return False
        except (OSError, ValueError):
            return False
        return True

    def remove(self, fd: int) -> None:
        try:
            self._epoll.unregister(fd)
        except (OSError, ValueError):
            pass

    def active(self) -> Set[int]:
        """The watched descriptors that received bytes since the last call and still have some unread (or
        closed)."""
        fds = set()
        for _ in range(1024):   # bounded: 1024 x 1024 wake-ups
            events = self._epoll.poll(0, 1024)
            fds.update(fd for fd, _ in events)
            if len(events) < 1024:
                break
        return fds

    def fileno(self) -> int:
        """Readable while a watched descriptor has a report waiting: the broker polls it beside its sockets."""
        return self._epoll.fileno()

    def close(self) -> None:
        self._epoll.close()


def source_fd(frame) -> Optional[int]:
    """The fd of the TCP connection a message came on (libzmq's SRCFD), or None."""
    try:
        return frame.get(zmq.SRCFD)
    except (zmq.ZMQError, AttributeError):
        return None
