"""CPU availability u_t in [0, 1], measured from the OS as the idle share of CPU time between two
readings of /proc/stat (the kernel's own accounting, so no extra dependency is needed)."""
import os
import time
from typing import Callable, Optional, Sequence, Tuple


def read_proc_stat(path: str = "/proc/stat") -> Tuple[int, int]:
    """Aggregate (idle, total) jiffies from the first line of /proc/stat. iowait counts as idle
    because a core waiting on I/O is free to plan."""
    with open(path) as stat:
        fields = stat.readline().split()
    if not fields or fields[0] != "cpu":
        raise ValueError(f"{path} does not start with an aggregate 'cpu' line")
    values = [int(v) for v in fields[1:]]
    # guest and guest_nice are already included in user and nice: counting them twice skews total.
    busy_and_idle = values[:8]
    idle = values[3] + (values[4] if len(values) > 4 else 0)
    return idle, sum(busy_and_idle)


class CpuAvailability:
    """Idle share of CPU time since the previous sample. The first sample (no previous reading yet)
    waits min_interval_s between two readings so it is never a made-up value."""

    def __init__(self, reader: Callable[[], Tuple[int, int]] = read_proc_stat,
                 sleep: Callable[[float], None] = time.sleep, min_interval_s: float = 0.05):
        self._reader = reader
        self._sleep = sleep
        self._min_interval_s = min_interval_s
        self._previous: Optional[Tuple[int, int]] = None

    def sample(self) -> float:
        if self._previous is None:
            self._previous = self._reader()
            self._sleep(self._min_interval_s)
        idle, total = self._reader()
        previous_idle, previous_total = self._previous
        self._previous = (idle, total)
        elapsed = total - previous_total
        if elapsed <= 0:
            # No jiffy elapsed between readings: nothing was measured, so the last estimate is
            # unknown; a fresh pair of readings is taken instead of inventing a value.
            self._sleep(self._min_interval_s)
            idle, total = self._reader()
            self._previous = (idle, total)
            elapsed = total - previous_total
            if elapsed <= 0:
                raise RuntimeError("CPU time counters did not advance; cannot measure availability")
        return min(1.0, max(0.0, (idle - previous_idle) / elapsed))


def parse_cpu_list(text: str) -> Tuple[int, ...]:
    """Core numbers from a taskset-style list such as "0", "0,2" or "0-3"."""
    cores = set()
    for part in str(text).replace(" ", "").split(","):
        if not part:
            continue
        low, _, high = part.partition("-")
        try:
            first, last = int(low), int(high or low)
        except ValueError:
            raise ValueError(f"bad CPU list {text!r}: expected numbers like 0 or 0,2 or 0-3") from None
        if first < 0 or last < first:
            raise ValueError(f"bad CPU list {text!r}: range {part} is empty or negative")
        cores.update(range(first, last + 1))
    if not cores:
        raise ValueError(f"bad CPU list {text!r}: no core named")
    return tuple(sorted(cores))


def read_proc_stat_cores(cores: Sequence[int], path: str = "/proc/stat") -> Tuple[int, int]:
    """(idle, total) jiffies summed over the per-core lines `cpuN` of the given cores only: the
    robot's availability is that of the cores its processes are pinned to, not the whole host's."""
    wanted = {f"cpu{core}" for core in cores}
    idle = total = 0
    found = set()
    with open(path) as stat:
        for line in stat:
            fields = line.split()
            if fields and fields[0] in wanted:
                values = [int(v) for v in fields[1:]]
                idle += values[3] + (values[4] if len(values) > 4 else 0)
                total += sum(values[:8])
                found.add(fields[0])
    missing = wanted - found
    if missing:
        raise ValueError(f"{path} has no line for {', '.join(sorted(missing))}: no such core")
    return idle, total


class CgroupBudgetReader:
    """(idle, total) nanoseconds of a cgroup v1 CPU budget, for CpuAvailability: total is wall time
    times the budget in cores (cpu.cfs_quota_us / cpu.cfs_period_us), idle is that minus the CPU time
    the group used (cpuacct.usage). Under a quota the robot's cores look mostly idle to /proc/stat
    while the robot itself is starved; this measures what is left of the robot's own budget."""

    def __init__(self, group: str, root: str = "/sys/fs/cgroup",
                 clock: Callable[[], int] = time.monotonic_ns):
        self.group = group.strip("/")
        cpu_dir = os.path.join(root, "cpu", self.group)
        self.usage_path = os.path.join(root, "cpuacct", self.group, "cpuacct.usage")
        try:
            with open(os.path.join(cpu_dir, "cpu.cfs_quota_us")) as quota_file:
                quota_us = int(quota_file.read())
            with open(os.path.join(cpu_dir, "cpu.cfs_period_us")) as period_file:
                period_us = int(period_file.read())
            self._read_usage()
        except (OSError, ValueError) as error:
            raise ValueError(f"cgroup {self.group!r} has no readable cpu quota and cpuacct usage under "
                             f"{root}: {error}") from error
        if quota_us <= 0 or period_us <= 0:
            raise ValueError(f"cgroup {self.group!r} has no CPU quota (cpu.cfs_quota_us is {quota_us})")
        self.budget_cores = quota_us / period_us
        self._clock = clock

    def _read_usage(self) -> int:
        with open(self.usage_path) as usage:
            return int(usage.read())

    def __call__(self) -> Tuple[int, int]:
        total = int(self._clock() * self.budget_cores)
        return total - self._read_usage(), total


class LatestCpuAvailability:
    """u_t for the request path, which must never wait: the idle share over the latest window in which
    the counters advanced by at least min_window (jiffy counters tick every 10 ms). A request arriving
    sooner gets the last measured value instead of a sleep. The first measurement is taken at
    construction, so there always is one."""

    def __init__(self, reader: Callable[[], Tuple[int, int]], min_window: int,
                 sleep: Callable[[float], None] = time.sleep, first_interval_s: float = 0.05):
        self._reader = reader
        self._min_window = min_window
        self._previous = reader()
        sleep(first_interval_s)
        self.value = float("nan")
        self._measure(force=True)

    def _measure(self, force: bool = False) -> float:
        idle, total = self._reader()
        elapsed = total - self._previous[1]
        if elapsed >= self._min_window or (force and elapsed > 0):
            self.value = min(1.0, max(0.0, (idle - self._previous[0]) / elapsed))
            self._previous = (idle, total)
        elif force:
            raise RuntimeError("CPU time counters did not advance; cannot measure availability")
        return self.value

    def sample(self) -> float:
        return self._measure()


def make_cpu_sampler(cores: str, cgroup: str) -> LatestCpuAvailability:
    """u_t of the robot: what is left of its cgroup CPU budget when it has one, else the idle share of
    the cores it is pinned to, else of the whole host. Never waits on the request path."""
    if cgroup:
        reader = CgroupBudgetReader(cgroup)
        return LatestCpuAvailability(reader, min_window=int(0.02 * 1e9 * reader.budget_cores))   # 20 ms
    if cores:
        pinned = parse_cpu_list(cores)
        return LatestCpuAvailability(lambda: read_proc_stat_cores(pinned), min_window=2 * len(pinned))
    return LatestCpuAvailability(read_proc_stat, min_window=2 * (os.cpu_count() or 1))
