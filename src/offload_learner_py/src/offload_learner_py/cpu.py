"""CPU availability u_t in [0, 1], measured from the OS as the idle share of CPU time between two
readings of /proc/stat (the kernel's own accounting, so no extra dependency is needed)."""
import time
from typing import Callable, Optional, Tuple


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
