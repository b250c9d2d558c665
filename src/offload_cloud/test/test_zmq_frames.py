"""zmq_frames: the hot path's multipart send and receive give what pyzmq's own would, and `readable` what
Socket.poll(0) says."""
import pytest
import zmq

from offload_cloud.zmq_frames import NOBLOCK, readable, recv_frames, send_frames


@pytest.fixture
def pair():
    context = zmq.Context()
    a, b = context.socket(zmq.PAIR), context.socket(zmq.PAIR)
    a.linger = b.linger = 0
    a.bind("inproc://frames")
    b.connect("inproc://frames")
    yield a, b
    a.close(0)
    b.close(0)
    context.term()


def test_frames_cross_whole_and_in_order(pair):
    a, b = pair
    big = bytes(range(256)) * 1024                  # 256 KiB: over pyzmq's copy threshold, sent without a copy
    sent = [b"envelope", memoryview(b"body"), b"", big]
    assert not readable(b) and not b.poll(0)
    send_frames(a, sent)
    assert readable(b) and b.poll(0)
    assert [frame.bytes for frame in recv_frames(b)] == [b"envelope", b"body", b"", big]
    assert not readable(b)
    send_frames(a, [b"one"])
    send_frames(a, [b"two", b"parts"])
    assert [frame.bytes for frame in recv_frames(b)] == [b"one"]
    assert [frame.bytes for frame in recv_frames(b)] == [b"two", b"parts"]


def test_nothing_waiting_is_zmq_again(pair):
    _, b = pair
    with pytest.raises(zmq.Again):
        recv_frames(b, NOBLOCK)
    b.rcvtimeo = 10
    with pytest.raises(zmq.Again):
        recv_frames(b)
