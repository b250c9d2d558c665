import pytest

from offload_learner_py.online.cpu import CgroupBudgetReader, CpuAvailability, LatestCpuAvailability, parse_cpu_list, \
    read_proc_stat, read_proc_stat_cores


class FakeStat:
    def __init__(self, readings):
        self.readings = list(readings)

    def __call__(self):
        return self.readings.pop(0)


def test_availability_is_idle_share_between_readings():
    sleeps = []
    cpu = CpuAvailability(reader=FakeStat([(100, 1000), (160, 1100), (160, 1200)]), sleep=sleeps.append)
    assert cpu.sample() == pytest.approx(0.6)
    assert sleeps == [0.05]  # only the first sample waits for a second reading
    assert cpu.sample() == pytest.approx(0.0)


def test_stalled_counters_take_a_fresh_reading():
    cpu = CpuAvailability(reader=FakeStat([(0, 0), (50, 100), (50, 100), (100, 200)]), sleep=lambda s: None)
    assert cpu.sample() == pytest.approx(0.5)
    assert cpu.sample() == pytest.approx(0.5)


def test_counters_that_never_move_raise():
    cpu = CpuAvailability(reader=lambda: (5, 10), sleep=lambda s: None)
    with pytest.raises(RuntimeError):
        cpu.sample()


def test_proc_stat_parsing(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  10 2 8 70 5 1 4 0 3 0\ncpu0 1 1 1 1 1 1 1 1 1 1\n")
    assert read_proc_stat(str(stat)) == (75, 100)
    stat.write_text("intr 1 2 3\n")
    with pytest.raises(ValueError):
        read_proc_stat(str(stat))


def test_the_real_os_gives_a_value_in_range():
    value = CpuAvailability(min_interval_s=0.02).sample()
    assert 0.0 <= value <= 1.0


def test_parse_cpu_list():
    assert parse_cpu_list("0") == (0,)
    assert parse_cpu_list("0,2-3") == (0, 2, 3)
    for bad in ("", "a", "3-1", "-1"):
        with pytest.raises(ValueError, match="CPU list"):
            parse_cpu_list(bad)


def test_per_core_proc_stat_counts_only_the_pinned_cores(tmp_path):
    stat = tmp_path / "stat"
    stat.write_text("cpu  300 0 300 600 0 0 0 0 0 0\n"
                    "cpu0 100 0 100 200 0 0 0 0 0 0\n"
                    "cpu1 200 0 200 400 0 0 0 0 0 0\n"
                    "intr 5\n")
    assert read_proc_stat_cores([0], str(stat)) == (200, 400)
    assert read_proc_stat_cores([0, 1], str(stat)) == (600, 1200)
    with pytest.raises(ValueError, match="cpu7"):
        read_proc_stat_cores([7], str(stat))


def test_cgroup_budget_availability_is_the_unused_share_of_the_quota(tmp_path):
    for controller in ("cpu", "cpuacct"):
        (tmp_path / controller / "robot").mkdir(parents=True)
    (tmp_path / "cpu" / "robot" / "cpu.cfs_quota_us").write_text("1000\n")
    (tmp_path / "cpu" / "robot" / "cpu.cfs_period_us").write_text("4000\n")
    usage = tmp_path / "cpuacct" / "robot" / "cpuacct.usage"
    usage.write_text("0\n")
    now = [0]
    reader = CgroupBudgetReader("robot", root=str(tmp_path), clock=lambda: now[0])
    assert reader.budget_cores == 0.25
    availability = CpuAvailability(reader, sleep=lambda s: now.__setitem__(0, now[0] + int(s * 1e9)))
    assert availability.sample() == 1.0              # first sample: nothing used over its short window
    now[0] += 1_000_000_000                          # one second of wall time: a 0.25 s budget
    usage.write_text(str(100_000_000))               # the group used 0.1 s of it
    assert availability.sample() == pytest.approx(0.6)


def test_cgroup_without_a_quota_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="cgroup 'nothere'"):
        CgroupBudgetReader("nothere", root=str(tmp_path))


def test_latest_availability_never_waits_and_keeps_the_last_measured_window():
    readings = iter([(0, 0), (50, 100), (50, 101), (60, 102), (110, 300)])
    slept = []
    cpu = LatestCpuAvailability(lambda: next(readings), min_window=10, sleep=slept.append)
    assert cpu.value == 0.5 and len(slept) == 1          # the first window, measured at construction
    assert cpu.sample() == 0.5 and cpu.sample() == 0.5   # 1 and 2 ticks later: too short, last value kept
    assert cpu.sample() == pytest.approx(60 / 200)       # 200 ticks since the last measured reading
    assert len(slept) == 1
