"""Online learning without ROS, in one place: what the robot learns from each request it routed. The router
(router.py) acts: it decides, calls the sides, hedges, cancels and settles. The learner learns: the router hands
it each request's Outcome once no side of it is running, and it

- measures l_local and l_cloud from the sides' answers; a cloud call that failed or answered too late costs the
  timeout (the paper's rule, core/reward.cloud_latency_s);
- imputes the latency of the side not run on a deployed request (bandit feedback) with that side's latency
  model (latency_model.py: the median for the state; the bias this gives eq. 10 is described there), which it
  trains on every measured latency. A local plan cancelled after it had run longer than the cloud took counts
  as that lower bound (or the model's estimate when larger);
- rewards the decided action by eq. 10 (core/reward.py) and hands the policy both actions' transitions
  (Algorithm 1 with full information: both latencies measured on a probe, one imputed on a deployed request),
  and, for a cloud side that answered, its round-trip variants to the DQN's replay (core/round_trip.py: the same
  request at other round trips the robot met);
- saves the policy's checkpoint every `checkpoint_every` learned requests (atomically; a failed save is logged
  at error level, counted, and tried again at the next learned request) and at close;
- keeps the recent figures the node publishes (loss, accuracy against the oracle, delivered latency), with a
  progress line in its log every `progress_every` requests.

The router reads the latency models for its hedge deadlines and asks `needs_both_sides()` whether a deployed
request should be a probe. The node builds it with `resume` and publishes `stats()`."""
import logging
import threading
import time
from collections import deque
from typing import Optional, Tuple

import numpy as np

from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.checkpoint import remove_orphaned_temps, save_checkpoint
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.evaluation import faster_actions
from offload_learner_py.core.policies import Policy
from offload_learner_py.core.reward import DEFAULT_CLOUD_TIMEOUT_S, CostWeights, cloud_latency_s, reward
from offload_learner_py.core.round_trip import RoundTripPool, at_round_trips
from offload_learner_py.core.state import State
from offload_learner_py.online.latency_model import LatencyModel, LatencyModelConfig
from offload_learner_py.online.router_types import Outcome, Statuses
from offload_learner_py.online.session import SessionConfig, make_policy

LOG = logging.getLogger("offload_learner_py.online.learning")
MAX_SAVE_BACKOFF = 64   # a failing checkpoint save is tried at most this many checkpoint periods apart


def latency_features(state: State) -> Tuple[float, float, float]:
    """What the latency models read of s_t."""
    return state.input_size, state.cpu_availability, state.round_trip_s


def correct_choice(action: int, local_s: float, cloud_s: float) -> bool:
    """Whether the action was the faster side (a tie is never a mistake)."""
    return bool(faster_actions(local_s, cloud_s, action) == action)


class OnlineLearner:
    """Learns from every routed request's Outcome (`learn`). `config` gives the checkpoint, its cadence and the
    statistics' window; `agent` is the DQN behind `policy` (the one the checkpoint saves), None for a fixed
    policy. Thread-safe: the router hands over outcomes from its side threads."""

    def __init__(self, policy: Policy, statuses: Statuses, weights: CostWeights = CostWeights(),
                 cloud_timeout_s: float = DEFAULT_CLOUD_TIMEOUT_S,
                 latency_model: LatencyModelConfig = LatencyModelConfig(), config: SessionConfig = SessionConfig(),
                 agent: Optional[DQNAgent] = None, log: logging.Logger = LOG):
        self.policy, self.statuses, self.agent, self.config, self.log = policy, statuses, agent, config, log
        self.weights, self.cloud_timeout_s = weights, cloud_timeout_s
        self.models = {LOCAL: LatencyModel(latency_model), CLOUD: LatencyModel(latency_model)}
        # The round trips met, for the DQN's round-trip variants (core/round_trip.py): as many as its replay holds;
        # none kept when the DQN takes none (round_trip_variants 0), so a request pays nothing for them.
        self.round_trips = RoundTripPool(agent.config.replay_capacity, agent.config.seed) \
            if agent is not None and agent.config.round_trip_variants else None
        self.checkpoint_failures = 0
        self.count = 0                                    # outcomes of decisions learned from
        self._lock = threading.Lock()
        self._recent = deque(maxlen=config.stats_window)  # (loss or nan, correct or nan)
        self._delivered_ms = deque(maxlen=config.stats_window)
        self._learned_since_checkpoint = 0
        self._save_backoff = 1   # checkpoint periods between tries: doubled by each failed save

    @classmethod
    def resume(cls, config: SessionConfig, statuses: Statuses, log: logging.Logger = LOG,
               **settings) -> "OnlineLearner":
        """The node's learner: the policy `config` names, resumed from its own checkpoint (else from ~model),
        once the temp files of a save killed mid-write are gone. `settings`: the reward's and latency models'
        (weights, cloud_timeout_s, latency_model)."""
        if config.checkpoint:
            for name in remove_orphaned_temps(config.checkpoint):
                log.warning("removed %s, left by a checkpoint save that was killed mid-write", name)
        policy, agent = make_policy(config, log)
        return cls(policy, statuses, config=config, agent=agent, log=log, **settings)

    @property
    def learns(self) -> bool:
        return bool(self.config.learn and self.policy.learns)

    def needs_both_sides(self) -> bool:
        """A learning policy still warming up (an untrained DQN), or a latency model still without its first
        samples (a warm-started DQN on a fresh node): a one-sided request would teach it little or nothing, as
        there is nothing yet to impute the other side with. A fleet robot's policy warms up too (its rows teach
        the fleet learner), though it does not learn here."""
        return bool(self.policy.warming_up) or (self.policy.learns and not all(m.ready for m in self.models.values()))

    # --- one request ----------------------------------------------------------------------------------------
    def learn(self, outcome: Outcome) -> None:
        """Measure, impute, reward and learn from one routed request, then count it and save when due. A
        request without a state (no map yet, a malformed pose) is not a decision: measured only."""
        self._measure(outcome)
        if outcome.state is None:
            return
        began_cpu = time.thread_time()   # the learner's own CPU on the robot (one torch thread)
        self._reward_and_learn(outcome)
        outcome.learner_cpu_s = time.thread_time() - began_cpu
        self._record(outcome)

    def _measure(self, outcome: Outcome) -> None:
        if outcome.local is not None:
            outcome.local_s = outcome.local.seconds
        if outcome.cloud is not None:
            failed = self.statuses.cloud_failed(outcome.cloud.status)
            outcome.cloud_timeout = outcome.cloud.status == self.statuses.cloud_timeout
            outcome.cloud_s = cloud_latency_s(None if failed else outcome.cloud.seconds, self.cloud_timeout_s)

    def _reward_and_learn(self, outcome: Outcome) -> None:
        """Reward and learn where the request itself was plannable: from both measured latencies (a probe, a
        hedge that ran both, a cloud failure that cost the timeout), else from the measured one and the other
        side's imputed latency (deployed)."""
        state = latency_features(outcome.state)
        if self.round_trips is not None:
            self.round_trips.add(outcome.state.round_trip_s)
        # A local answer that waited for a map the planner never took measures the wait, not planning.
        local_ok = outcome.local is not None and outcome.local.status == self.statuses.ok and outcome.local.note is None
        cloud_ok = outcome.cloud is not None and outcome.cloud.status == self.statuses.ok
        if local_ok:
            self.models[LOCAL].observe(state, outcome.local_s)
        local_s = outcome.local_s if local_ok else None
        # A cloud that failed (or never answered from the map in force) cost the timeout: that is measured too,
        # and the cloud's latency model learns it, so a request it imputes l_cloud for sees an erroring cloud as
        # the cost it is (learning only its successes made a cloud that mostly failed look fast).
        cloud_measured = outcome.cloud is not None and (cloud_ok or self.statuses.cloud_failed(outcome.cloud.status))
        if cloud_measured:
            self.models[CLOUD].observe(state, outcome.cloud_s)
        cloud_s = outcome.cloud_s if cloud_measured else None
        self.policy.observe(outcome.state, local_s, outcome.cloud_s if cloud_ok else None)   # a rule's predictions
        if local_s is None and cloud_s is None:
            return     # nothing measured about planning (a refused request, a stale map, a dead local planner)
        if local_s is None and outcome.local is not None:
            return     # the local planner answered but not with a plannable path: nothing to impute against
        bound = outcome.local_lower_bound_s
        if local_s is None and bound is not None and cloud_ok and bound >= cloud_s:
            # Cancelled after running longer than the cloud took: l_local is at least `bound`, so the cloud was
            # the better action whatever the rest would have been. Learning from the bound (or the model's
            # estimate when larger) keeps the slowest local plans, the ones cancelled most, in the picture.
            estimate = self.models[LOCAL].impute_s(state)
            if estimate is None or estimate < bound:
                self.models[LOCAL].observe(state, bound)
            local_s, outcome.imputed = bound if estimate is None else max(bound, estimate), LOCAL
        if local_s is None:
            local_s, outcome.imputed = self.models[LOCAL].impute_s(state), LOCAL
        elif cloud_s is None:
            cloud_s, outcome.imputed = self.models[CLOUD].impute_s(state), CLOUD
        if local_s is None or cloud_s is None:
            return     # the model of the side not run has too few samples yet
        local_s, cloud_s = max(local_s, 1e-9), max(cloud_s, 1e-9)
        outcome.reward = reward(outcome.decision.action, local_s, cloud_s, self.weights)
        if self.policy.learns:
            # Both actions' rewards are known: two transitions (full information, or one side imputed).
            for action in (LOCAL, CLOUD):
                loss = self.policy.learn(outcome.state, action, reward(action, local_s, cloud_s, self.weights))
                outcome.loss = loss if loss is not None else outcome.loss
            outcome.learned = True
            outcome.transitions = 2
            if cloud_ok:
                self._learn_round_trip_variants(outcome.state, local_s, cloud_s)

    def _learn_round_trip_variants(self, state: State, local_s: float, cloud_s: float) -> None:
        """The measured cloud side at other round trips the robot met, for the DQN's replay (core/round_trip.py);
        l_local, measured or imputed, stays as it was."""
        if self.round_trips is None:
            return
        round_trips = self.round_trips.draw_above(state.round_trip_s, self.agent.config.round_trip_variants)
        if not len(round_trips):
            return
        states, clouds = at_round_trips(np.repeat(state.as_array()[None], len(round_trips), axis=0),
                                        np.full(len(round_trips), cloud_s), round_trips)
        for row, cloud in zip(states, clouds):   # l_cloud' = b' + work > b' > b >= 0: never 0
            self.policy.remember(State(*row), CLOUD, reward(CLOUD, local_s, float(cloud), self.weights))

    # --- statistics and checkpoints -------------------------------------------------------------------------
    def _record(self, outcome: Outcome) -> None:
        """Count one decision's outcome, save the model when due, log the progress line when one is due."""
        correct = float("nan")
        if outcome.reward is not None and outcome.imputed is None:
            correct = float(correct_choice(outcome.decision.action, outcome.local_s, outcome.cloud_s))
        with self._lock:
            self._recent.append((outcome.loss if outcome.loss is not None else float("nan"), correct))
            self._delivered_ms.append(1000.0 * outcome.delivered_s)
            self.count += 1
            count = self.count
            self._learned_since_checkpoint += bool(outcome.learned)
            due = self.config.checkpoint_every > 0 and \
                self._learned_since_checkpoint >= self.config.checkpoint_every * self._save_backoff
        if due:
            self.save()
        if self.config.progress_every > 0 and count % self.config.progress_every == 0:
            stats = self.stats()
            with self._lock:
                delivered = float(np.mean(self._delivered_ms))
            self.log.info("request %d: last %d mean %.1f ms to path, accuracy %.0f%% vs oracle, model steps %d",
                          count, stats["recent_window"], delivered, 100 * stats["recent_accuracy"], self.policy.steps)

    def stats(self) -> dict:
        """The policy's counters with the recent window's mean loss and accuracy, and checkpoint failures."""
        with self._lock:
            recent = np.array(self._recent, dtype=np.float64).reshape(-1, 2)

        def mean(column: int) -> float:
            finite = recent[:, column][np.isfinite(recent[:, column])]
            return float(finite.mean()) if len(finite) else float("nan")
        return {**self.policy.stats(), "recent_window": len(recent), "recent_loss": mean(0),
                "recent_accuracy": mean(1), "checkpoint_failures": self.checkpoint_failures}

    def save(self) -> bool:
        """Write the checkpoint; a failure (a full disk, a diverged network) is logged at error level, counted in
        stats(), and tried again after twice as many learned requests each time (up to MAX_SAVE_BACKOFF times
        checkpoint_every): retried on every request, a full disk cost 130 ms of CPU and an error line per
        request (#31). A success goes back to every checkpoint_every."""
        if not self.config.checkpoint or self.agent is None or not self.policy.learns:
            return False
        try:
            with self.policy.lock:
                save_checkpoint(self.agent, self.config.checkpoint)
        except (OSError, ValueError) as error:
            with self._lock:
                self.checkpoint_failures += 1
                self._learned_since_checkpoint = 0
                self._save_backoff = min(2 * self._save_backoff, MAX_SAVE_BACKOFF)
                retry = self.config.checkpoint_every * self._save_backoff
            self.log.error("checkpoint %s not written (%d failures so far; next try in %d learned requests): %s",
                           self.config.checkpoint, self.checkpoint_failures, retry, error)
            return False
        with self._lock:
            self._learned_since_checkpoint = 0
            self._save_backoff = 1
        self.log.debug("checkpoint %s at %d steps", self.config.checkpoint, self.agent.steps)
        return True

    def close(self) -> bool:
        """Store the last pending transition and save; whether a checkpoint was written."""
        self.policy.flush()
        if self.save():
            self.log.info("checkpoint %s: %d steps", self.config.checkpoint, self.agent.steps)
            return True
        return False
