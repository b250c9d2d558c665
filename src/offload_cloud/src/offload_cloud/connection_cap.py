"""How many TCP connections the cloud server holds open, below its file descriptor limit.

A process at its descriptor limit cannot accept: libzmq's listener then spins on a failing accept() (a core's
worth of CPU) and every new robot is locked out, while anyone can open plain TCP connections without a key. So
the server raises its soft RLIMIT_NOFILE to the hard limit at start, keeps its connections `max_connections`
below what remains (its own descriptors and a margin for the accepts between two checks), and when a new
connection takes it over that cap cuts one: the oldest of those that have not said whose they are (a
handshake or greeting left idle) once it had a second to complete its handshake, else the newcomer (so a
flood of connections faster than the cap per second cannot cut every handshake short); when every other
connection said whose it is, the one whose last message is the oldest."""
import os
import resource
from typing import Callable, Dict, Optional

_MARGIN_MIN = 128        # descriptors kept free beyond those the server holds at start ...
_MARGIN_SHARE = 16       # ... or 1/16 of the limit, whichever is more: connections libzmq accepted before the
                         # broker heard of them, and those cut that libzmq has not closed yet
# A connection has this long to say whose it is before a newcomer may take its place: connections coming
# faster than the cap per this time are refused instead, so a flood cannot cut every handshake short.
HANDSHAKE_GRACE_S = 1.0


def raise_descriptor_limit() -> int:
    """Raises the soft RLIMIT_NOFILE to the hard limit (a systemd unit starts services at 1024 soft); returns the
    soft limit in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = hard if hard != resource.RLIM_INFINITY else max(soft, 1 << 20)
    if soft == resource.RLIM_INFINITY or soft >= target:
        return soft if soft != resource.RLIM_INFINITY else 1 << 20
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        return target
    except (ValueError, OSError):
        return soft


def descriptors_open() -> int:
    """Descriptors this process holds now (Linux /proc; elsewhere a guess of 64)."""
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 64


def connection_cap(limit: int, in_use: int) -> int:
    """Connections that fit under a descriptor limit with `in_use` descriptors held already, leaving a margin
    (at least 1)."""
    return max(1, limit - in_use - max(_MARGIN_MIN, limit // _MARGIN_SHARE))


def cap_for(limit: int, in_use: int, wanted: int, warn: Callable[..., None]) -> int:
    """--max-connections `wanted` (0: what fits under the descriptor limit), never more than fits."""
    fits = connection_cap(limit, in_use)
    if wanted > fits:
        warn("--max-connections %d does not fit the descriptor limit %d: %d instead", wanted, limit, fits)
    return min(wanted or fits, fits)


def over_cap_victim(connections: Dict[int, object], unidentified: Dict[int, object], cap: int,
                    newest: Optional[int], now: float) -> Optional[int]:
    """The fd to cut while more than `cap` connections are open, or None. `connections`: fd -> an object with
    identified, accepted_at, last_active; `unidentified`: those yet to say whose they are, oldest first. The
    oldest of those once it had HANDSHAKE_GRACE_S for that; while all are younger (connections coming faster
    than the cap per grace period) the newest, `newest`, is refused; with none, the least recently active one
    makes room."""
    if len(connections) <= cap:
        return None
    oldest = next((fd for fd in unidentified if fd != newest), None)   # at most two looks: newest is last
    if oldest is not None:
        if newest not in connections or now - connections[oldest].accepted_at >= HANDSHAKE_GRACE_S:
            return oldest
        return newest
    return min(connections, key=lambda fd: connections[fd].last_active)


def enforce(connections: Dict[int, object], unidentified: Dict[int, object], cap: int, drop: Callable[[int], None],
            log: Callable[..., None], newest: Optional[int], now: float) -> None:
    """Cuts connections (`drop(fd)` removes and shuts one) until at most `cap` remain."""
    while True:
        fd = over_cap_victim(connections, unidentified, cap, newest, now)
        if fd is None:
            return
        connection = connections[fd]
        why = ("the newest (the others yet to say whose they are had less than %g s)" % HANDSHAKE_GRACE_S
               if fd == newest and not connection.identified else
               "the oldest that has not said whose it is" if not connection.identified else "least recently active")
        log("cut the connection from %s: %d connections open (bound %d, --max-connections): %s goes",
            connection.address, len(connections), cap, why)
        drop(fd)
