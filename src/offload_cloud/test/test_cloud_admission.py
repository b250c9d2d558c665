"""The cloud server's admission and connection guard as pure logic: fake requests, a fake clock, fake
TCP counters; no socket, no thread."""
import collections
from dataclasses import dataclass

import pytest

from offload_cloud.admission import Admission, AdmissionConfig
from offload_cloud.connection_guard import STALE, ConnectionGuard
from offload_cloud.protocol import ProtocolError, Status


@dataclass(eq=False)
class FakeRequest:
    client: object
    nbytes: int
    uploads: object = None


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def admission(**config):
    return Admission(AdmissionConfig(**{"workers": 1, "max_queued": 8, "max_queued_bytes": 8000, "max_wait_s": 10.0,
                                        "rate_per_client": 0.0, **config}), Clock())


def wait(adm, queue, name, nbytes=100, idle=False):
    """Admit one request of client `name` and queue it; the refusal's message, or None."""
    client = adm.client(name)

    def displace(victim, why):
        queue.remove(victim)
        adm.dequeued(victim)
    try:
        adm.admit(client, nbytes, queue, 0.0, idle, displace)
    except ProtocolError as error:
        assert error.status == Status.BUSY
        return str(error)
    request = FakeRequest(client, nbytes)
    adm.enqueued(request)
    queue.append(request)
    return None


def test_a_client_alone_may_fill_the_queue_then_gets_busy():
    adm, queue = admission(), collections.deque()
    assert all(wait(adm, queue, "robot1") is None for _ in range(8))
    assert "all 1 workers busy and 8 requests" in wait(adm, queue, "robot1")
    assert adm.waiting == 8 and adm.queued_bytes == 800 and adm.clients_waiting == 1


def test_a_newcomer_takes_the_place_of_the_newest_request_of_the_heaviest_client():
    adm, queue = admission(), collections.deque()
    for _ in range(8):
        wait(adm, queue, "robot1")
    newest = queue[-1]
    assert wait(adm, queue, "robot2") is None
    assert newest not in queue and adm.clients["robot1"].fair_share_refused == 1
    assert [request.client.name for request in queue].count("robot2") == 1 and adm.waiting == 8


def test_fair_share_counts_places_and_bytes():
    adm, queue = admission(), collections.deque()
    wait(adm, queue, "robot2")                                  # two clients share the queue now
    for _ in range(4):
        assert wait(adm, queue, "robot1") is None               # places: 4 of 8 each
    assert "fair share: client robot1 already has 4 requests" in wait(adm, queue, "robot1")
    adm, queue = admission(), collections.deque()
    wait(adm, queue, "robot2")
    assert wait(adm, queue, "robot1", nbytes=3000) is None
    refusal = wait(adm, queue, "robot1", nbytes=1500)           # 4500 bytes > its 4000-byte share
    assert refusal and "(3000 bytes) queued" in refusal
    assert wait(adm, queue, "robot2", nbytes=1500) is None      # the other robot still gets its share


def test_the_rate_limit_applies_only_while_the_server_is_busy():
    adm, queue = admission(rate_per_client=1.0, burst_per_client=1), collections.deque()
    client = adm.client("robot1")
    adm.admit(client, 10, queue, 0.0, True, None)               # the token
    adm.admit(client, 10, queue, 0.0, True, None)               # no token, but a worker is idle: served
    with pytest.raises(ProtocolError, match="rate limit"):
        adm.admit(client, 10, queue, 0.0, False, None)
    adm.clock.now += 1.0
    adm.admit(client, 10, queue, 0.0, False, None)              # refilled


def test_a_request_expected_to_wait_too_long_is_refused_at_once():
    adm, queue = admission(max_wait_s=1.0), collections.deque()
    for _ in range(3):
        wait(adm, queue, "robot1")
    with pytest.raises(ProtocolError, match="about 1.50 s of work"):
        adm.admit(adm.client("robot1"), 10, queue, 0.5, False, None)


def test_each_busy_is_counted_under_its_reason():
    """The BUSY reasons STATS and the metrics show: one count per BUSY reply, under the rule that refused it."""
    adm, queue = admission(), collections.deque()
    for _ in range(8):
        wait(adm, queue, "robot1")
    wait(adm, queue, "robot1")                                  # the queue is full
    assert adm.busy == {"queue_full": 1}
    for _ in range(4):
        wait(adm, queue, "robot2")                              # each takes robot1's newest place: robot1 gets BUSY
    assert adm.busy == {"queue_full": 1, "displaced": 4}
    wait(adm, queue, "robot2")                                  # robot2 holds its share, 4 of 8
    assert adm.busy == {"queue_full": 1, "displaced": 4, "fair_share": 1}
    adm, queue = admission(max_wait_s=1.0, rate_per_client=1.0, burst_per_client=1), collections.deque()
    for _ in range(3):
        wait(adm, queue, "robot1", idle=True)                   # the token, then two over the rate with one waiting
    with pytest.raises(ProtocolError):
        adm.admit(adm.client("robot1"), 10, queue, 2.0, False, None)   # 1 waiting x 2 s of work > 1 s
    with pytest.raises(ProtocolError):
        adm.charge_stats(adm.client("robot1"))
    assert adm.busy == {"rate_limit": 3, "expected_wait": 1}


def test_dequeued_and_resized_keep_the_accounting():
    adm, queue = admission(), collections.deque()
    wait(adm, queue, "robot1", nbytes=500)
    wait(adm, queue, "robot2", nbytes=300)
    adm.resized(queue[0], 100)
    assert adm.queued_bytes == 400 and adm.clients["robot1"].waiting_bytes == 100
    adm.dequeued(queue.popleft())
    assert (adm.waiting, adm.queued_bytes, adm.clients_waiting) == (1, 300, 1)


class FakeTcp:
    def __init__(self):
        self.received, self.unread, self.cut = {}, {}, []

    def __call__(self, fd):
        return self.received.get(fd)


def guard(limit=1000, total=2500, per_key=1500, **options):
    tcp = FakeTcp()
    return ConnectionGuard(limit, total, per_key, lambda *args: None, received=tcp, cut=tcp.cut.append,
                           unread=lambda fd: tcp.unread.get(fd, 0), **options), tcp


def test_a_connection_over_its_own_bound_is_cut():
    g, tcp = guard()
    tcp.received.update({3: 0, 4: 0})
    g.accepted(3)
    g.accepted(4)
    tcp.received.update({3: 1001, 4: 1000})
    g.check()
    assert tcp.cut == [3] and set(g.connections) == {4} and g.cuts == 1
    g.delivered(4)                                              # a message came: the count starts again
    tcp.received[4] = 1900
    g.check()
    assert tcp.cut == [3]


def test_the_largest_holders_are_cut_until_all_are_under_the_total():
    g, tcp = guard()
    for fd in (3, 4, 5, 6):
        tcp.received[fd] = 0
        g.accepted(fd)
    tcp.received.update({3: 900, 4: 800, 5: 700, 6: 600})      # 3000 held, over 2500
    g.check()
    assert tcp.cut == [3] and set(g.connections) == {4, 5, 6}


def test_one_keys_connections_are_bounded_together():
    g, tcp = guard(total=10_000)
    for fd in (3, 4, 5, 6):
        tcp.received[fd] = 0
        g.accepted(fd)
    for fd in (3, 4, 5):
        g.connections[fd].user = b"robot1-key"
    g.connections[6].user = b"robot2-key"
    tcp.received.update({3: 900, 4: 500, 5: 400, 6: 900})      # robot1: 1800 held, over 1500
    g.check()
    assert tcp.cut == [3] and set(g.connections) == {4, 5, 6}   # robot2's 900 are its own business


def test_before_its_first_message_a_connection_may_have_only_a_first_message_read():
    g, tcp = guard(limit=10_000_000, total=100_000_000, per_key=50_000_000, first_limit_bytes=100_000)
    for fd in (3, 4, 5, 6):
        tcp.received[fd] = 0
        g.accepted(fd)
    g.delivered(5)                                              # 5 said whose it is
    tcp.received.update({3: 500_000, 4: 500_000, 5: 500_000, 6: 100_000})
    tcp.unread[4] = 450_000                                     # the kernel holds most of 4's: libzmq read 50 kB
    g.check(drained=lambda: False)      # a message waits for the broker (3's first, maybe): nobody is judged yet
    assert tcp.cut == []
    g.check()
    assert tcp.cut == [3] and set(g.connections) == {4, 5, 6}   # 5 holds 500 kB as a known key may; 6 is at the bound


def test_a_first_message_waiting_for_the_broker_is_judged_after_every_connection_had_its_turn():
    """A flood of messages from other connections keeps the broker busy: a connection past its first message is
    still judged, once the broker has read as many messages as there are connections since it was seen."""
    g, tcp = guard(limit=10_000_000, total=100_000_000, per_key=50_000_000, first_limit_bytes=100_000)
    for fd in (3, 4, 5):
        tcp.received[fd] = 0
        g.accepted(fd)
    tcp.received[3] = 500_000
    busy = lambda: False                                        # noqa: E731
    g.check(busy)                       # seen past its first bytes: the broker's turns are counted from here
    g.delivered(4)
    g.delivered(5)
    g.check(busy)
    assert tcp.cut == []                                        # two turns of three connections
    g.delivered(4)
    g.check(busy)
    assert tcp.cut == [3]


def test_connections_yet_to_say_whose_they_are_share_one_budget_and_the_oldest_go_first():
    clock = [0.0]
    g, tcp = guard(limit=10_000_000, total=100_000_000, per_key=50_000_000, first_limit_bytes=100_000,
                   unidentified_limit_bytes=250_000, clock=lambda: clock[0])
    for fd in (3, 4, 5, 6):
        clock[0] += 1.0
        tcp.received[fd] = 0
        g.accepted(fd)
    tcp.received.update({3: 90_000, 4: 90_000, 5: 90_000, 6: 90_000})   # each under its own bound, 360 kB together
    g.check()
    assert tcp.cut == [3, 4] and set(g.connections) == {5, 6}


def test_over_the_total_the_connections_yet_to_say_whose_they_are_go_first():
    g, tcp = guard(limit=10_000, total=2500, per_key=10_000, first_limit_bytes=5000, unidentified_limit_bytes=5000)
    for fd in (3, 4, 5):
        tcp.received[fd] = 0
        g.accepted(fd)
    g.delivered(3)
    tcp.received.update({3: 1500, 4: 700, 5: 600})             # 2800 held; the robot that said whose holds the most
    g.check()
    assert tcp.cut == [4] and set(g.connections) == {3, 5}


def test_a_key_over_its_connections_loses_its_least_recently_active_one():
    """A connection whose peer vanished without a word (power loss, a NAT that forgot it) must not lock the
    key out: the newest connection goes on and the one idle longest makes room."""
    clock = [0.0]
    g, tcp = guard(key_connections=2, clock=lambda: clock[0])
    for fd in (3, 4, 5, 6, 7):
        tcp.received[fd] = 0
        g.accepted(fd)
    for fd in (3, 4):
        clock[0] += 1.0
        g.delivered(fd)
        g.identify(fd, g.connections[fd], b"robot1-key")
    g.identify(6, g.connections[6], b"robot2-key")
    assert tcp.cut == []
    clock[0] += 1.0
    g.delivered(3)                                              # 3 is active again: 4 is now the idlest
    clock[0] += 1.0
    g.delivered(5)
    g.identify(5, g.connections[5], b"robot1-key")
    assert tcp.cut == [4] and set(g.connections) == {3, 5, 6, 7}   # the newest goes on
    g.identify(3, g.connections[3], b"robot1-key")             # its next messages pass
    assert tcp.cut == [4]


def test_many_idle_connections_do_not_put_the_judgement_off():
    clock = [0.0]
    g, tcp = guard(limit=10_000_000, total=100_000_000, per_key=50_000_000, first_limit_bytes=100_000,
                   clock=lambda: clock[0])
    for fd in range(3, 103):                                    # 100 connections, 99 of them idle
        tcp.received[fd] = 0
        g.accepted(fd)
    tcp.received[3] = 500_000
    busy = lambda: False                                        # noqa: E731
    g.check(busy)
    g.delivered(4)
    clock[0] += 1.0
    g.check(busy)
    assert tcp.cut == []                                        # one turn of 100, 1 s: its first message may wait
    clock[0] += 1.0
    g.check(busy)
    assert tcp.cut == [3]                                       # FIRST_MESSAGE_WAIT_S: no first message waits that long


def test_a_message_an_earlier_connection_on_the_same_fd_left_waiting_is_credited_to_none():
    """libzmq may still hand the broker messages of a connection that closed, stamped with its fd, after a new
    connection took that fd: the ROUTER's pipe numbers tell them apart (wrapping at 2^32)."""
    g, tcp = guard()
    tcp.received[7] = 0
    g.accepted(7)
    pipe = lambda number: b"\x00" + number.to_bytes(4, "big")   # noqa: E731
    assert g.delivered(7, pipe(1000)) is g.connections[7]
    assert g.delivered(7, pipe(999)) is STALE                   # the earlier connection's, read late: dropped
    assert g.delivered(7, b"\x07chosen") is None                # a routing id a peer chose itself
    assert g.delivered(7, pipe(1000)) is g.connections[7]
    tcp.received[8] = 0
    g.accepted(8)
    assert g.delivered(8, pipe(2**32 - 1)) is g.connections[8]
    assert g.delivered(8, pipe(1)) is g.connections[8]          # the counter wrapped: a newer pipe
    assert g.delivered(8, pipe(2**32 - 1)) is STALE
