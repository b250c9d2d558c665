"""The caller takes its path before the side thread that delivered it goes on (online/router.py, _settle). That
thread holds the interpreter: what it does next (the learner, the node's records, a probe's other side) kept the
woken caller waiting, 0.5 ms at the median and 4-6 ms at the 90th percentile on a loaded robot, after delivered_s
had been taken. No timing here: the interpreter is made to switch threads only where one blocks."""
import sys
import time

from offload_learner_py.core.policies import AlwaysLocal
from routertools import STATE, FakePlanner, VirtualClock, finish, make_router


def test_the_caller_has_its_path_before_the_side_that_delivered_it_goes_on():
    clock = VirtualClock()
    router, recorder = make_router(AlwaysLocal("local"), FakePlanner(clock, 0.1), FakePlanner(clock, 0.05), clock)
    finished = []

    def outcome_that_holds_the_interpreter(outcome):
        end = time.perf_counter() + 0.3
        while time.perf_counter() < end:    # no blocking call: the interpreter is not given up
            pass
        finished.append(outcome.request_id)
    router.on_outcome = outcome_that_holds_the_interpreter
    interval = sys.getswitchinterval()
    sys.setswitchinterval(30.0)             # no forced switch within the test: a thread runs until it blocks
    try:
        delivered = router.route("req", STATE)
        finished_before_the_caller_had_its_path = list(finished)
    finally:
        sys.setswitchinterval(interval)
    finish(router)
    assert delivered.response["side"] is not None
    assert finished_before_the_caller_had_its_path == [], \
        "the side that delivered went on to the outcome before the caller took its path"
    assert finished == [recorder.routings[0].request_id]


def test_a_failing_on_delivered_hook_loses_neither_the_path_nor_the_outcome():
    clock = VirtualClock()
    router, recorder = make_router(AlwaysLocal("local"), FakePlanner(clock, 0.1), FakePlanner(clock, 0.05), clock)

    def broken(routing):
        raise RuntimeError("a broken record")
    router.on_delivered = broken
    for _ in range(2):
        assert router.route("req", STATE).response is not None
        assert router.wait_idle(30), "the request never finished: its outcome was lost with the hook's error"
    finish(router)
    assert len(recorder.outcomes) == 2
