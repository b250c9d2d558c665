"""A map's cells on the wire: frames of at most FRAME_MAX_BYTES each, joined back into one grid by the server.

libzmq decrypts a CURVE frame whole, in one call, on the I/O thread that owns the connection, and that thread
serves its other connections only between frames. A 64 MiB map in one frame held it for the decryption and its
64 MiB copies, hundreds of milliseconds on a loaded 2-core host, while another robot's ping on the same thread
waited (#31 Medium 8: one key's 64 MiB plans on 8 connections took another robot's ping p99 from 4 ms idle to 410
ms). In frames of 1 MiB the thread decrypts a frame at a time and reads its other connections in between: the same
flood gave 42 ms, against 28 ms when it went to another server process (the README has the figures). The server
refuses larger frames (libzmq's MAXMSGSIZE is --max-frame-mib), so no key can hold an I/O thread longer.
"""
from typing import List, Sequence

import numpy as np

# A client splits a map's cells into frames of this size (the last one shorter); every other frame of a request
# is far smaller. The server's default bound on a frame (--max-frame-mib).
FRAME_MAX_BYTES = 1 << 20
# What CURVE adds to a frame on the wire (a MESSAGE command: name, nonce, box MAC and flags, 33 bytes), with room
# to spare: libzmq's MAXMSGSIZE counts the frame as it arrives, before decryption.
FRAME_SLACK_BYTES = 4096


def split(buffer) -> List[memoryview]:
    """Views of `buffer` (no copy) of at most FRAME_MAX_BYTES each; one empty frame for an empty buffer."""
    view = memoryview(buffer).cast("B")
    if view.nbytes <= FRAME_MAX_BYTES:
        return [view]
    return [view[start:start + FRAME_MAX_BYTES] for start in range(0, view.nbytes, FRAME_MAX_BYTES)]


def total_bytes(frames: Sequence) -> int:
    return sum(memoryview(frame).nbytes for frame in frames)


def join(frames: Sequence) -> memoryview:
    """The cells of `frames` as one buffer: the frame itself when there is one (no copy), else a new array the
    frames are copied into. numpy copies without the GIL, so a worker joining 64 MiB does not hold up the
    broker (bytes.join would)."""
    if len(frames) == 1:
        return memoryview(frames[0]).cast("B")
    cells = np.empty(total_bytes(frames), np.uint8)
    start = 0
    for frame in frames:
        part = np.frombuffer(frame, np.uint8)
        cells[start:start + part.size] = part
        start += part.size
    return memoryview(cells)
