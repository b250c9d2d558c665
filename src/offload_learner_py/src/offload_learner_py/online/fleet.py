"""Deployed with a fleet learner: the robot decides, the cloud learns (no ROS).

`FleetPolicy` decides with the compiled FastDecision of the model version it holds and never learns: no replay, no
gradient step, no torch on the robot's request path. The version and its network are one `DeployedModel`
reference, read once per decision and replaced whole by a swap (`swap`, from the link's thread, after the new
file was fetched, checked and loaded there), so a decision sees either the old model or the new one, never half
of each, and records the version that decided (Decision.model_version, OffloadDecision.model_version). Before
any model (no ~model and none fetched yet) it plans locally.

`FleetRobot` wires it: the policy, the rollback guard (model_guard.py) and the link (fleet_link.py). Per finished
request (`on_outcome`, after the caller has its path) it hands the guard the policy's latency and enqueues the
request's row; a guard verdict of "worse" swaps the guard's reference model back at once (model_guard.py: the last
version kept that was no slower than the reference before it, not merely the version before), adds the version to the
rolled-back list (never loaded again; the learner hears it with the next version query, asked at once) and says
so in the log. `make_fleet_robot` is the entry point for the node and for benchmarks without ROS."""
import logging
import math
import threading
from typing import Any, Callable, List, NamedTuple, Optional, Tuple

from offload_learner_py import LOCAL
from offload_learner_py.core.model_file import agent_model_bytes, load_model, model_version
from offload_learner_py.core.policies import Decision, Policy
from offload_learner_py.online.fleet_link import FleetConfig, FleetLink
from offload_learner_py.online.model_guard import GuardConfig, ModelGuard, Verdict

LOG = logging.getLogger("offload_learner_py.online.fleet")


class DeployedModel(NamedTuple):
    version: str
    fast: Any            # core.dqn.FastDecision


class FleetPolicy(Policy):
    """The greedy policy of the deployed model; never learns."""
    name = "dqn"
    learns = False

    def __init__(self, model: Optional[DeployedModel] = None, warmup_requests: int = 0):
        self._model = model
        self.warmup_requests = warmup_requests
        self._decided = 0      # decisions so far: the first warmup_requests are probes (warming_up)

    @property
    def warming_up(self) -> bool:
        """The robot's first requests: the router probes both sides, as for a DQN learning alone, and the rows
        give the fleet learner this robot's trade-off to train on (a fleet robot probing at 5 % from its first
        request gave it 12-15 both-sides rows in 300 requests, against the 60 a robot alone collects first)."""
        return 0 < self.warmup_requests and self._decided <= self.warmup_requests   # asked after decide()

    @property
    def model(self) -> Optional[DeployedModel]:
        return self._model

    @property
    def version(self) -> str:
        model = self._model
        return model.version if model is not None else ""

    def swap(self, model: Optional[DeployedModel]) -> Optional[DeployedModel]:
        """Replace the model in one reference assignment; the model it replaced."""
        previous, self._model = self._model, model
        return previous

    def choose(self, table):
        model = self._model
        if model is None:
            return [LOCAL] * len(table)
        return [model.fast.decide(*row)[0] for row in table.states]

    def decide(self, state):
        self._decided += 1           # under the router's decision lock
        model = self._model          # once: the version and its network are one object
        if model is None:
            return Decision(LOCAL, 1.0)
        action, q_local, q_cloud = model.fast.decide(*state.as_tuple())
        return Decision(action, 1.0, q_local, q_cloud, model.version)


def policy_latency_s(outcome) -> float:
    """What the decided action cost: on a probe the decided side's measured latency (a cloud failure costs the
    timeout), else the latency delivered to the caller."""
    action = outcome.decision.action
    if outcome.probe:
        side, seconds = (outcome.local, outcome.local_s) if action == LOCAL else (outcome.cloud, outcome.cloud_s)
        if side is not None and seconds is not None and math.isfinite(seconds):
            return seconds
    return outcome.delivered_s


class FleetRobot:
    """The policy, the guard and the link of a robot deployed with a fleet learner."""

    def __init__(self, policy: FleetPolicy, guard: ModelGuard, log: logging.Logger = LOG):
        self.policy, self.guard, self.log = policy, guard, log
        self.link: Optional[FleetLink] = None
        self._rolled_back: List[str] = []
        self._kept = {}                     # version -> DeployedModel: the previous one, for a rollback
        self._lock = threading.Lock()
        self.verdicts: List[Verdict] = []

    def rolled_back(self) -> Tuple[str, ...]:
        with self._lock:
            return tuple(self._rolled_back)

    def install(self, version: str, fast) -> None:
        """A new version, loaded off the request path, takes over (the link's thread calls it)."""
        with self._lock:
            if version in self._rolled_back:
                return
            previous = self.policy.swap(DeployedModel(version, fast))
            models = dict(self._kept)
            if previous is not None:
                models[previous.version] = previous
            self.guard.begin(version, previous.version if previous is not None else "")
            reference = self.guard.reference     # the model a rollback goes back to: kept, the others let go
            self._kept = {reference: models[reference]} if reference in models else {}
        self.log.info("model %s now decides (was %s)", version[:12],
                      previous.version[:12] if previous is not None and previous.version else "none")

    def on_outcome(self, outcome, row: Any = None) -> Optional[Verdict]:
        """After the caller has its path: the guard's sample and the row for the learner. Inference, accounting
        and a bounded enqueue; a rollback is one reference swap."""
        verdict = None
        if outcome.state is not None:
            verdict = self.guard.observe(outcome.decision.model_version, policy_latency_s(outcome))
            if verdict is not None:
                self._judge(verdict)
        if row is not None and self.link is not None:
            self.link.enqueue(row)
        return verdict

    def _judge(self, verdict: Verdict) -> None:
        self.verdicts.append(verdict)
        if not verdict.worse:
            self.log.info("%s: kept", verdict.describe())
            return
        with self._lock:
            self._rolled_back.append(verdict.version)
            back = self._kept.get(verdict.previous)
            if self.policy.version == verdict.version:
                self.policy.swap(back)
        self.log.warning("%s: rolled back to %s; the fleet learner is told and will not offer it again",
                         verdict.describe(), verdict.previous[:12] or "no model (local plans)")
        if self.link is not None:
            self.link.poll_soon()

    def stats(self) -> dict:
        link = self.link
        return {"model_version": self.policy.version, "rolled_back": list(self.rolled_back()),
                "fleet_rows_sent": link.sent if link else 0, "fleet_rows_dropped": link.dropped if link else 0,
                "fleet_rows_pending": len(link.buffer) if link else 0}

    def close(self) -> None:
        if self.link is not None:
            self.link.close()


def load_initial(path: str, dqn_config=None) -> Tuple[Optional[DeployedModel], int]:
    """The model a fleet robot starts with: ~model as a model file (.npz, loaded weights-only) or a learner
    checkpoint (its greedy network, versioned by the model file it makes); None for no path. And the requests it
    learned from on a robot: a learner checkpoint's steps (a learning run's, each request measured on both sides),
    0 for a model file (the fleet's pooled model) or none."""
    if not path:
        return None, 0
    with open(path, "rb") as handle:
        data = handle.read()
    steps = 0
    if not data.startswith(b"PK") or path.endswith(".pt"):
        from offload_learner_py.core.checkpoint import load_checkpoint
        from offload_learner_py.core.config import DQNConfig

        agent = load_checkpoint(path, dqn_config or DQNConfig())
        data, steps = agent_model_bytes(agent), int(agent.steps)
    fast, _ = load_model(data)
    return DeployedModel(model_version(data), fast), steps


def make_fleet_robot(config: FleetConfig, guard: GuardConfig = GuardConfig(), model: str = "",
                     client_factory: Optional[Callable[[], Any]] = None, encode: Callable = lambda row: row,
                     definitions: Optional[dict] = None, md5: Optional[dict] = None,
                     errors: Optional[Tuple[type, type, type]] = None, log: logging.Logger = LOG,
                     start: bool = True) -> FleetRobot:
    """A fleet robot: its policy from `model` (see load_initial), the guard, and (with an endpoint) the link to
    the fleet learner through offload_cloud's FleetClient, or `client_factory` with the `errors` it raises
    (timeout, busy, refused) for tests and benchmarks."""
    start_model, learned = load_initial(model)
    # The warm-up gives the fleet this robot's both-sides measurements; a robot started from its own learning run's
    # checkpoint measured both sides on that run's requests (the run whose bag seeds the fleet learner): those
    # count, so a restart of a deployed robot does not pay the warm-up's double plans again.
    warmup = max(0, config.warmup_requests - learned) if config.enabled else 0
    if config.enabled and warmup < config.warmup_requests:
        log.info("started from a checkpoint that learned from %d requests: %d warm-up requests of %d", learned,
                 warmup, config.warmup_requests)
    robot = FleetRobot(FleetPolicy(start_model, warmup), ModelGuard(guard), log)
    if config.enabled:
        if client_factory is None:
            from offload_cloud.client import CloudTimeout
            from offload_cloud.fleet_client import FleetBusy, FleetClient, FleetError

            errors = (CloudTimeout, FleetBusy, FleetError)
            client_factory = lambda: FleetClient(  # noqa: E731
                config.endpoint, keys_dir=config.keys_dir or None, insecure=config.insecure, timeout_s=config.timeout_s)
        robot.link = FleetLink(config, client_factory, definitions or {}, md5 or {}, errors, robot.install,
                               lambda: robot.policy.version, robot.rolled_back, encode, log)
        if start:
            robot.link.start()
    return robot

