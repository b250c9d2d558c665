"""What the router records about a side when its own bookkeeping breaks, when a call started late, and for a
request it could not decide (found unchecked by `make mutate` over online/router.py, #31): the times are the
side's own, a broken accounting counts as a link failure, and an undecided request was the local planner's for
certain."""
import pytest

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.policies import AlwaysCloud
from offload_learner_py.online.breaker import BreakerConfig
from offload_learner_py.online.router_types import RouterConfig
from routertools import OK, STATE, STATUSES, FakePlanner, Recorder, VirtualClock, finish, wired_router


def _router(clock, local, cloud, account=None, **config):
    recorder = Recorder()
    config.setdefault("probe_while_warming_up", False)
    router = wired_router(AlwaysCloud("cloud"), local, cloud, STATUSES, RouterConfig(**config),
                          on_decision=recorder.decision, on_outcome=recorder.outcome, clock=clock, account=account)
    return router, recorder


def test_a_side_that_started_late_records_when_it_started_and_its_own_latency():
    """The request reached the node 1 s (virtual) before it was routed: the call started 1 s after the arrival,
    and its latency is its own 0.2 s, not the time since the arrival."""
    clock = VirtualClock()
    router, recorder = _router(clock, FakePlanner(clock, 0.1), FakePlanner(clock, 0.2))
    assert router.route("req", STATE, arrived=-1.0).status == OK
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.cloud.started_after_s == pytest.approx(1.0)
    assert outcome.cloud_s == pytest.approx(0.2)


def test_an_accounting_that_raises_is_a_failed_call_of_its_own_duration_that_counts_for_the_breaker():
    """A broken `account()` (the node's bookkeeping, after the cloud answered): the request still gets a path
    (from the local planner), the cloud call counts as a link failure for the breaker, and its latency is the
    call's own 0.2 s even though the request arrived 1 s earlier."""
    clock = VirtualClock()

    def account(response):
        if response["side"] is cloud:
            raise KeyError("bytes_sent")
        return 0.0, 0, 0
    local, cloud = FakePlanner(clock, 0.1), FakePlanner(clock, 0.2)
    router, recorder = _router(clock, local, cloud, account=account, breaker=BreakerConfig(failures_to_open=1))
    result = router.route("req", STATE, arrived=-1.0)
    finish(router)
    assert result.status == OK and result.response["side"] is local
    (outcome,) = recorder.outcomes
    assert outcome.cloud.link_failed and "KeyError" in outcome.cloud.raised
    assert outcome.cloud.seconds == pytest.approx(0.2)
    assert router.breaker.is_open, "one failure opens a breaker of failures_to_open 1"


def test_a_request_without_a_state_is_the_local_planners_with_propensity_one():
    clock = VirtualClock()
    router, recorder = _router(clock, FakePlanner(clock, 0.1), FakePlanner(clock, 0.2))
    assert router.route("req", None).status == OK
    finish(router)
    (outcome,) = recorder.outcomes
    assert outcome.decision.action == LOCAL and outcome.decision.propensity == 1.0
    assert outcome.delivered == LOCAL and outcome.cloud is None and CLOUD != LOCAL
