"""The link breaker: opens on consecutive failures or a bad heartbeat, trials while open, closes on health."""
import pytest

from offload_learner_py.online.breaker import CLOSED, OPEN, TRIAL, BreakerConfig, LinkBreaker


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_opens_after_consecutive_failures_only():
    breaker = LinkBreaker(BreakerConfig(failures_to_open=3), clock=Clock())
    for succeeded in (False, False, True, False, False):
        breaker.record_call(succeeded)
    assert breaker.admit() == CLOSED            # a success in between resets the count
    breaker.record_call(False)
    assert breaker.admit() == OPEN and breaker.trips == 1 and "3 cloud failures" in breaker.reason


def test_heartbeat_opens_when_unreachable_or_too_slow_and_closes_when_healthy():
    breaker = LinkBreaker(BreakerConfig(max_round_trip_s=0.5), clock=Clock())
    breaker.record_heartbeat(True, 0.6)
    assert breaker.admit() == OPEN and "round trip" in breaker.reason
    breaker.record_heartbeat(True, 0.4)
    assert breaker.admit() == CLOSED
    breaker.record_heartbeat(False, 5.0)
    assert breaker.admit() == OPEN and "unreachable" in breaker.reason
    breaker.record_heartbeat(True, float("nan"))   # a NaN round trip is not healthy
    assert breaker.is_open


def test_one_trial_per_retry_period_while_open():
    clock = Clock()
    breaker = LinkBreaker(BreakerConfig(failures_to_open=1, retry_after_s=2.0), clock=clock)
    breaker.record_call(False)
    assert breaker.admit() == OPEN
    clock.now = 1.9
    assert breaker.admit() == OPEN
    clock.now = 2.0
    assert breaker.admit() == TRIAL and breaker.admit() == OPEN   # one trial, then open again
    breaker.record_call(True)
    assert breaker.admit() == CLOSED


def test_disabled_breaker_never_opens():
    breaker = LinkBreaker(BreakerConfig(failures_to_open=0))
    for _ in range(10):
        breaker.record_call(False)
    breaker.record_heartbeat(False, 5.0)
    assert breaker.admit() == CLOSED


@pytest.mark.parametrize("kwargs", [{"failures_to_open": -1}, {"max_round_trip_s": 0.0},
                                    {"retry_after_s": float("inf")}])
def test_config_rejects_bad_values(kwargs):
    with pytest.raises(ValueError):
        BreakerConfig(**kwargs)


def test_the_retry_period_runs_from_when_the_breaker_opened():
    """A breaker opened at t = 100 gives its first trial at 100 + retry_after_s, not at once (#31: with every
    test opening at t = 0, forgetting the opening time went unnoticed)."""
    clock = Clock()
    clock.now = 100.0
    breaker = LinkBreaker(BreakerConfig(failures_to_open=1, retry_after_s=5.0), clock=clock)
    breaker.record_call(False)
    clock.now = 101.0
    assert breaker.admit() == OPEN
    clock.now = 105.0
    assert breaker.admit() == TRIAL


def test_slow_answers_count_as_failures():
    """#31 Medium 10: a cloud that pings fine but takes 4.5 s a plan never tripped the breaker (67 of 100 requests
    waited 4.5 s). An answer slower than slow_call_s counts as a failure."""
    breaker = LinkBreaker(BreakerConfig(failures_to_open=3, slow_call_s=2.0), clock=Clock())
    for _ in range(2):
        breaker.record_call(True, 4.5)
    breaker.record_call(True, 0.1)                 # a timely answer resets the count
    for _ in range(3):
        breaker.record_call(True, 4.5)
    assert breaker.admit() == OPEN and "slow" in breaker.reason


def test_a_healthy_heartbeat_does_not_undo_failed_calls():
    """#31 Low: an erroring cloud that pings fine re-closed the breaker at each heartbeat (35 trips in 200
    requests). Opened by calls, only a trial's timely answer closes it; and a heartbeat between failures does not
    reset their count (two failures, a heartbeat, one failure: open)."""
    clock = Clock()
    breaker = LinkBreaker(BreakerConfig(failures_to_open=3, retry_after_s=5.0), clock=clock)
    breaker.record_call(False)
    breaker.record_call(False)
    breaker.record_heartbeat(True, 0.01)
    breaker.record_call(False)
    assert breaker.admit() == OPEN
    breaker.record_heartbeat(True, 0.01)
    assert breaker.is_open and breaker.trips == 1, "a ping says nothing of the plans that failed"
    clock.now = 5.0
    assert breaker.admit() == TRIAL
    breaker.record_call(True, 0.2)
    assert breaker.admit() == CLOSED


def test_a_link_the_heartbeat_found_down_closes_when_the_heartbeat_finds_it_back():
    breaker = LinkBreaker(BreakerConfig(failures_to_open=3), clock=Clock())
    for _ in range(3):
        breaker.record_call(False)
    breaker.record_heartbeat(False, 5.0)           # the link itself is down: its return may close the breaker
    breaker.record_heartbeat(True, 0.02)
    assert breaker.admit() == CLOSED


def test_a_cloud_answers_round_trip_reads_like_a_heartbeats_and_a_missing_answer_is_left_to_the_calls():
    """The bridge rests its heartbeat while plans measure the link: a slow link seen only by the plans' answers
    must still open the breaker, and a healthy answer close one the round trip opened; a plan the cloud did not
    answer is one failed call (record_call), never an unreachable heartbeat that opens at once."""
    breaker = LinkBreaker(BreakerConfig(max_round_trip_s=0.5, failures_to_open=3), clock=Clock())
    breaker.record_round_trip(False, False, 5.0)   # a request's timeout
    assert breaker.admit() == CLOSED
    breaker.record_round_trip(False, True, 0.7)    # a request's answer over a slow link
    assert breaker.admit() == OPEN and "round trip 0.700 s" in breaker.reason
    breaker.record_round_trip(False, True, 0.1)
    assert breaker.admit() == CLOSED
    breaker.record_round_trip(True, False, 1.0)    # a heartbeat nobody answered
    assert breaker.admit() == OPEN and "unreachable" in breaker.reason
