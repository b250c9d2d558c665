import pytest

from offload_learner_py.online.cpu import CpuAvailability, read_proc_stat


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
