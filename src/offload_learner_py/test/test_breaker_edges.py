"""The breaker's bounds and boundaries (found by `make mutate` over online/breaker.py, #31): which settings are
refused, that a call exactly at slow_call_s and a round trip exactly at max_round_trip_s still count as healthy,
a negative failures_to_open refused, and the breaker's settings fixed once made."""
import dataclasses
import math

import pytest

from offload_learner_py.online.breaker import CLOSED, OPEN, BreakerConfig, LinkBreaker


@pytest.mark.parametrize("field", ["max_round_trip_s", "retry_after_s", "slow_call_s"])
@pytest.mark.parametrize("value", [0.0, -0.5, -1.0, math.nan])
def test_a_duration_that_is_not_positive_is_refused(field, value):
    with pytest.raises(ValueError, match=field):
        BreakerConfig(**{field: value})


@pytest.mark.parametrize("field", ["max_round_trip_s", "retry_after_s", "slow_call_s"])
def test_a_short_positive_duration_is_taken(field):
    assert getattr(BreakerConfig(**{field: 0.25}), field) == 0.25


def test_retry_after_must_be_finite_and_failures_not_negative():
    with pytest.raises(ValueError, match="retry_after_s"):
        BreakerConfig(retry_after_s=math.inf)
    with pytest.raises(ValueError, match="failures_to_open"):
        BreakerConfig(failures_to_open=-1)
    assert not LinkBreaker(BreakerConfig(failures_to_open=0)).enabled
    assert LinkBreaker(BreakerConfig(failures_to_open=1)).enabled


def test_settings_cannot_change_under_a_running_breaker():
    with pytest.raises(dataclasses.FrozenInstanceError):
        BreakerConfig().slow_call_s = 9.0


def test_a_call_exactly_at_slow_call_s_is_a_success():
    breaker = LinkBreaker(BreakerConfig(failures_to_open=1, slow_call_s=0.5), clock=lambda: 100.0)
    breaker.record_call(True, 0.5)
    assert breaker.admit() == CLOSED
    breaker.record_call(True, 0.5000001)
    assert breaker.admit() == OPEN


def test_a_round_trip_exactly_at_the_bound_keeps_the_breaker_closed():
    breaker = LinkBreaker(BreakerConfig(max_round_trip_s=0.8), clock=lambda: 100.0)
    breaker.record_heartbeat(True, 0.8)
    assert breaker.admit() == CLOSED
    breaker.record_heartbeat(True, 0.8000001)
    assert breaker.admit() == OPEN


def test_a_call_without_its_duration_counts_as_a_timely_answer():
    breaker = LinkBreaker(BreakerConfig(failures_to_open=1, slow_call_s=0.25), clock=lambda: 100.0)
    breaker.record_call(True)
    assert breaker.admit() == CLOSED and breaker.trips == 0
