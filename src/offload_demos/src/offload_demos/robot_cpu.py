"""What the robot pays in full: the CPU of everything on the robot's side, not only the planning the nodes
account for themselves (#30 item 7).

The demo runs every robot process through scripts/robot_confine (planner node, cloud bridge, learner, the
recorder and the background workload), inside the cgroup v1 `offload_robot_<pid>` when the robot has a CPU budget. A sampler
thread in the demo driver reads, every `period_s`:
- the cgroup's cpuacct.usage (nanoseconds of CPU charged to the group since it was made: every process in
  it, threads and children included, and the processes that have exited);
- each robot process's own utime + stime (+ its waited-for children's) from /proc/<pid>/stat, the processes
  being those in the group's cgroup.procs and those robot_confine listed in $OFFLOAD_ROBOT_PIDS (one
  "<pid> <command>" line each; the list is all there is without a budget).
The run's window is its requests' span (the first decision to the last answer, from the bag); each counter is
interpolated linearly at the window's ends. The robot's total is the cgroup's usage less the workload's (the
workload burns CPU on purpose: it is the condition the policies meet, not their cost, and is reported
apart); without a cgroup, the sum of the robot processes' other than the workload's. What no sampled process
accounts for (a process that came and went between samples, a respawned node's predecessor) stays in the
total and is reported as `unattributed`. No ROS import."""
import json
import os
import pathlib
import threading
import time
from typing import Callable, Dict, Iterable, List, Optional

import numpy as np

PIDS_ENV = "OFFLOAD_ROBOT_PIDS"     # robot_confine appends "<pid> <command...>" to this file when it is set
PIDS_FILE = "robot_pids.txt"                 # in a demo run's directory: robot_confine's list
SAMPLES_FILE = "robot_cpu_samples.json"      # in a demo run's directory: the counters over the run
WORKLOAD_NODES = ("robot_workload",)
# The robot's nodes by their ROS name (the `__name:=` roslaunch gives them); any other process is "other".
NODE_GROUPS = {"planner": "planner", "cloud_bridge": "bridge", "offload_learner": "learner",
               "robot_workload": "workload",
               # the recorder on the robot: offload_record becomes offload_bag_recorder (exec, the same process); a
               # `rosbag record` (older launch files) runs its C++ recorder as a child process
               "offload_record": "recorder", "offload_bag_recorder": "recorder", "rosbag": "recorder",
               "record": "recorder"}
CLOCK_TICKS_S = 1.0 / os.sysconf("SC_CLK_TCK")


def process_cpu_s(stat_text: str) -> float:
    """utime + stime + cutime + cstime of a /proc/<pid>/stat line, in seconds (the command may hold spaces
    and parentheses: the fields start after the last ')')."""
    fields = stat_text[stat_text.rindex(")") + 2:].split()
    # fields[0] is field 3 (state): utime..cstime are fields 14..17
    return sum(int(value) for value in fields[11:15]) * CLOCK_TICKS_S


UNKNOWN = "?"   # process_name of an empty command line: a process caught inside an exec reads so


def process_name(cmdline: List[str]) -> str:
    """The ROS node name of a command line (`__name:=planner`), else the program's base name (the script's,
    for an interpreter running one)."""
    for argument in cmdline:
        if argument.startswith("__name:="):
            return argument.split(":=", 1)[1]
    words = [word for word in cmdline if not word.startswith("-")]
    if len(words) > 1 and os.path.basename(words[0]).startswith("python"):
        return os.path.basename(words[1])
    return os.path.basename(words[0]) if words else UNKNOWN


def listed_names(pids_file) -> Dict[int, str]:
    """{pid: node name} from robot_confine's list ("<pid> <command...>" lines, written before the exec; a pid
    without its command is listed as UNKNOWN)."""
    names = {}
    try:
        lines = pathlib.Path(pids_file).read_text().splitlines()
    except OSError:
        return names
    for line in lines:
        words = line.split()
        if words and words[0].isdigit():
            names[int(words[0])] = process_name(words[1:])
    return names


def group_of(name: str) -> str:
    return NODE_GROUPS.get(name, "other")


class CpuSampler:
    """Samples the robot's CPU counters (see the module's text) on a thread; `samples` is the list of
    {"t": wall-clock s, "cgroup_ns": int or None, "procs": {pid: [name, cpu_s]}}."""

    def __init__(self, cgroup_dir: Optional[str] = None, pids_file: Optional[str] = None, proc_root: str = "/proc",
                 period_s: float = 0.2, clock: Callable[[], float] = time.time):
        self.cgroup_dir, self.pids_file, self.proc_root = cgroup_dir, pids_file, pathlib.Path(proc_root)
        self.period_s, self.clock = period_s, clock
        self.samples: List[Dict] = []
        self.names: Dict[int, str] = {}
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def pids(self, listed: Optional[Dict[int, str]] = None) -> Iterable[int]:
        """The cgroup's processes and robot_confine's list (`listed`, read from pids_file when not given)."""
        found = set()
        if self.cgroup_dir:
            try:
                found.update(int(pid) for pid in pathlib.Path(self.cgroup_dir, "cgroup.procs").read_text().split())
            except (OSError, ValueError):
                pass
        if listed is None and self.pids_file:
            listed = listed_names(self.pids_file)
        found.update(listed or ())
        return sorted(found)

    def sample(self) -> Dict:
        cgroup_ns = None
        if self.cgroup_dir:
            try:
                cgroup_ns = int(pathlib.Path(self.cgroup_dir, "cpuacct.usage").read_text())
            except (OSError, ValueError):
                pass
        procs = {}
        listed = listed_names(self.pids_file) if self.pids_file else {}     # read once a sample
        for pid in self.pids(listed):
            try:
                if pid not in self.names:
                    cmdline = (self.proc_root / str(pid) / "cmdline").read_bytes().split(b"\0")
                    name = process_name([part.decode(errors="replace") for part in cmdline if part])
                    if name == UNKNOWN:
                        name = listed.get(pid, UNKNOWN)
                    if name != UNKNOWN:   # read again next time: an exec empties the command line for a moment
                        self.names[pid] = name
                procs[pid] = [self.names.get(pid, UNKNOWN),
                              process_cpu_s((self.proc_root / str(pid) / "stat").read_text())]
            except (OSError, ValueError, IndexError):
                continue        # gone between the listing and the read: its last sample stands
        record = {"t": self.clock(), "cgroup_ns": cgroup_ns, "procs": procs}
        self.samples.append(record)
        return record

    def _run(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.period_s)

    def start(self) -> "CpuSampler":
        self._thread = threading.Thread(target=self._run, name="robot-cpu", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.sample()

    def save(self, path) -> None:
        with open(path, "w") as out:
            json.dump({"cgroup_dir": self.cgroup_dir, "period_s": self.period_s,
                       "samples": [{**s, "procs": {str(pid): v for pid, v in s["procs"].items()}}
                                   for s in self.samples]}, out)


def _at(times: np.ndarray, values: np.ndarray, t: float) -> float:
    return float(np.interp(t, times, values))


def window_usage(samples: List[Dict], t0: float, t1: float) -> Dict:
    """CPU seconds spent in [t0, t1] (wall-clock s): the cgroup's (None without one) and each process's, by
    pid and by group, each counter interpolated at the window's ends. A process is at 0 before it was first
    seen (started in between) and at its last value after it was last seen (exited)."""
    if not samples:
        raise ValueError("no CPU sample")
    if not t1 >= t0:
        raise ValueError(f"window ends before it begins: [{t0}, {t1}]")
    times = np.asarray([s["t"] for s in samples], dtype=np.float64)
    if t0 < times[0] or t1 > times[-1]:
        raise ValueError(f"window [{t0:.3f}, {t1:.3f}] not inside the samples' [{times[0]:.3f}, {times[-1]:.3f}]")
    cgroup = [s.get("cgroup_ns") for s in samples]
    cgroup_s = None
    if all(value is not None for value in cgroup):
        counter = np.asarray(cgroup, dtype=np.float64) * 1e-9
        cgroup_s = _at(times, counter, t1) - _at(times, counter, t0)
    names: Dict[str, str] = {}
    for s in samples:
        for pid, (name, _) in s["procs"].items():
            if name != UNKNOWN or str(pid) not in names:
                names[str(pid)] = name
    by_pid = {}
    for pid in names:
        series, last = [], 0.0
        for s in samples:
            entry = s["procs"].get(pid, s["procs"].get(int(pid)) if pid.isdigit() else None)
            last = entry[1] if entry is not None else last
            series.append(last)
        spent = _at(times, np.asarray(series), t1) - _at(times, np.asarray(series), t0)
        if spent > 0:
            by_pid[pid] = spent
    groups: Dict[str, float] = {}
    for pid, spent in by_pid.items():
        group = group_of(names[pid])
        groups[group] = groups.get(group, 0.0) + spent
    return {"window_s": t1 - t0, "cgroup_cpu_s": cgroup_s, "by_pid": by_pid,
            "names": {pid: names[pid] for pid in by_pid}, "by_group": groups}


def robot_cpu(usage: Dict, requests: int) -> Dict:
    """The robot's figures of one window: total (the policy's cost: everything but the workload), each group's,
    the workload apart and what no sampled process accounts for; per request too."""
    if requests < 1:
        raise ValueError(f"requests must be positive, got {requests}")
    groups = dict(usage["by_group"])
    workload_s = groups.pop("workload", 0.0)
    processes_s = sum(groups.values())
    if usage["cgroup_cpu_s"] is not None:
        total_s, source = usage["cgroup_cpu_s"] - workload_s, "cgroup"
    else:
        total_s, source = processes_s, "processes"
    figures = {"source": source, "requests": requests, "window_s": usage["window_s"], "total_cpu_s": total_s,
               "workload_cpu_s": workload_s, "unattributed_cpu_s": total_s - processes_s,
               **{f"{group}_cpu_s": spent for group, spent in groups.items()}}
    for group in ("planner", "bridge", "learner", "recorder", "other"):
        figures.setdefault(f"{group}_cpu_s", 0.0)
    return {**figures, **per_request(figures)}


def per_request(figures: Dict) -> Dict:
    return {key[:-len("_cpu_s")] + "_cpu_s_per_request": value / figures["requests"]
            for key, value in figures.items() if key.endswith("_cpu_s")}


def pool(runs: List[Dict]) -> Optional[Dict]:
    """Several runs' figures as one (CPU seconds and requests summed); None if any run has none."""
    if not runs or any(run is None for run in runs):
        return None
    keys = [key for key in runs[0] if key.endswith("_cpu_s")]
    figures = {"source": ",".join(sorted({run["source"] for run in runs})),
               "requests": sum(run["requests"] for run in runs), "window_s": sum(run["window_s"] for run in runs),
               **{key: sum(run.get(key, 0.0) for run in runs) for key in keys}}
    return {**figures, **per_request(figures)}


def request_window(stamp_ns: np.ndarray, delivered_s: np.ndarray) -> tuple:
    """(first request's arrival, last answer) in wall-clock seconds, from the request log's decision stamps and
    delivered latencies (an unanswered request's latency is NaN: its arrival bounds the window)."""
    arrivals = np.asarray(stamp_ns, dtype=np.float64) * 1e-9
    answers = arrivals + np.nan_to_num(np.asarray(delivered_s, dtype=np.float64), nan=0.0)
    return float(arrivals.min()), float(answers.max())


def run_robot_cpu(samples_path, stamp_ns, delivered_s) -> Optional[Dict]:
    """A run's robot CPU figures from its samples file and its requests (the request log's decision stamps and
    delivered latencies); None when the run has no samples (a run from before them) or no request."""
    if not os.path.exists(samples_path) or len(stamp_ns) == 0:
        return None
    with open(samples_path) as stream:
        samples = json.load(stream)["samples"]
    # A process whose every sample reads UNKNOWN (samples written before the sampler read the list) is named by
    # robot_confine's list beside them: else the workload's CPU counted as the robot's "other".
    listed = listed_names(os.path.join(os.path.dirname(str(samples_path)), PIDS_FILE))
    for sample in samples:
        for pid, entry in sample["procs"].items():
            if entry[0] == UNKNOWN and str(pid).isdigit() and int(pid) in listed:
                entry[0] = listed[int(pid)]
    t0, t1 = request_window(stamp_ns, delivered_s)
    return robot_cpu(window_usage(samples, t0, t1), len(stamp_ns))


def format_robot_cpu(figures: Optional[Dict]) -> str:
    """The demo summary's line."""
    if figures is None:
        return "robot CPU: not sampled"
    ms = lambda name: 1e3 * figures.get(f"{name}_cpu_s_per_request", 0.0)  # noqa: E731
    return (f"robot CPU per request, everything on the robot's side ({figures['source']}, {figures['requests']} "
            f"requests over {figures['window_s']:.1f} s): total {ms('total'):.2f} ms = planner {ms('planner'):.2f} "
            f"+ bridge {ms('bridge'):.2f} + learner {ms('learner'):.2f} + recorder {ms('recorder'):.2f} + other "
            f"{ms('other'):.2f} + unattributed "
            f"{ms('unattributed'):.2f}; the workload apart: {ms('workload'):.2f} ms")
