"""A robot workload whose CPU demand varies over the run (perception, control and logging stand-ins),
so the robot's CPU availability u_t really varies and really slows local planning. It burns real CPU
time: within each slice it spins until its own CPU clock has advanced by the level's share of the
robot's budget, then sleeps to the end of the slice."""
import bisect
import math
import time
from dataclasses import dataclass
from typing import Callable, Optional, Sequence, Tuple

import numpy as np


@dataclass(frozen=True)
class LoadSchedule:
    """Piecewise-constant load levels: a new level, drawn (seeded) from `levels`, every `phase_s`
    seconds. A level is the share of the robot's CPU budget the workload takes, in [0, 1)."""
    levels: Tuple[float, ...] = (0.0, 0.3, 0.55, 0.75)
    phase_s: float = 8.0
    seed: int = 1

    def __post_init__(self):
        if not self.levels or not all(0.0 <= level < 1.0 for level in self.levels):
            raise ValueError(f"levels must be non-empty, each in [0, 1), got {self.levels}")
        if not (self.phase_s > 0 and math.isfinite(self.phase_s)):
            raise ValueError(f"phase_s must be positive, got {self.phase_s}")

    def level_at(self, elapsed_s: float) -> float:
        phase = int(max(elapsed_s, 0.0) // self.phase_s)
        # One generator per phase index keeps level_at a pure function of time and seed.
        return float(np.random.default_rng([self.seed, phase]).choice(self.levels))


@dataclass(frozen=True)
class StepLoad:
    """A scenario's load schedule (offload_demos.scenario): (time_s, level) steps, each level holding from its time
    on, looped after the last step's time like an RTT trace file (the last step only marks the period; a single
    step holds for ever). Same `level_at` as LoadSchedule."""
    steps: Tuple[Tuple[float, float], ...]

    def __post_init__(self):
        if not self.steps:
            raise ValueError("a load schedule needs at least one [time_s, level] step")
        times = [time_s for time_s, _ in self.steps]
        if times[0] != 0 or any(not later > earlier for earlier, later in zip(times, times[1:])):
            raise ValueError(f"load schedule times must start at 0 and increase, got {times}")
        for time_s, level in self.steps:
            if not (math.isfinite(time_s) and 0.0 <= level < 1.0):
                raise ValueError(f"a load level is a share of the budget in [0, 1), got {level!r} at {time_s!r} s")

    def level_at(self, elapsed_s: float) -> float:
        period = self.steps[-1][0]
        t = max(elapsed_s, 0.0) % period if period > 0 else 0.0
        return float(self.steps[bisect.bisect_right([s for s, _ in self.steps], t) - 1][1])


def run_workload(schedule, budget_cores: float, stop: Callable[[], bool],
                 on_level: Callable[[float], None] = lambda level: None, slice_s: float = 0.02,
                 clock: Callable[[], float] = time.monotonic, cpu_clock: Callable[[], float] = time.thread_time,
                 sleep: Callable[[float], None] = time.sleep, began: Optional[float] = None) -> None:
    """`schedule`: a LoadSchedule or a StepLoad. Burn schedule.level_at(t) x budget_cores of CPU per second until stop() is true; t runs from `began` (a
    clock() reading shared with the rest of a run, so every process's schedule starts at the same instant;
    before it the first level holds), by default from the call."""
    if not budget_cores > 0:
        raise ValueError(f"budget_cores must be positive, got {budget_cores}")
    began = clock() if began is None else began
    level = None
    while not stop():
        slice_start = clock()
        current = schedule.level_at(slice_start - began)
        if current != level:
            level = current
            on_level(level)
        target_cpu_s = level * budget_cores * slice_s
        cpu_start = cpu_clock()
        while cpu_clock() - cpu_start < target_cpu_s and clock() - slice_start < slice_s:
            pass
        remaining = slice_s - (clock() - slice_start)
        if remaining > 0:
            sleep(remaining)


def parse_levels(values: Sequence) -> Tuple[float, ...]:
    try:
        return tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ValueError(f"levels must be a list of numbers, got {values!r}") from None
