"""The demo driver's own duties, without ROS: options checked before anything starts, stale CPU budgets of
dead drivers removed, and roslaunch ending with the driver however the driver dies."""
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from offload_demos import driver as demo

MAPS = os.path.join(os.path.dirname(__file__), "..", "..", "offload_planner_cpp", "maps")


def options(**overrides):
    return SimpleNamespace(**{"steps": 10, "map": "", "model": "", "fleet": False, "fleet_seed_bag": "",
                              "policy": "dqn", "mode": "learning", **overrides})


def test_options_are_checked_before_anything_starts(tmp_path):
    assert demo.check_options(options()) == ""
    assert demo.check_options(options(map=os.path.join(MAPS, "turtlebot3_world", "map.yaml"))) == ""
    assert "positive" in demo.check_options(options(steps=0))
    assert "MAP /nonexistent.yaml" in demo.check_options(options(map="/nonexistent.yaml"))
    missing_image = tmp_path / "map.yaml"
    missing_image.write_text("image: gone.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 0\n"
                             "occupied_thresh: 0.65\nfree_thresh: 0.196\n")
    problem = demo.check_options(options(map=str(missing_image)))
    assert problem.startswith(f"MAP {missing_image}") and "\n" not in problem
    assert "no such file" in demo.check_options(options(model=str(tmp_path / "none.pt")))
    # the fleet learner serves the deployed DQN only, and its seed bag must be there
    assert demo.check_options(options(fleet=True, mode="deployed")) == ""
    assert "--policy dqn --mode deployed" in demo.check_options(options(fleet=True, mode="learning"))
    assert "--policy dqn --mode deployed" in demo.check_options(options(fleet=True, mode="deployed", policy="local"))
    assert "no such file" in demo.check_options(options(fleet=True, mode="deployed",
                                                        fleet_seed_bag=str(tmp_path / "none.bag")))


def test_budgets_of_dead_drivers_are_removed_and_live_ones_kept(tmp_path, monkeypatch):
    monkeypatch.setattr(demo, "CGROUP_ROOT", str(tmp_path))
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for controller in ("cpu", "cpuacct"):
        (tmp_path / controller / f"offload_robot_{dead.pid}").mkdir(parents=True)
        (tmp_path / controller / f"offload_robot_{os.getpid()}").mkdir()
    removed = demo.remove_stale_budgets()
    assert sorted(os.path.basename(path) for path in removed) == [f"offload_robot_{dead.pid}"] * 2
    assert sorted(p.name for p in (tmp_path / "cpu").iterdir()) == [f"offload_robot_{os.getpid()}"]


def test_the_launch_ends_when_the_driver_is_killed(tmp_path):
    pid_file = tmp_path / "child.pid"
    driver = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
        import subprocess, time
        from offload_demos.driver import end_with_parent
        child = subprocess.Popen(["sleep", "60"], start_new_session=True, preexec_fn=end_with_parent)
        open({str(pid_file)!r}, "w").write(str(child.pid))
        time.sleep(60)
        """)])
    deadline = time.monotonic() + 30
    while not (pid_file.exists() and pid_file.read_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    child = int(pid_file.read_text())
    driver.kill()                      # SIGKILL: no handler of the driver runs
    driver.wait()
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            return
        if open(f"/proc/{child}/stat").read().split()[2] == "Z":
            return                     # dead, waiting for init to reap it
        time.sleep(0.05)
    os.kill(child, signal.SIGKILL)
    raise AssertionError("the child outlived the driver")


@pytest.mark.parametrize("script, expected", [("demo_cloud_server", "--keys-dir"), ("demo_wan_emulator", "--upstream")])
def test_the_demos_cloud_host_nodes_start(script, expected):
    """The demo's cloud server once called a main() the move to offload_cloud had taken away: it died at start,
    every request fell back to the local side, and the demo still exited 0. Each script's command line answers."""
    path = Path(__file__).resolve().parents[1] / "scripts" / script
    done = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and expected in done.stdout, done.stderr[-2000:]
