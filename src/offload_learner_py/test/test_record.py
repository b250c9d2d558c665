"""offload_record's checks before it becomes rosbag record: never replace a bag, never record nothing."""
import os
import subprocess
import sys

import pytest

from offload_learner_py.nodes import record


def test_an_unnamed_bag_gets_a_new_time_stamped_name():
    assert record.bag_path("", "/data/offload", 0.0).startswith("/data/offload-19")
    assert record.bag_path("/data/run.bag", "/data/offload", 0.0) == "/data/run.bag"


def test_a_name_without_the_suffix_is_checked_as_the_file_rosbag_writes(tmp_path):
    """#31 Medium 7: with bag:=NAME, rosbag writes NAME.bag; the check looked at NAME and NAME.active, so an
    earlier run's NAME.bag went from 143 to 45 messages and a crashed run's NAME.bag.active was replaced."""
    assert record.bag_path(str(tmp_path / "run"), "/data/offload", 0.0) == str(tmp_path / "run.bag")
    for existing in ("run.bag", "run.bag.active"):
        (tmp_path / existing).write_bytes(b"#ROSBAG V2.0\n recorded requests")
        done = subprocess.run([sys.executable, "-m", "offload_learner_py.nodes.record", "--bag", str(tmp_path / "run"),
                               "--", "/offload_learner/decision"], capture_output=True, text=True)
        assert done.returncode == 1 and existing in done.stderr, done.stderr
        assert (tmp_path / existing).read_bytes().endswith(b"recorded requests")
        (tmp_path / existing).unlink()


@pytest.mark.parametrize("existing", ["run.bag", "run.bag.active"])
def test_an_existing_or_crashed_bag_is_never_replaced(tmp_path, existing):
    (tmp_path / existing).write_bytes(b"#ROSBAG V2.0\n recorded requests")
    why = record.problem(str(tmp_path / "run.bag"), min_free_mib=0)
    assert "refusing to replace" in why and existing in why
    assert (tmp_path / existing).read_bytes().endswith(b"recorded requests")


def test_too_little_free_space_is_refused_before_rosbag_starts(tmp_path):
    assert record.problem(str(tmp_path / "run.bag"), min_free_mib=0) == ""
    why = record.problem(str(tmp_path / "run.bag"), min_free_mib=1 << 30)   # a PiB: never free here
    assert "MiB free" in why and "record nothing" in why


def test_the_command_exits_non_zero_with_one_line(tmp_path):
    (tmp_path / "run.bag").write_bytes(b"x")
    done = subprocess.run([sys.executable, "-m", "offload_learner_py.nodes.record", "--bag", str(tmp_path / "run.bag"),
                           "--", "/offload_learner/decision", "__name:=offload_record"], capture_output=True, text=True)
    assert done.returncode == 1 and done.stderr.count("\n") == 1 and "refusing to replace" in done.stderr
