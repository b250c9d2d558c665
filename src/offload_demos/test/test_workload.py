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
