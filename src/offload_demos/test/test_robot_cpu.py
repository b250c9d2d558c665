"""The robot's whole CPU (#30 item 7): a fake cgroup and a fake /proc with known counters give known figures
(the workload apart, every process in the sum, what no process accounts for kept in the total), windows are
interpolated, runs pool, robot_confine lists what it starts, and bench-policies' measure reports it."""
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bagtools import make_requests, write
from offload_demos import robot_cpu
from offload_demos.bench_measure import measure

TICK = robot_cpu.CLOCK_TICKS_S
CONFINE = Path(__file__).resolve().parents[1] / "scripts" / "robot_confine"


class FakeRobot:
    """A cgroup dir and a /proc dir whose counters the test sets."""

    def __init__(self, root: Path, with_cgroup: bool = True):
        self.cgroup = root / "cpuacct" / "offload_robot_1" if with_cgroup else None
        self.proc = root / "proc"
        self.pids_file = root / "robot_pids.txt"
        self.proc.mkdir(parents=True)
        if self.cgroup:
            self.cgroup.mkdir(parents=True)
        self.in_group, self.listed = [], []
        self.pids_file.write_text("")

    def process(self, pid: int, cmdline, in_group=True, listed=True):
        (self.proc / str(pid)).mkdir()
        (self.proc / str(pid) / "cmdline").write_bytes(b"\0".join(word.encode() for word in cmdline) + b"\0")
        if in_group:
            self.in_group.append(pid)
        if listed:
            with open(self.pids_file, "a") as out:
                out.write(f"{pid} {' '.join(cmdline)}\n")
        self._procs()

    def _procs(self):
        if self.cgroup:
            (self.cgroup / "cgroup.procs").write_text("".join(f"{pid}\n" for pid in self.in_group))

    def cpu(self, pid: int, seconds: float):
        ticks = int(round(seconds / TICK))
        # utime stime cutime cstime split unevenly; the command holds ") (" to trip a naive parser
        (self.proc / str(pid) / "stat").write_text(
            f"{pid} (py) (thon) S 1 1 1 0 -1 0 0 0 0 0 {ticks - ticks // 3} {ticks // 3 - ticks // 7} {ticks // 7} 0 "
            "20 0 1 0 0 0 0\n")

    def exit(self, pid: int):
        for name in ("stat", "cmdline"):
            (self.proc / str(pid) / name).unlink()
        (self.proc / str(pid)).rmdir()
        if pid in self.in_group:
            self.in_group.remove(pid)
        self._procs()

    def cgroup_s(self, seconds: float):
        (self.cgroup / "cpuacct.usage").write_text(f"{int(round(seconds * 1e9))}\n")

    def sampler(self, clock):
        return robot_cpu.CpuSampler(str(self.cgroup) if self.cgroup else None, str(self.pids_file),
                                    proc_root=str(self.proc), clock=clock)


def node(name, script):
    return [sys.executable, f"/opt/robot/lib/{script}", f"__name:={name}", "__log:=/tmp/x.log"]


def robot(tmp_path, with_cgroup=True):
    fake = FakeRobot(tmp_path, with_cgroup)
    fake.process(101, ["/opt/robot/lib/offload_planner_cpp/planner_node", "__name:=planner"])
    fake.process(102, node("cloud_bridge", "cloud_bridge"))
    fake.process(103, node("offload_learner", "offload_learner"))
    fake.process(104, node("robot_workload", "robot_workload"))
    return fake


def test_stat_and_names_are_parsed():
    line = "42 (a) (b c) R 1 1 1 0 -1 0 0 0 0 0 150 50 7 3 20 0 1 0\n"
    assert robot_cpu.process_cpu_s(line) == pytest.approx((150 + 50 + 7 + 3) * TICK)
    assert robot_cpu.process_name(["/usr/bin/python3", "/x/offload_learner", "__name:=offload_learner"]) == "offload_learner"
    assert robot_cpu.process_name(["/usr/bin/python3", "-u", "/x/tool.py"]) == "tool.py"
    assert robot_cpu.process_name(["/x/planner_node"]) == "planner_node"


def test_known_counters_give_the_total_without_the_workload(tmp_path):
    fake, now = robot(tmp_path), [100.0]
    # the workload forks helpers (tools.workload_main): in the group, not in robot_confine's list, its command line
    fake.process(108, node("robot_workload", "robot_workload"), listed=False)
    sampler = fake.sampler(lambda: now[0])
    for t, (planner, bridge, learner, workload, group) in [(100.0, (1.0, 0.5, 2.0, 3.0, 7.0)),
                                                          (110.0, (3.0, 1.0, 2.5, 8.0, 18.0))]:
        now[0] = t
        for pid, value in zip((101, 102, 103, 104), (planner, bridge, learner, workload)):
            fake.cpu(pid, value)
        fake.cpu(108, (t - 100.0) / 5.0)
        fake.cgroup_s(group)
        sampler.sample()
    figures = robot_cpu.robot_cpu(robot_cpu.window_usage(sampler.samples, 100.0, 110.0), requests=40)
    assert figures["source"] == "cgroup"
    assert figures["workload_cpu_s"] == pytest.approx(5.0 + 2.0)
    # the cgroup's 11 s less the workload's 5 + 2 s; the nodes account for 2 + 0.5 + 0.5 = 3 s of it
    assert figures["total_cpu_s"] == pytest.approx(4.0)
    assert figures["planner_cpu_s"] == pytest.approx(2.0)
    assert figures["bridge_cpu_s"] == pytest.approx(0.5)
    assert figures["learner_cpu_s"] == pytest.approx(0.5)
    assert figures["unattributed_cpu_s"] == pytest.approx(1.0)
    assert figures["total_cpu_s_per_request"] == pytest.approx(0.1)
    assert figures["workload_cpu_s_per_request"] == pytest.approx(7.0 / 40)
    # half the window: every counter interpolated linearly
    half = robot_cpu.robot_cpu(robot_cpu.window_usage(sampler.samples, 102.5, 107.5), requests=20)
    assert half["total_cpu_s"] == pytest.approx(2.0) and half["workload_cpu_s"] == pytest.approx(3.5)


def test_every_process_counts_without_a_cgroup_and_one_that_exits_keeps_its_share(tmp_path):
    fake, now = robot(tmp_path, with_cgroup=False), [0.0]
    # a process robot_confine started that is not a known node: it is the robot's too ("other")
    fake.process(105, ["/usr/bin/helper", "--x"])
    sampler = fake.sampler(lambda: now[0])
    for pid in (101, 102, 103, 104, 105):
        fake.cpu(pid, 1.0)
    sampler.sample()
    now[0] = 10.0
    for pid, value in ((101, 2.0), (102, 1.5), (103, 1.25), (104, 9.0), (105, 1.5)):
        fake.cpu(pid, value)
    sampler.sample()
    fake.exit(102)                       # the bridge dies; its respawn comes up as a new process
    fake.process(106, node("cloud_bridge", "cloud_bridge"))
    fake.cpu(106, 0.5)
    now[0] = 20.0
    sampler.sample()
    figures = robot_cpu.robot_cpu(robot_cpu.window_usage(sampler.samples, 0.0, 20.0), requests=10)
    assert figures["source"] == "processes"
    assert figures["workload_cpu_s"] == pytest.approx(8.0)
    assert figures["bridge_cpu_s"] == pytest.approx(0.5 + 0.5)       # the one that died, and its respawn
    assert figures["other_cpu_s"] == pytest.approx(0.5)
    assert figures["total_cpu_s"] == pytest.approx(1.0 + 1.0 + 0.25 + 0.5)
    assert figures["unattributed_cpu_s"] == pytest.approx(0.0)


def test_a_process_not_in_the_list_is_still_in_the_cgroup_total(tmp_path):
    # A child a node forked (in the group, not listed by robot_confine) and CPU of processes gone between
    # samples: the group's counter has them; the sum by process does not.
    fake, now = robot(tmp_path), [0.0]
    fake.process(107, ["/bin/sh", "-c", "child"], listed=False)
    sampler = fake.sampler(lambda: now[0])
    for t, child, group in ((0.0, 0.0, 0.0), (5.0, 2.0, 6.0)):
        now[0] = t
        for pid in (101, 102, 103):
            fake.cpu(pid, t / 5.0)
        fake.cpu(104, 0.0)
        fake.cpu(107, child)
        fake.cgroup_s(group)
        sampler.sample()
    figures = robot_cpu.robot_cpu(robot_cpu.window_usage(sampler.samples, 0.0, 5.0), requests=1)
    assert figures["other_cpu_s"] == pytest.approx(2.0)
    assert figures["total_cpu_s"] == pytest.approx(6.0)
    assert figures["unattributed_cpu_s"] == pytest.approx(1.0)


def test_windows_outside_the_samples_and_empty_runs_are_refused(tmp_path):
    fake, now = robot(tmp_path), [1.0]
    sampler = fake.sampler(lambda: now[0])
    for pid in (101, 102, 103, 104):
        fake.cpu(pid, 0.0)
    fake.cgroup_s(0.0)
    sampler.sample()
    now[0] = 2.0
    sampler.sample()
    with pytest.raises(ValueError, match="not inside"):
        robot_cpu.window_usage(sampler.samples, 0.5, 2.0)
    with pytest.raises(ValueError, match="ends before"):
        robot_cpu.window_usage(sampler.samples, 1.8, 1.2)
    with pytest.raises(ValueError):
        robot_cpu.robot_cpu(robot_cpu.window_usage(sampler.samples, 1.0, 2.0), requests=0)


def test_runs_pool_by_seconds_and_requests():
    a = {"source": "cgroup", "requests": 10, "window_s": 5.0, "total_cpu_s": 1.0, "workload_cpu_s": 2.0}
    b = {"source": "cgroup", "requests": 30, "window_s": 15.0, "total_cpu_s": 5.0, "workload_cpu_s": 2.0}
    pooled = robot_cpu.pool([a, b])
    assert pooled["total_cpu_s_per_request"] == pytest.approx(6.0 / 40)
    assert pooled["workload_cpu_s_per_request"] == pytest.approx(0.1)
    assert robot_cpu.pool([a, None]) is None


def test_the_request_window_is_first_arrival_to_last_answer():
    stamps = np.array([10, 11, 12], dtype=np.int64) * 1_000_000_000
    assert robot_cpu.request_window(stamps, np.array([0.5, 3.0, np.nan])) == pytest.approx((10.0, 14.0))


def test_robot_confine_lists_the_process_it_becomes(tmp_path):
    pids = tmp_path / "pids.txt"
    out = subprocess.run([str(CONFINE), "0", "-", sys.executable, "-c", "import os; print(os.getpid())"],
                         env=dict(os.environ, OFFLOAD_ROBOT_PIDS=str(pids)), capture_output=True, text=True, check=True)
    pid, command = pids.read_text().split(" ", 1)
    assert pid == out.stdout.strip() and command.startswith(sys.executable)


def test_a_live_process_is_sampled_from_proc(tmp_path):
    pids = tmp_path / "pids.txt"
    burner = subprocess.Popen([str(CONFINE), "0", "-", sys.executable, "-c",
                               "import time\nend = time.process_time() + 0.4\nwhile time.process_time() < end: pass\n"
                               "time.sleep(0.5)\nprint(time.process_time())"],
                              env=dict(os.environ, OFFLOAD_ROBOT_PIDS=str(pids)), stdout=subprocess.PIPE, text=True)
    sampler = robot_cpu.CpuSampler(None, str(pids), period_s=0.05)
    time.sleep(0.05)
    sampler.start()
    own_s = float(burner.communicate()[0])
    sampler.stop()
    usage = robot_cpu.window_usage(sampler.samples, sampler.samples[0]["t"], sampler.samples[-1]["t"])
    # the process's whole CPU, less what it spent before the first sample (start-up) and tick rounding
    assert usage["by_group"]["other"] == pytest.approx(own_s, abs=0.15)


def test_bench_measure_reports_the_robots_total_per_request(tmp_path):
    run = tmp_path / "dqn"
    run.mkdir()
    write(run / "offload.bag", make_requests(20, probe_every=4))    # one request every 0.1 s from 1.7e9 s
    t0 = 1_700_000_000.0
    samples = [{"t": t0 - 1.0, "cgroup_ns": 0, "procs": {"1": ["planner", 0.0], "2": ["robot_workload", 0.0]}},
               {"t": t0 + 5.0, "cgroup_ns": int(6e9), "procs": {"1": ["planner", 1.2], "2": ["robot_workload", 3.6]}}]
    (run / robot_cpu.SAMPLES_FILE).write_text(json.dumps({"samples": samples}))
    figures = measure(run, 5.0)
    window = figures["robot_cpu"]["window_s"]
    assert 1.9 < window < 2.1
    # every counter rises linearly over the samples' 6 s: the window's share of the group less the workload's
    assert figures["robot_total_cpu_s_per_request"] == pytest.approx((6.0 - 3.6) * window / 6.0 / 20)
    assert figures["robot_workload_cpu_s_per_request"] == pytest.approx(3.6 * window / 6.0 / 20)
    (run / robot_cpu.SAMPLES_FILE).unlink()
    assert measure(run, 5.0)["robot_total_cpu_s_per_request"] is None


def test_the_recorder_is_a_robot_process_of_its_own():
    """The recorder on the robot (offload_record becomes offload_bag_recorder; `rosbag record`'s C++ recorder is a
    child): its CPU is the robot's and shows apart, not in `other`."""
    for cmdline in (["/usr/bin/python3", "/x/offload_record", "--bag", "b", "__name:=offload_record"],
                    ["/x/offload_bag_recorder", "--min-free-mib", "1024", "b.bag", "/t", "__name:=offload_record"],
                    ["/x/offload_bag_recorder", "b.bag", "/t"],
                    ["/usr/bin/python3", "/usr/bin/rosbag", "record", "-O", "b.bag", "/t"],
                    ["/usr/lib/rosbag/record", "--buffsize", "256", "-O", "b.bag", "/t"]):
        assert robot_cpu.group_of(robot_cpu.process_name(cmdline)) == "recorder", cmdline
    assert robot_cpu.group_of("tool.py") == "other"


def test_a_process_caught_inside_an_exec_is_named_later_and_its_cpu_stays_the_workloads(tmp_path):
    """bench-policies (held-out load pulse, the DQN's first run): the sampler read the workload's command line while
    it was empty (inside an exec), named it "?" for the whole run, and the workload's 10.9 CPU-s counted as the
    robot's "other": the DQN's robot total read 21.6 ms a request instead of 10.3."""
    fake, now = robot(tmp_path), [100.0]
    fake.process(109, node("robot_workload", "robot_workload"), listed=False)   # a forked helper, not in the list
    (fake.proc / "104" / "cmdline").write_bytes(b"")                           # mid-exec
    (fake.proc / "109" / "cmdline").write_bytes(b"")
    sampler = fake.sampler(lambda: now[0])
    for t, workload in ((100.0, 1.0), (110.0, 6.0)):
        now[0] = t
        for pid, value in ((101, 1.0), (102, 0.5), (103, 2.0), (104, workload), (109, workload)):
            fake.cpu(pid, value)
        fake.cgroup_s(3.5 + 2 * workload)
        sampler.sample()
        (fake.proc / "109" / "cmdline").write_bytes(b"/opt/robot/lib/robot_workload\0__name:=robot_workload\0")
    assert [s["procs"][104][0] for s in sampler.samples] == ["robot_workload"] * 2   # from robot_confine's list
    assert [s["procs"][109][0] for s in sampler.samples] == ["?", "robot_workload"]  # read again, not kept as "?"
    figures = robot_cpu.robot_cpu(robot_cpu.window_usage(sampler.samples, 100.0, 110.0), requests=10)
    assert figures["workload_cpu_s"] == pytest.approx(10.0) and figures["other_cpu_s"] == 0.0
    assert figures["total_cpu_s"] == pytest.approx(0.0)


def test_samples_saved_with_an_unknown_name_are_named_from_robot_confines_list(tmp_path):
    run = tmp_path / "dqn"
    run.mkdir()
    write(run / "offload.bag", make_requests(20, probe_every=4))
    t0 = 1_700_000_000.0
    samples = [{"t": t0 - 1.0, "cgroup_ns": 0, "procs": {"1": ["planner", 0.0], "2": ["?", 0.0]}},
               {"t": t0 + 5.0, "cgroup_ns": int(6e9), "procs": {"1": ["planner", 1.2], "2": ["?", 3.6]}}]
    (run / robot_cpu.SAMPLES_FILE).write_text(json.dumps({"samples": samples}))
    (run / robot_cpu.PIDS_FILE).write_text("1 /x/planner_node __name:=planner\n2 /x/robot_workload __name:=robot_workload "
                                          "__log:=/tmp/w.log\n")
    figures = measure(run, 5.0)["robot_cpu"]
    assert figures["other_cpu_s"] == 0.0 and figures["workload_cpu_s"] == pytest.approx(3.6 * figures["window_s"] / 6)
