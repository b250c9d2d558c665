"""Every hyperparameter of the DQN learner in one place. The paper's Table 1 is missing from its
text, so the values below are our defaults; the architecture, replay size and epsilon are the paper's.
The defaults are what the robot's learner node runs (launch/config/learner.yaml sets none of them); the
offline experiments on synthetic streams run EXPERIMENT_SCHEDULE over them."""
import math
import numbers
from dataclasses import asdict, dataclass, fields
from typing import Tuple


# The largest network a config may describe: a guard against configs (and checkpoints) that would
# allocate gigabytes before anything else is checked. The paper's 3 x 256 network has 133,378 weights;
# 20 million is three hidden layers of about 3,100.
MAX_PARAMETERS = 20_000_000
# Replay memory is preallocated (two float32 state arrays): 10 million experiences take about 280 MB.
MAX_REPLAY_CAPACITY = 10_000_000
# More variants than this would fill the replay with copies of a few requests.
MAX_ROUND_TRIP_VARIANTS = 8


def parameter_count(hidden_sizes, state_size: int = 3, n_actions: int = 2) -> int:
    """Weights and biases of the Q-network state_size -> hidden_sizes -> n_actions."""
    widths = [state_size, *hidden_sizes, n_actions]
    return sum(w_in * w_out + w_out for w_in, w_out in zip(widths[:-1], widths[1:]))


def _is_int(value) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


# The offline experiments' schedule over the defaults (offline/experiments.py, the accuracy bar): a longer
# warm-up, a gradient step every 2 environment steps and a target copy every 50. On the synthetic streams,
# training every step over-fits the sparse exploratory cloud samples and every 4 steps under-fits the CPU
# boundary; 2 is robust for both. The robot trains on every request: it meets far fewer of them.
EXPERIMENT_SCHEDULE = {"learning_starts": 200, "train_frequency": 2, "target_update_interval": 50}


@dataclass(frozen=True)
class DQNConfig:
    seed: int = 1
    """seed of torch, numpy and the exploration draws; same seed, same run."""
    hidden_sizes: Tuple[int, ...] = (256, 256, 256)
    """hidden ReLU layers between the 3 inputs and the 2 Q-values (paper: three of 256)."""
    gamma: float = 0.0
    """discount; 0 is the contextual-bandit reading (s_t+1 ignores a_t), > 0 reproduces the paper."""
    learning_rate: float = 1e-3
    """Adam step size."""
    weight_decay: float = 0.0
    """decoupled weight decay (AdamW); damps Q-value wiggles between sparse, noisy samples."""
    replay_capacity: int = 1000
    """FIFO replay memory size (paper: 1000 experiences)."""
    batch_size: int = 64
    """minibatch drawn uniformly from replay memory per gradient step."""
    learning_starts: int = 60
    """warm-up steps of uniformly random actions before the first gradient step; the state
    normalisation is first fitted on these states."""
    normalisation_refit_interval: int = 100
    """environment steps between re-fits of the state normalisation over the replay memory after the warm-up
    (the network re-expressed so that its Q-values do not change); 0 freezes it after the warm-up. On conditions
    that change (a link handover), a warm-up inside one regime gave the round trip a scale 7x too small: later
    states reached 18 standard deviations and the network's inputs were dominated by b_t."""
    train_frequency: int = 1
    """environment steps between gradient steps (a robot's request: each one's two transitions train)."""
    gradient_steps: int = 1
    """gradient steps each time training runs."""
    target_update_interval: int = 25
    """environment steps between copies of the online weights into the target network (K)."""
    epsilon: float = 0.1
    """epsilon-greedy exploration rate after warm-up (paper: 0.1)."""
    huber_delta: float = 1.0
    """Huber (smooth L1) loss threshold; rewards lie in [-1, 1] so the loss is quadratic there."""
    max_grad_norm: float = 10.0
    """gradient norm clip, guards against rare large TD errors when gamma > 0."""
    log_input_size: bool = True
    """feed log(d + 1e-6) and log(p + 1e5) for d and p: they span orders of magnitude (the schema's log floors)."""
    round_trip_variants: int = 1
    """copies of each request whose cloud side was measured, added to replay with its round trip redrawn from those
    above its own that the robot met and its cloud latency moved with it (core/round_trip.py: the round trip adds to
    the cloud's latency whatever the load). Applied by the learner node and by training from bags (retrain, the
    fleet learner); the paper's synthetic streams have no link, and run_online does not apply it. 0: none. On by
    default since 2026-11-28 (#33, BENCHMARKS.md): with one, the deployed DQN met the bar on stationary, handover
    and load-shift, and on the held-out load pulse its probe regret fell from 3.0-3.2 to 2.2-2.4 ms."""

    def __post_init__(self):
        for spec in fields(self):
            value = getattr(self, spec.name)
            if spec.name == "hidden_sizes":
                if not isinstance(value, (tuple, list)) or not all(_is_int(h) for h in value):
                    raise ValueError(f"hidden_sizes must be a list of integers, got {value!r}")
                object.__setattr__(self, "hidden_sizes", tuple(int(h) for h in value))
            elif isinstance(spec.default, bool):
                if not isinstance(value, bool):
                    raise ValueError(f"{spec.name} must be true or false, got {value!r}")
            elif isinstance(spec.default, int):
                if not _is_int(value):
                    raise ValueError(f"{spec.name} must be an integer, got {value!r}")
            elif not (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)):
                raise ValueError(f"{spec.name} must be a finite number, got {value!r}")
        for name in ("huber_delta", "max_grad_norm"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        # Adam's step is about learning_rate per weight; above 1 the weights of this network (inputs and
        # rewards of order 1) diverge to inf and torch fails far from the cause.
        if not 0.0 < self.learning_rate <= 1.0:
            raise ValueError(f"learning_rate must be in (0, 1], got {self.learning_rate}")
        if not 0.0 <= self.weight_decay <= 1.0:
            raise ValueError(f"weight_decay must be in [0, 1], got {self.weight_decay}")
        if self.replay_capacity > MAX_REPLAY_CAPACITY:
            raise ValueError(f"replay_capacity must be at most {MAX_REPLAY_CAPACITY}, got {self.replay_capacity}")
        if not 0.0 <= self.gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {self.gamma}")
        if not 0.0 <= self.epsilon <= 1.0:
            raise ValueError(f"epsilon must be in [0, 1], got {self.epsilon}")
        for name in ("replay_capacity", "batch_size", "train_frequency", "gradient_steps",
                     "target_update_interval"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if not 0 <= self.round_trip_variants <= MAX_ROUND_TRIP_VARIANTS:
            raise ValueError(f"round_trip_variants must be in [0, {MAX_ROUND_TRIP_VARIANTS}], got "
                             f"{self.round_trip_variants}")
        if self.normalisation_refit_interval < 0:
            raise ValueError(f"normalisation_refit_interval must be >= 0, got {self.normalisation_refit_interval}")
        if self.learning_starts < 0:
            raise ValueError(f"learning_starts must be >= 0, got {self.learning_starts}")
        if not self.hidden_sizes or min(self.hidden_sizes) < 1:
            raise ValueError(f"hidden_sizes must be positive, got {self.hidden_sizes}")
        if parameter_count(self.hidden_sizes) > MAX_PARAMETERS:
            raise ValueError(f"hidden_sizes {list(self.hidden_sizes)} give {parameter_count(self.hidden_sizes)} "
                             f"parameters, more than {MAX_PARAMETERS}")
        if self.batch_size > self.replay_capacity:
            raise ValueError("batch_size cannot exceed replay_capacity")

    def to_dict(self) -> dict:
        values = asdict(self)
        values["hidden_sizes"] = list(self.hidden_sizes)
        return values

    @classmethod
    def from_dict(cls, values: dict) -> "DQNConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown DQNConfig fields: {sorted(unknown)}")
        values = dict(values)
        if "hidden_sizes" in values:
            sizes = values["hidden_sizes"]
            if not isinstance(sizes, (list, tuple)):
                raise ValueError(f"hidden_sizes must be a list of integers, got {sizes!r}")
            values["hidden_sizes"] = tuple(sizes)
        return cls(**values)
