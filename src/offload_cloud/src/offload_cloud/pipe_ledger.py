"""Which connection a message came from when libzmq reuses descriptors: the connection guard's record of the
connections that closed, by fd.

libzmq stamps every message with the fd it came on (SRCFD) and its ROUTER gives every connection's pipe a
number, in the order the pipes attach (the routing id: a zero byte and a 32-bit counter). A connection that
closes may still have messages waiting in its pipe; the broker reads them after it learnt of the close, maybe
after a new connection took the same fd. Since a new connection is accepted after the old one's descriptor
was closed, its pipe attaches later and has the larger number. So a message on a reused fd is:
- stale (its connection closed: nobody to answer) when its number is at most that of a closed connection of
  the fd whose number is known (it delivered a message before it closed);
- doubtful when the closed connection never delivered a message (its number is unknown) and the message
  could be its first as well as the new connection's: it counts as the new connection's delivered message for
  the byte bounds, but its key names no connection. Two numbers met on the fd settle it (the older is the
  closed one's); so does the closed connection's pipe being empty for sure: libzmq
  signals the close after the connection's last message entered its pipe, so once the broker has found no
  message waiting (at least SETTLE_S after it learnt of the close: libzmq flushes the pipe just after the
  signal), or has read enough messages for every pipe to have had `hwm + 1` turns, or FIRST_MESSAGE_WAIT_S
  have passed, no message of the closed connection is left;
- else the current connection's."""
import time
from dataclasses import dataclass
from typing import Callable, Dict, Optional

OK, STALE, DOUBTFUL = "ok", "stale", "doubtful"
# However many connections wait their turn, a first message waits for the broker no longer than this (a broker
# that far behind answers BUSY, --max-wait-s); the guard's first-message judgement uses it too.
FIRST_MESSAGE_WAIT_S = 2.0
SETTLE_S = 0.05   # libzmq flushes a closed connection's pipe microseconds after it signals the close


def pipe_number(routing_id: bytes) -> Optional[int]:
    """The number libzmq's ROUTER gave a pipe (its routing id: a zero byte and a 32-bit counter), or None for a
    routing id a peer chose itself (this project's clients never do)."""
    if len(routing_id) != 5 or routing_id[0] != 0:
        return None
    return int.from_bytes(routing_id[1:], "big")


def newer(number: int, other: int) -> bool:
    """`number` was given after `other` (32-bit serial arithmetic: the counter starts at random and wraps)."""
    return number != other and (number - other) % (1 << 32) < (1 << 31)


@dataclass
class Retired:
    floor: Optional[int]        # messages on the fd numbered at most this are stale
    closed_at: float            # when the broker learnt of the last close
    messages_at: int            # broker messages read by then
    doubtful: bool              # a connection closed with its number unknown: its first message may still come
    seen: Optional[int] = None  # the number of a doubtful message met on the fd since


class PipeLedger:
    """fd -> Retired, and the classification of a message by its fd and pipe number (the broker's thread)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, receive_hwm: int = 4):
        self.clock, self.receive_hwm = clock, receive_hwm
        self.retired: Dict[int, Retired] = {}
        self.unsettled: Dict[int, Retired] = {}   # the doubtful records, in the order of their closes

    def retire(self, fd: int, number: Optional[int], messages: int) -> None:
        """A connection on `fd` closed; `number` is its pipe's, when it delivered a message (else None)."""
        old = self.retired.get(fd)
        floor = old.floor if old is not None else None
        if number is not None and (floor is None or newer(number, floor)):
            floor = number
        doubtful = number is None or (old is not None and old.doubtful)
        record = self.retired[fd] = Retired(floor, self.clock(), messages, doubtful,
                                            old.seen if old is not None else None)
        self.unsettled.pop(fd, None)
        if doubtful:
            self.unsettled[fd] = record

    def classify(self, fd: int, number: int, current: Optional[int], messages: int, turns: int) -> str:
        """OK, STALE or DOUBTFUL for a message of pipe `number` on `fd`, whose open connection's number is
        `current` (None: it delivered nothing yet, or the fd has no open connection the guard knows)."""
        record = self.retired.get(fd)
        if record is None:
            return OK
        if record.floor is not None and not newer(number, record.floor):
            return STALE
        if not record.doubtful or current is not None:
            return OK
        if self._settled(record, messages, turns):
            self._settle(fd, record)
            return OK
        if record.seen is None or record.seen == number:
            record.seen = number
            return DOUBTFUL
        older, newest = (record.seen, number) if newer(number, record.seen) else (number, record.seen)
        record.floor = older if record.floor is None or newer(older, record.floor) else record.floor
        self._settle(fd, record)
        return OK if number == newest else STALE

    def credited(self, fd: int) -> None:
        """The fd's open connection delivered a message numbered above the floor: its own number now tells the
        closed connections' messages (older numbers) apart."""
        if fd not in self.unsettled:
            self.retired.pop(fd, None)

    def drained(self) -> None:
        """The broker found no message waiting: the pipes of connections closed more than SETTLE_S ago are
        empty."""
        now = self.clock()
        while self.unsettled:
            fd, record = next(iter(self.unsettled.items()))   # the oldest close first
            if now - record.closed_at < SETTLE_S:
                break
            self._settle(fd, record)

    def settle_due(self, messages: int, turns: int) -> None:
        """Settles the records whose closed connections' messages must all have been read by now."""
        while self.unsettled:
            fd, record = next(iter(self.unsettled.items()))   # the oldest close first: later ones are due later
            if not self._settled(record, messages, turns):
                break
            self._settle(fd, record)

    def _settled(self, record: Retired, messages: int, turns: int) -> bool:
        return (self.clock() - record.closed_at >= FIRST_MESSAGE_WAIT_S
                or messages - record.messages_at >= (self.receive_hwm + 1) * (turns + 1))

    def _settle(self, fd: int, record: Retired) -> None:
        record.doubtful, record.seen = False, None
        self.unsettled.pop(fd, None)
        if record.floor is None:   # nothing left to tell apart on this fd
            del self.retired[fd]
