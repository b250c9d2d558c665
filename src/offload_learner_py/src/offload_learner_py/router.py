"""The online decision loop of the offloading learner, without ROS: per planning request, decide local
or cloud from s_t, call the chosen side (both on a probe step), hand the caller the first good path,
then measure, reward (eq. 10) and learn (Algorithm 1) off the caller's path.

The ROS node injects the two planners as callables `plan(request) -> (status, response)` and the
PlanPath status codes, so this module never imports a message type; tests drive it with fakes.

Probe steps run both sides at once, not one after the other: the caller gets whichever good path
arrives first (a probe never makes a request slower than its faster side), and both latencies are
measured over the same moment of CPU load and link state, which is what the oracle compares. The
slower side finishes in the background; the next request waits for it before it starts, so no two
requests ever share the robot's CPU or the link.
"""
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Tuple

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.reward import CostWeights, cloud_latency_s, reward
from offload_learner_py.state import State

NO_PATH_DELIVERED = 255   # `delivered` when neither side produced a path


@dataclass(frozen=True)
class Statuses:
    """The PlanPath status codes the router must tell apart (the node passes the message's constants)."""
    ok: int
    cloud_timeout: int
    cloud_error: int

    def cloud_failed(self, status: int) -> bool:
        """The cloud could not answer; the request itself may be fine, so plan it locally."""
        return status in (self.cloud_timeout, self.cloud_error)


@dataclass(frozen=True)
class Decision:
    action: int
    propensity: float
    q_local: float = float("nan")
    q_cloud: float = float("nan")


@dataclass
class SideResult:
    """One planner call as the learner saw it: status, response, request-to-reply seconds."""
    status: int
    response: Any
    seconds: float
    raised: Optional[str] = None    # no usable answer (planner node down, a stale map): why
    note: Optional[str] = None      # a usable answer with a caveat (planned on the last map the planner took)


@dataclass
class Outcome:
    request_id: int
    state: Optional[State]
    decision: Decision
    probe: bool
    delivered: int                  # LOCAL, CLOUD or NO_PATH_DELIVERED
    delivered_s: float              # request to path as the caller saw it
    local: Optional[SideResult] = None
    cloud: Optional[SideResult] = None
    local_s: Optional[float] = None     # l_local when measured
    cloud_s: Optional[float] = None     # l_cloud when measured (timeout when the cloud failed)
    cloud_timeout: bool = False
    reward: Optional[float] = None
    loss: Optional[float] = None
    learned: bool = False           # a transition went to the learner


class DecisionPolicy:
    """What the router asks of a policy. Baselines never learn."""
    name = "policy"
    learns = False

    def decide(self, state: State) -> Decision:
        raise NotImplementedError

    def learn(self, state: State, action: int, reward_value: float) -> Optional[float]:
        return None

    @property
    def steps(self) -> int:
        return 0

    def stats(self) -> dict:
        return {"steps": self.steps, "gradient_steps": 0, "replay_size": 0, "epsilon": 0.0}


class FixedPolicy(DecisionPolicy):
    def __init__(self, action: int, name: str):
        self.action, self.name = action, name

    def decide(self, state):
        return Decision(self.action, 1.0)


class RandomDecision(DecisionPolicy):
    name = "random"

    def __init__(self, seed: int = 1):
        self.rng = np.random.default_rng(seed)

    def decide(self, state):
        return Decision(int(self.rng.integers(0, 2)), 0.5)


class InputSizeThresholdDecision(DecisionPolicy):
    """Offload when d_t is above a fixed threshold (the rule the paper's policy came to resemble)."""
    name = "threshold"

    def __init__(self, threshold: float):
        if not (threshold >= 0 and math.isfinite(threshold)):
            raise ValueError(f"input-size threshold must be finite and >= 0, got {threshold}")
        self.threshold = threshold

    def decide(self, state):
        return Decision(CLOUD if state.input_size > self.threshold else LOCAL, 1.0)


class DQNDecision(DecisionPolicy):
    """Algorithm 1 online. Decisions read a numpy snapshot of the Q-network (FastDecision), rebuilt
    after each gradient step, so deciding never waits for training or takes the torch path. With
    learn false the greedy policy of the loaded model is used and nothing is trained."""
    name = "dqn"

    def __init__(self, agent, learn: bool = True, seed: Optional[int] = None):
        self.agent = agent
        self.learns = learn
        self.rng = np.random.default_rng(agent.config.seed if seed is None else seed)
        self._lock = threading.Lock()
        self._pending: Optional[Tuple[np.ndarray, int, float]] = None
        self._snapshot = agent.fast_decision()

    def epsilon(self) -> float:
        if not self.learns:
            return 0.0
        return 1.0 if self.agent.in_warm_up() else self.agent.config.epsilon

    def decide(self, state):
        greedy, q_local, q_cloud = self._snapshot.decide(state.input_size, state.cpu_availability,
                                                         state.round_trip_s)
        epsilon = self.epsilon()
        action = int(self.rng.integers(0, 2)) if self.rng.random() < epsilon else greedy
        propensity = epsilon / 2 + (1.0 - epsilon if action == greedy else 0.0)
        return Decision(action, propensity, q_local, q_cloud)

    def learn(self, state, action, reward_value):
        """Store the transition and train on schedule. The next state of a transition is the state of
        the next learned request (it does not depend on the action), so each transition is stored
        when its successor arrives; flush() stores the last one with its own state."""
        if not self.learns:
            return None
        with self._lock:
            current = state.as_array()
            loss = None
            if self._pending is not None:
                loss = self._observe(*self._pending, current)
            self._pending = (current, action, reward_value)
            return loss

    def flush(self) -> Optional[float]:
        with self._lock:
            if self._pending is None:
                return None
            state, action, reward_value = self._pending
            self._pending = None
            return self._observe(state, action, reward_value, state)

    def _observe(self, state, action, reward_value, next_state):
        steps_before = self.agent.gradient_steps
        loss = self.agent.observe(state, action, reward_value, next_state)
        if self.agent.gradient_steps != steps_before or self.agent.steps == 1:
            self._snapshot = self.agent.fast_decision()
        return loss

    @property
    def steps(self):
        return self.agent.steps

    def stats(self):
        return {"steps": self.agent.steps, "gradient_steps": self.agent.gradient_steps,
                "replay_size": len(self.agent.memory), "epsilon": self.epsilon()}


@dataclass
class RouterConfig:
    probe_rate: float = 1.0
    """share of requests on which both sides run (1.0 while learning, as the paper; small deployed)."""
    cloud_timeout_s: float = 5.0
    """l_cloud of a request the cloud did not answer (the paper's 5 s)."""
    weights: CostWeights = field(default_factory=CostWeights)
    seed: int = 1
    """seed of the probe draws."""
    map_wait_s: float = 2.0
    """how long a side that answers from a map older than the one in force is asked again before its
    answer counts as a failure (a planner gets a new map a moment after the learner hears of it)."""
    map_retry_s: float = 0.02
    """pause between those calls."""

    def __post_init__(self):
        if not 0.0 <= self.probe_rate <= 1.0:
            raise ValueError(f"probe_rate must be in [0, 1], got {self.probe_rate}")
        if not (self.cloud_timeout_s > 0 and math.isfinite(self.cloud_timeout_s)):
            raise ValueError(f"cloud_timeout_s must be positive, got {self.cloud_timeout_s}")
        if not (self.map_wait_s >= 0 and math.isfinite(self.map_wait_s)):
            raise ValueError(f"map_wait_s must be finite and >= 0, got {self.map_wait_s}")
        if not (self.map_retry_s > 0 and math.isfinite(self.map_retry_s)):
            raise ValueError(f"map_retry_s must be positive, got {self.map_retry_s}")


PlanCall = Callable[[Any], Tuple[int, Any]]


class OffloadRouter:
    """Routes requests between `local` and `cloud` planners. `route()` returns the response the caller
    gets; `on_outcome(outcome)` is called once per request when everything about it is known (after
    learning), from a background thread on probe steps.

    `stale(response)` (optional) says why a good answer was planned on a map older than the one in
    force, or None. The side is asked again until it answers from the current map or `config.map_wait_s`
    has passed. Then the cloud counts as failed (CLOUD_ERROR, so the robot plans locally), while the
    local planner's answer is delivered with a note: it planned on the last map it accepted, so the
    announced map never reached it in a usable form (a malformed grid it refused, a lost message), and
    the last good map keeps serving rather than leaving a robot without a path."""

    def __init__(self, policy: DecisionPolicy, local: PlanCall, cloud: PlanCall, statuses: Statuses,
                 config: RouterConfig = RouterConfig(), on_decision: Callable = None,
                 on_outcome: Callable = None, clock: Callable[[], float] = time.perf_counter,
                 stale: Callable[[Any], Optional[str]] = None, sleep: Callable[[float], None] = time.sleep):
        self.policy, self.local, self.cloud, self.statuses = policy, local, cloud, statuses
        self.config = config
        self.stale = stale
        self.sleep = sleep
        self.on_decision = on_decision or (lambda request_id, state, decision, probe: None)
        self.on_outcome = on_outcome or (lambda outcome: None)
        self.clock = clock
        self.rng = np.random.default_rng(config.seed)
        self._pool = ThreadPoolExecutor(max_workers=3, thread_name_prefix="offload-side")
        self._previous_done = threading.Event()
        self._previous_done.set()
        self._serial = threading.Lock()
        self.next_request_id = 0

    def close(self) -> None:
        self._previous_done.wait()
        self._pool.shutdown(wait=True)

    def wait_idle(self, timeout_s: Optional[float] = None) -> bool:
        """True once the last request's outcome was handed over."""
        return self._previous_done.wait(timeout_s)

    # --- one request ----------------------------------------------------------------------------
    def route(self, request, state: Optional[State]):
        """The caller's response. state None (no map yet, a malformed pose): the request goes to the
        local planner, which reports the exact status, and nothing is learned from it."""
        with self._serial:
            self._previous_done.wait()   # the previous probe's slower side has finished
            self._previous_done.clear()
            request_id = self.next_request_id
            self.next_request_id += 1
        try:
            if state is None:
                return self._unlearnable(request_id, request)
            decision = self.policy.decide(state)
            probe = bool(self.config.probe_rate >= 1.0 or self.rng.random() < self.config.probe_rate)
            self.on_decision(request_id, state, decision, probe)
            if probe:
                return self._probe(request_id, request, state, decision)
            return self._single(request_id, request, state, decision)
        except BaseException:
            self._previous_done.set()
            raise

    def _call(self, side: PlanCall, request, failure_status: int, stale_status: Optional[int]) -> SideResult:
        """stale_status None: after the wait, an answer from the older map is delivered with a note."""
        began = self.clock()
        while True:
            try:
                status, response = side(request)
            except Exception as error:   # the planner node is gone or broke: a failed side, never a lost request
                return SideResult(failure_status, None, self.clock() - began,
                                  raised=f"planner call failed: {type(error).__name__}: {error}")
            why = self.stale(response) if self.stale is not None and status == self.statuses.ok else None
            if why is None:
                return SideResult(int(status), response, self.clock() - began)
            if self.clock() - began >= self.config.map_wait_s:
                if stale_status is None:
                    return SideResult(int(status), response, self.clock() - began,
                                      note=f"planned on the last map the planner accepted: {why} (still not "
                                           f"taken after {self.config.map_wait_s:g} s)")
                return SideResult(stale_status, None, self.clock() - began,
                                  raised=f"no path on the map in force within {self.config.map_wait_s:g} s: {why}")
            self.sleep(self.config.map_retry_s)

    def _call_local(self, request) -> SideResult:
        # A local planner that cannot be called at all is reported as a cloud-style error status so
        # the caller still learns why; there is nobody else to plan.
        return self._call(self.local, request, self.statuses.cloud_error, None)

    def _call_cloud(self, request) -> SideResult:
        return self._call(self.cloud, request, self.statuses.cloud_error, self.statuses.cloud_error)

    def _unlearnable(self, request_id, request):
        began = self.clock()
        local = self._call_local(request)
        outcome = Outcome(request_id, None, Decision(LOCAL, 1.0), False,
                          LOCAL if local.status == self.statuses.ok else NO_PATH_DELIVERED,
                          self.clock() - began, local=local, local_s=local.seconds)
        self._pool.submit(self._finish, outcome)
        return local

    def _single(self, request_id, request, state, decision):
        began = self.clock()
        outcome = Outcome(request_id, state, decision, False, NO_PATH_DELIVERED, 0.0)
        if decision.action == CLOUD:
            outcome.cloud = self._call_cloud(request)
            self._score_cloud(outcome)
            delivered = outcome.cloud
            if self.statuses.cloud_failed(outcome.cloud.status):
                outcome.local = self._call_local(request)   # fallback: the robot still gets its path
                outcome.local_s = outcome.local.seconds
                delivered = outcome.local
                outcome.delivered = LOCAL if delivered.status == self.statuses.ok else NO_PATH_DELIVERED
            else:
                outcome.delivered = CLOUD if delivered.status == self.statuses.ok else NO_PATH_DELIVERED
        else:
            outcome.local = delivered = self._call_local(request)
            outcome.local_s = outcome.local.seconds
            outcome.delivered = LOCAL if delivered.status == self.statuses.ok else NO_PATH_DELIVERED
        outcome.delivered_s = self.clock() - began
        self._pool.submit(self._finish, outcome)   # learning happens after the caller has its path
        return delivered

    def _probe(self, request_id, request, state, decision):
        began = self.clock()
        outcome = Outcome(request_id, state, decision, True, NO_PATH_DELIVERED, 0.0)
        first_good = threading.Event()
        results = {}
        lock = threading.Lock()

        def run(side, call):
            result = call(request)
            with lock:
                results[side] = result
                # A noted answer (the last good map) only when the other side has nothing fresher.
                if result.status == self.statuses.ok and result.note is None and "delivered" not in results:
                    results["delivered"] = side
                    outcome.delivered_s = self.clock() - began
                    first_good.set()
                if LOCAL in results and CLOUD in results:
                    first_good.set()   # neither succeeded: the caller gets the local answer
            return result

        local_future = self._pool.submit(run, LOCAL, self._call_local)
        cloud_future = self._pool.submit(run, CLOUD, self._call_cloud)
        first_good.wait()
        with lock:
            side = results.get("delivered")
        if side is None:
            local_future.result()
            delivered = results[LOCAL]
            outcome.delivered_s = self.clock() - began
            if delivered.status == self.statuses.ok:
                outcome.delivered = LOCAL
        else:
            delivered = results[side]
            outcome.delivered = side

        def complete():
            try:
                outcome.local, outcome.cloud = local_future.result(), cloud_future.result()
                outcome.local_s = outcome.local.seconds
                self._score_cloud(outcome)
                self._finish(outcome)
            except BaseException:
                self._previous_done.set()
                raise

        self._pool.submit(complete)
        return delivered

    def _score_cloud(self, outcome: Outcome) -> None:
        cloud = outcome.cloud
        failed = self.statuses.cloud_failed(cloud.status)
        outcome.cloud_timeout = cloud.status == self.statuses.cloud_timeout
        # A cloud that failed or answered after the deadline costs the full timeout (the paper's rule).
        outcome.cloud_s = cloud_latency_s(None if failed else cloud.seconds, self.config.cloud_timeout_s)

    def _finish(self, outcome: Outcome) -> None:
        """Reward and learn where both latencies are known and the request itself was plannable."""
        try:
            # A local answer that waited for a map the planner never took measures the wait, not planning.
            local_ok = outcome.local is not None and outcome.local.status == self.statuses.ok \
                and outcome.local.note is None
            if outcome.state is not None and outcome.local_s is not None and outcome.cloud_s is not None and local_ok:
                local_s = max(outcome.local_s, 1e-9)
                outcome.reward = reward(outcome.decision.action, local_s, outcome.cloud_s, self.config.weights)
                if self.policy.learns:
                    outcome.loss = self.policy.learn(outcome.state, outcome.decision.action, outcome.reward)
                    outcome.learned = True
            self.on_outcome(outcome)
        finally:
            self._previous_done.set()
