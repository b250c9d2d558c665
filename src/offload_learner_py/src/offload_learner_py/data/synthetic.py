"""The paper's three synthetic datasets (section V.B), built on a trace of real local planning times:
every l_local is a time the real planner measured, and only l_cloud is synthetic.

- local (eq. 13): l_cloud = m * l_local with m = 1.0 + U{0..9}/10, so the cloud is never faster.
  The printed formula, 0.90 + (rand() % 10)/10, gives m = 0.9 one time in ten, which contradicts the
  paper's own text for that dataset (r_t in [-1, 0], "the reward is always negative" when offloading,
  "a random number from 0.9 to 1.9"); we follow the text, keeping the ten-step draw.
- cloud (eq. 14): m = 0.1 + U{0..9}/10, as printed (m = 1.0 is a tie, r_t = 0, as the text says).
- cpu (eq. 15): the cloud is faster exactly when u_t < x (x = 0.6): m = 0.1 + U{0..8}/10 below x and
  1.1 + U{0..8}/10 above it, with u_t uniform on both sides of x (the paper saw 50-70 %).

Rows carry a uniformly random logging action (propensity 0.5), as Algorithm 1 line 10 explores;
learners read the states and both latencies, never that action.
"""
from dataclasses import dataclass

import numpy as np

from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.core.reward import CostWeights, rewards
from offload_learner_py.data.trace import PlanningTrace

SYNTHETIC_KINDS = ("local", "cloud", "cpu")


@dataclass(frozen=True)
class SyntheticSettings:
    cpu_threshold: float = 0.6
    """x of eq. 15."""
    cpu_availability_range: tuple = (0.5, 0.7)
    """u_t is drawn uniformly from this range (the paper observed 50-70 %)."""
    round_trip_s: float = 0.030
    """mean b_t (the paper measured about 30 ms to AWS Ohio)."""
    round_trip_variation: float = 0.05
    """b_t varies uniformly by this fraction of its mean (the paper: under 5 %)."""


def cloud_multiplier(kind: str, cpu_availability: np.ndarray, rng: np.random.Generator,
                     settings: SyntheticSettings = SyntheticSettings()) -> np.ndarray:
    steps = len(cpu_availability)
    if kind == "local":
        return 1.0 + rng.integers(0, 10, steps) / 10.0
    if kind == "cloud":
        return 0.1 + rng.integers(0, 10, steps) / 10.0
    if kind == "cpu":
        step = rng.integers(0, 9, steps) / 10.0
        return np.where(cpu_availability < settings.cpu_threshold, 0.1 + step, 1.1 + step)
    raise ValueError(f"kind must be one of {SYNTHETIC_KINDS}, got {kind!r}")


def generate_synthetic(kind: str, trace: PlanningTrace, steps: int, seed: int,
                       weights: CostWeights = CostWeights(),
                       settings: SyntheticSettings = SyntheticSettings()) -> TransitionTable:
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if len(trace) == 0:
        raise ValueError("the trace is empty")
    if kind not in SYNTHETIC_KINDS:
        raise ValueError(f"kind must be one of {SYNTHETIC_KINDS}, got {kind!r}")
    rng = np.random.default_rng(seed)
    # Requests are drawn from the trace with replacement: a stream of random goals, as in the paper.
    rows = rng.integers(0, len(trace), steps)
    input_size = trace.input_size[rows]
    local_s = trace.local_s[rows]
    low, high = settings.cpu_availability_range
    cpu_availability = rng.uniform(low, high, steps)
    round_trip_s = settings.round_trip_s * (1.0 + rng.uniform(-1.0, 1.0, steps) * settings.round_trip_variation)
    cloud_s = cloud_multiplier(kind, cpu_availability, rng, settings) * local_s
    action = rng.integers(0, 2, steps)
    return TransitionTable(
        t=np.arange(steps), input_size=input_size, cpu_availability=cpu_availability, round_trip_s=round_trip_s,
        local_s=local_s, cloud_s=cloud_s, action=action, action_propensity=np.full(steps, 0.5),
        reward=rewards(action, local_s, cloud_s, weights),
        metadata={"kind": kind, "seed": seed, "alpha": weights.alpha, "beta": weights.beta,
                  "cpu_threshold": settings.cpu_threshold,
                  "cpu_availability_range": list(settings.cpu_availability_range),
                  "trace_map": trace.metadata.get("map_name", ""), "logging_policy": "uniform"})
