"""Admission's edges the end-to-end tests pass through without looking (found by `make mutate` over admission.py,
#31: 82 of 218 mutants survived test_cloud_admission.py): the STATS rate, the bound on tracked clients, what each
refusal counts, and the boundaries of the byte bound, the expected wait and the token bucket."""
import collections
import dataclasses

import pytest

from offload_cloud import admission as admission_module
from offload_cloud.admission import Admission, AdmissionConfig, Client
from offload_cloud.protocol import ProtocolError, Status
from test_cloud_admission import Clock, FakeRequest, admission, wait


def test_stats_are_charged_to_the_token_bucket_and_counted():
    adm = admission(rate_per_client=1.0, burst_per_client=2)
    client = adm.client("robot1")
    adm.charge_stats(client)
    adm.charge_stats(client)                                     # the burst
    with pytest.raises(ProtocolError, match="over its rate of 1 requests/s") as refused:
        adm.charge_stats(client)
    assert refused.value.status == Status.BUSY and client.rate_limited == 1
    adm.clock.now += 1.0
    adm.charge_stats(client)                                     # one token back after a second
    unlimited = admission(rate_per_client=0.0, burst_per_client=1)
    for _ in range(5):
        unlimited.charge_stats(unlimited.client("robot2"))        # rate 0: no limit


def test_a_rate_refusal_is_counted_once():
    adm, queue = admission(rate_per_client=1.0, burst_per_client=1), collections.deque()
    client = adm.client("robot1")
    adm.admit(client, 10, queue, 0.0, False, None)
    with pytest.raises(ProtocolError):
        adm.admit(client, 10, queue, 0.0, False, None)
    assert client.rate_limited == 1


def test_the_token_bucket_refills_at_the_rate_up_to_the_burst():
    client = Client("robot1", tokens=0.0, refilled=0.0)
    assert not client.take_token(0.5, 1.0, 3)                    # half a token
    assert client.take_token(1.0, 1.0, 3) and client.tokens == 0.0
    assert client.take_token(100.0, 1.0, 3) and client.tokens == 2.0   # capped at the burst, one taken
    assert client.take_token(100.0, 1.0, 3) and client.take_token(100.0, 1.0, 3)
    assert not client.take_token(100.0, 1.0, 3)


def test_tracked_clients_are_bounded_and_the_least_recently_seen_idle_one_goes(monkeypatch):
    monkeypatch.setattr(admission_module, "MAX_TRACKED_CLIENTS", 3)
    adm, queue = admission(), collections.deque()
    wait(adm, queue, "busy")                                     # waiting: never forgotten
    adm.client("idle1")
    adm.client("idle2")
    adm.client("new")
    assert list(adm.clients) == ["busy", "idle2", "new"]
    adm.client("idle2")                                          # seen again: now the most recent
    adm.client("newer")
    assert list(adm.clients) == ["busy", "idle2", "newer"]
    assert admission_module.MAX_TRACKED_CLIENTS == 3 and len(adm.clients) == 3


def test_every_client_waiting_keeps_its_place_beyond_the_bound(monkeypatch):
    monkeypatch.setattr(admission_module, "MAX_TRACKED_CLIENTS", 2)
    adm, queue = admission(), collections.deque()
    wait(adm, queue, "a")
    wait(adm, queue, "b")
    adm.client("c")                                              # nobody idle to forget: tracked anyway
    assert set(adm.clients) == {"a", "b", "c"}


def test_the_byte_bound_admits_a_queue_filled_exactly():
    adm, queue = admission(max_queued_bytes=1000), collections.deque()
    assert wait(adm, queue, "robot1", nbytes=600) is None
    assert wait(adm, queue, "robot1", nbytes=400) is None        # 1000 of 1000: in
    assert "all 1 workers busy" in wait(adm, queue, "robot1", nbytes=1)


def test_a_wait_of_exactly_max_wait_is_accepted():
    adm, queue = admission(max_wait_s=1.0), collections.deque()
    wait(adm, queue, "robot1")
    wait(adm, queue, "robot1")
    adm.admit(adm.client("robot1"), 10, queue, 0.5, False, None)       # 2 x 0.5 s / 1 worker = 1.0 s
    with pytest.raises(ProtocolError, match="about 1.50 s"):
        adm.admit(adm.client("robot1"), 10, queue, 0.75, False, None)
    two = Admission(dataclasses.replace(adm.config, workers=2), Clock())
    for _ in range(3):
        wait(two, queue, "robot1")
    two.admit(two.client("robot1"), 10, queue, 0.6, False, None)      # 3 x 0.6 / 2 = 0.9 s


def test_fair_share_refusals_are_counted_and_a_map_carrier_is_never_displaced():
    adm, queue = admission(), collections.deque()
    wait(adm, queue, "robot2")
    for _ in range(4):
        wait(adm, queue, "robot1")
    assert "fair share" in wait(adm, queue, "robot1")
    assert adm.clients["robot1"].fair_share_refused == 1
    adm, queue = admission(), collections.deque()
    for _ in range(8):
        wait(adm, queue, "robot1")
    for request in queue:
        request.uploads = object()                               # each carries a map others may wait for
    assert "all 1 workers busy" in wait(adm, queue, "robot2")
    assert adm.clients["robot1"].fair_share_refused == 0 and len(queue) == 8


def test_the_byte_bound_holds_after_a_displacement():
    adm, queue = admission(max_queued_bytes=1000), collections.deque()
    for _ in range(5):
        wait(adm, queue, "robot1", nbytes=200)
    # robot2 (share 4 of 8 places) asks for 600 bytes: displacing robot1's newest 200 leaves 800 + 600 > 1000
    assert "all 1 workers busy" in wait(adm, queue, "robot2", nbytes=600)
    assert len(queue) == 5 and adm.queued_bytes == 1000
    assert wait(adm, queue, "robot2", nbytes=200) is None         # 800 + 200 = 1000: displaced and in
    assert adm.queued_bytes == 1000 and adm.clients["robot1"].waiting == 4


def test_a_client_within_its_share_does_not_displace_another_holding_no_more():
    adm, queue = admission(max_queued=4, max_queued_bytes=10 ** 6), collections.deque()
    wait(adm, queue, "robot1")
    wait(adm, queue, "robot1")
    wait(adm, queue, "robot2")
    wait(adm, queue, "robot2")
    # full; robot3's share is 4 // 3 = 1; the heaviest hold 2 > 1: one is displaced
    assert wait(adm, queue, "robot3") is None
    assert sorted(request.client.name for request in queue).count("robot3") == 1
