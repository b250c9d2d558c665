"""The router's side calls run on reused threads (online/sides.Workers), not a thread started per call: a request
one after another keeps a thread, a call that blocks never holds up the next, idle threads leave, and each call
sees its starter's context, not the previous call's."""
import contextvars
import threading
import time

from offload_learner_py.core.policies import AlwaysCloud
from offload_learner_py.online.router_types import RouterConfig
from offload_learner_py.online.sides import Workers
from routertools import OK, STATE, STATUSES, FakePlanner, Recorder, VirtualClock, finish, wired_router


class ThreadRecorder(FakePlanner):
    """A fake planner that keeps the thread of each call (the objects themselves: an exited thread's ident may be
    reused by the next)."""

    def __init__(self, clock, cost_s):
        super().__init__(clock, cost_s)
        self.threads = []

    def __call__(self, request):
        self.threads.append(threading.current_thread())
        return super().__call__(request)


def run_and_wait(workers, function):
    done = threading.Event()
    workers.submit(lambda: (function(), done.set()))
    assert done.wait(10)


def test_requests_one_after_another_reuse_one_thread():
    clock = VirtualClock()
    cloud = ThreadRecorder(clock, 0.05)
    router = wired_router(AlwaysCloud("cloud"), FakePlanner(clock, 0.1), cloud, STATUSES,
                          RouterConfig(probe_while_warming_up=False), on_outcome=Recorder().outcome, clock=clock)
    for _ in range(20):
        assert router.route("req", STATE).status == OK
        assert router.wait_idle(10)
        time.sleep(0.01)   # the call's thread back in the pool (it marks itself idle after the request is done)
    finish(router)
    assert len(cloud.threads) == 20
    assert len(set(cloud.threads)) <= 2   # one per call before


def test_a_blocked_call_does_not_hold_up_the_next():
    workers = Workers("test")
    gate, ran = threading.Event(), threading.Event()
    workers.submit(gate.wait, 10)
    workers.submit(ran.set)
    assert ran.wait(10)
    gate.set()
    assert workers.started == 2


def test_idle_threads_leave_and_new_calls_still_run():
    workers = Workers("test-idle", idle_s=0.05)
    run_and_wait(workers, lambda: None)
    deadline = time.monotonic() + 10
    while any(t.name == "test-idle" for t in threading.enumerate()) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not any(t.name == "test-idle" for t in threading.enumerate())
    run_and_wait(workers, lambda: None)
    assert workers.started == 2


def test_a_call_sees_its_starters_context_not_the_last_calls():
    workers = Workers("test-context")
    var = contextvars.ContextVar("var", default="unset")
    seen = []
    run_and_wait(workers, lambda: (seen.append(var.get()), var.set("left by the first call")))
    var.set("the starter's")
    run_and_wait(workers, lambda: seen.append(var.get()))
    assert seen == ["unset", "the starter's"]
    assert workers.started == 1
