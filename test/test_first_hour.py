"""The README's first-hour commands, run as written (the venv's python, the module paths, the options) on a
bag of a run recorded for the test, so a renamed module or option breaks this test before a newcomer."""
import os
import re
import subprocess
import sys
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[1]


def first_hour_commands():
    text = (WORKSPACE / "README.md").read_text()
    block = re.search(r"<!-- first-hour -->\n```\n(.*?)```\n<!-- /first-hour -->", text, re.S)
    assert block, "the README's first-hour block is missing"
    return [line for line in block.group(1).splitlines() if line.startswith(".venv/bin/python ")]


def fresh_shell():
    return {name: value for name, value in os.environ.items()
            if not name.startswith(("ROS", "PYTHON", "CMAKE", "PKG_CONFIG", "LD_LIBRARY", "CATKIN"))}


def test_the_first_hour_commands_run_as_written(tmp_path):
    sys.path.insert(0, str(WORKSPACE / "src" / "offload_learner_py" / "test"))
    from bagtools import make_requests, write
    run = tmp_path / "runs" / "20260101-000000"
    run.mkdir(parents=True)
    write(run / "offload.bag", make_requests(120, probe_every=1))
    commands = first_hour_commands()
    assert [c.split()[2] for c in commands] == ["offload_learner_py.offline.retrain",
                                                "offload_learner_py.offline.report",
                                                "offload_learner_py.offline.off_policy"]
    for command in commands:
        argv = [str(WORKSPACE / ".venv" / "bin" / "python")] + command.replace("$RUN", str(run)).split()[1:]
        # A fresh shell: nothing of `source devel/setup.bash` (PYTHONPATH, ROS_*, CMAKE_PREFIX_PATH ...).
        done = subprocess.run(argv, cwd=WORKSPACE, capture_output=True, text=True, timeout=600, env=fresh_shell())
        assert done.returncode == 0, f"{command}\n{done.stderr[-2000:]}"
    assert (run / "retrained" / "checkpoint.pt").exists()
    assert (run / "report-again" / "report.html").exists()
