"""The router's two planner sides without ROS: how a side takes calls (a Lane: the local planner one at a time,
the cloud concurrently), one call to a side as the router measures it (SideCaller: the cancelled status, a
stale map asked again, the serving node's CPU and link accounting), a SideResult, and the threads that run the
calls (Workers)."""
import contextvars
import queue
import threading
from typing import Any, Callable, Optional, Tuple

from offload_learner_py.online.router_types import RouterConfig, SideResult, Statuses

PlanCall = Callable[..., Tuple[int, Any]]
Accounting = Callable[[Any], Tuple[float, int, int]]


class Lane:
    """One planner side. `serial`: one call at a time, and a call nobody waits for any more is dropped before
    it starts (or cancelled while it runs) when a newer request needs the side. The requests are the router's:
    each has `outcome.request_id` and a `delivered` event."""

    def __init__(self, serial: bool):
        self.serial = serial
        self.lock = threading.Lock()     # held through a call when serial
        self.state = threading.Lock()
        self.newest = -1
        self.running = {}                # call_id -> the request it serves

    def want(self, request_id: int) -> None:
        with self.state:
            self.newest = max(self.newest, request_id)

    def superseded(self, request_id: int) -> bool:
        with self.state:
            return self.newest > request_id

    def begin(self, call_id: int, req) -> None:
        with self.state:
            self.running[call_id] = req

    def end(self, call_id: int) -> None:
        with self.state:
            self.running.pop(call_id, None)

    def abandoned(self, request_id: int):
        """Calls running for earlier requests whose callers already have their path."""
        with self.state:
            return [call_id for call_id, req in self.running.items()
                    if req.outcome.request_id < request_id and req.delivered.is_set()]

    def calls_of(self, req):
        with self.state:
            return [call_id for call_id, running in self.running.items() if running is req]

    def busy(self) -> bool:
        """A call runs whose caller still waits for it (one that could not be cancelled)."""
        with self.state:
            return self.serial and any(not req.delivered.is_set() for req in self.running.values())


class SideCaller:
    """Calls a planner side and measures the call. `stale(response)` (optional) says why a good answer was
    planned on a map older than the one in force, or None: the side is then asked again until it answers from
    the current map or `config.map_wait_s` has passed. `account(response)` (optional) gives (robot CPU-seconds,
    link bytes sent, link bytes received) that the serving node reported for one call."""

    def __init__(self, statuses: Statuses, config: RouterConfig, clock: Callable[[], float],
                 sleep: Callable[[float], None], stale: Callable[[Any], Optional[str]] = None,
                 account: Accounting = None):
        self.statuses, self.config, self.clock, self.sleep = statuses, config, clock, sleep
        self.stale, self.account = stale, account
        self._waited_out = {}   # id(side) -> the stale-map verdict it was waited out on

    def call(self, side: PlanCall, request, stale_fails: bool, call_id: int = 0) -> SideResult:
        """A side that cannot be called at all answers CLOUD_ERROR (for the local planner too: the caller still
        learns why, and there is nobody else to plan). After the map wait, an answer from the older map counts
        as CLOUD_ERROR when `stale_fails` (the cloud: the robot plans locally), else it is delivered with a note
        (and the STALE_MAP status when the node gave one). A side already waited out on the same stale map is not
        waited for again: one wait per stale map, not one per request."""
        statuses, config = self.statuses, self.config
        began = self.clock()
        cancellable = getattr(side, "cancel", None) is not None
        while True:
            try:
                status, response = side(request, call_id=call_id) if cancellable else side(request)
            except Exception as error:   # the planner node is gone or broke: a failed side, never a lost request
                return SideResult(statuses.cloud_error, None, self.clock() - began, link_failed=True,
                                  raised=f"planner call failed: {type(error).__name__}: {error}")
            if statuses.cancelled is not None and status == statuses.cancelled:
                result = SideResult(int(status), response, self.clock() - began, cancelled=True,
                                    raised="cancelled: a newer request needed this side")
                break
            why = self.stale(response) if self.stale is not None and status == statuses.ok else None
            if why is None:
                result = SideResult(int(status), response, self.clock() - began,
                                    link_failed=statuses.cloud_failed(int(status)))
                break
            waited_out = self._waited_out.get(id(side)) == why
            if waited_out or self.clock() - began >= config.map_wait_s:
                self._waited_out[id(side)] = why
                if not stale_fails:
                    stale = statuses.stale_map
                    result = SideResult(int(status) if stale is None else stale, response, self.clock() - began,
                                        note=f"planned on the last map the planner accepted: {why} (still not "
                                             f"taken after {config.map_wait_s:g} s)")
                else:
                    result = SideResult(statuses.cloud_error, None, self.clock() - began,
                                        raised=f"no path on the map in force within {config.map_wait_s:g} s: {why}")
                break
            self.sleep(config.map_retry_s)
        if self.account is not None and response is not None:
            result.cpu_s, result.bytes_sent, result.bytes_received = self.account(response)
        return result


class Workers:
    """Threads for the router's side calls. A call goes to an idle thread, or to a new one when none is idle (a call
    may wait out a cloud timeout: calls never wait for each other); a thread idle for `idle_s` leaves. A thread
    started per call cost the robot about 80 us of CPU per request, and up to 0.4 ms before the call began on a
    loaded core. Each call runs in a copy of the context it was submitted from (contextvars), as a new thread's
    call would see its starter's state and not the last call's."""

    def __init__(self, name: str, idle_s: float = 30.0):
        self.name, self.idle_s = name, idle_s
        self._tasks = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._idle = 0          # threads waiting for a call, less the calls handed to them and not yet taken
        self.started = 0        # threads started

    def submit(self, function: Callable, *args) -> None:
        task = (contextvars.copy_context(), function, args)
        with self._lock:
            if self._idle > 0:
                self._idle -= 1
                self._tasks.put(task)
                return
            self.started += 1
        threading.Thread(target=self._run, args=(task,), daemon=True, name=self.name).start()

    def _run(self, task) -> None:
        while task is not None:
            context, function, args = task
            context.run(function, *args)
            task = None
            with self._lock:
                self._idle += 1
            try:
                task = self._tasks.get(timeout=self.idle_s)
            except queue.Empty:
                with self._lock:   # a call handed over as the wait ended is taken; else this thread leaves
                    try:
                        task = self._tasks.get_nowait()
                    except queue.Empty:
                        self._idle -= 1
