"""Multipart send, receive and readiness for the link's hot path, with pyzmq's own calls underneath.

pyzmq's send_multipart checks every part's type and ORs enum flags per frame, recv_multipart does the same on
the way in, and Socket.poll builds a Poller for one look: about 3, 4 and 1 us a call on this machine, and a plan
on a cached map passes six multipart sends and receives and a dozen looks between the robot and the server's
broker and workers (`make bench-link`, BENCHMARKS.md). Same frames, same flags, same copy rules: a frame under
the socket's copy_threshold (64 KiB) is copied, a larger one (a map's 1 MiB frames) is sent without a copy."""
import zmq

_MORE = int(zmq.SNDMORE)
_POLLIN = int(zmq.POLLIN)
_EVENTS = int(zmq.EVENTS)
NOBLOCK = int(zmq.NOBLOCK)


def send_frames(socket: zmq.Socket, frames, flags: int = 0) -> None:
    """socket.send_multipart(frames, flags, copy=False) for a non-empty list of bytes, memoryviews or Frames."""
    send, more = socket.send, _MORE | flags
    for frame in frames[:-1]:
        send(frame, more, copy=False)
    send(frames[-1], flags, copy=False)


def recv_frames(socket: zmq.Socket, flags: int = 0) -> list:
    """socket.recv_multipart(flags, copy=False): the message's Frames (zmq.Again when none is waiting under
    NOBLOCK or RCVTIMEO; a message's later frames are there once its first is)."""
    frame = socket.recv(flags, copy=False)
    frames = [frame]
    while frame.more:
        frame = socket.recv(copy=False)
        frames.append(frame)
    return frames


def readable(socket: zmq.Socket) -> bool:
    """socket.poll(0) != 0 without a Poller: ZMQ_EVENTS, which processes the socket's pending commands as
    zmq_poll does before it answers."""
    return bool(socket.getsockopt(_EVENTS) & _POLLIN)


def send_or_drop(socket: zmq.Socket, frames, log) -> None:
    """send_frames without blocking: a reply its peer cannot take (not reading, gone) is logged and dropped, never
    fatal for the sender."""
    try:
        send_frames(socket, frames, NOBLOCK)
    except zmq.Again:
        log.warning("reply dropped: client not reading")
    except zmq.ZMQError as error:
        log.warning("reply dropped: %s", error)
