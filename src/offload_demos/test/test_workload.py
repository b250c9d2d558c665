"""demo/workload.py: the demo robot's seeded load schedule, burnt for real."""
import numpy as np
import pytest

from offload_demos.workload import LoadSchedule, run_workload


def test_load_schedule_is_a_seeded_function_of_time():
    schedule = LoadSchedule(levels=(0.0, 0.5, 0.9), phase_s=2.0, seed=7)
    levels = [schedule.level_at(t) for t in np.arange(0, 40, 0.5)]
    assert set(levels) <= {0.0, 0.5, 0.9} and len(set(levels)) > 1
    assert levels == [LoadSchedule(levels=(0.0, 0.5, 0.9), phase_s=2.0, seed=7).level_at(t)
                      for t in np.arange(0, 40, 0.5)]
    assert schedule.level_at(0.1) == schedule.level_at(1.9)
    with pytest.raises(ValueError, match="levels"):
        LoadSchedule(levels=(1.0,))


def test_workload_burns_its_share_of_the_budget_per_slice():
    wall, cpu, slept, seen = [0.0], [0.0], [], []

    def clock():
        return wall[0]

    def cpu_clock():              # spinning: every look at the CPU clock burns 1 ms of CPU and wall time
        wall[0] += 0.001
        cpu[0] += 0.001
        return cpu[0]

    def sleep(seconds):
        slept.append(seconds)
        wall[0] += seconds

    run_workload(LoadSchedule(levels=(0.5,), phase_s=10.0), budget_cores=0.4, stop=lambda: len(slept) >= 20,
                 on_level=seen.append, slice_s=0.02, clock=clock, cpu_clock=cpu_clock, sleep=sleep)
    assert seen == [0.5]
    # 0.5 of a 0.4-core budget over 20 slices of 20 ms is 80 ms of CPU (within one clock tick per slice).
    assert cpu[0] == pytest.approx(0.5 * 0.4 * 0.02 * 20, abs=20 * 0.002)


def test_workload_schedule_runs_from_a_shared_epoch():
    """`began` is the run's epoch: the level at a moment is the schedule's at that moment since the epoch, so
    every process of a run (and every run) burns the same level at the same moment; before the epoch the
    first phase's level holds."""
    schedule = LoadSchedule(levels=(0.0, 0.3, 0.6, 0.9), phase_s=1.0, seed=5)
    phase_levels = [schedule.level_at(k + 0.5) for k in range(20)]
    assert len(set(phase_levels)) > 1

    wall, cpu = [0.0], [0.0]

    def cpu_clock():              # spinning burns 1 ms of CPU and of wall time per look
        wall[0] += 0.001
        cpu[0] += 0.001
        return cpu[0]

    def run(start_wall, stop, seen):
        wall[0] = start_wall
        run_workload(schedule, budget_cores=1.0, stop=stop, on_level=seen.append, slice_s=0.01,
                     clock=lambda: wall[0], cpu_clock=cpu_clock, sleep=lambda s: wall.__setitem__(0, wall[0] + s),
                     began=100.0)

    # A process started 7.5 s after the epoch burns phase 7's level first, not phase 0's.
    seen = []
    run(107.5, lambda: len(seen) >= 1, seen)
    assert seen == [phase_levels[7]]
    # One started before the epoch burns phase 0's level until the epoch, then the schedule's.
    seen = []
    run(95.0, lambda: wall[0] >= 102.5, seen)
    expected = phase_levels[0:3]
    assert seen == [level for k, level in enumerate(expected) if k == 0 or level != expected[k - 1]]
