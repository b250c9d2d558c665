"""A bounded coverage-guided fuzz run (atheris) of the bag reader, seeded with real small bags: every
input reads or is refused with BagReadError, within libFuzzer's memory limit. `make fuzz` runs it longer."""
import os
import subprocess
import sys

import pytest


def tmp_dir(tmp_path):
    (tmp_path / "tmp").mkdir()
    return tmp_path / "tmp"


@pytest.mark.timeout(300)
def test_bag_reader_fuzz_finds_no_crash(tmp_path):
    # Through a shell that forks it: libFuzzer's rss is the process's peak (ru_maxrss), which Linux carries over
    # exec from the forked parent, so a fuzzer started straight from a pytest process of 1.1 GB (the whole suite's)
    # reported 1090-1210 MB before its first input and stopped "out of memory" at its 1024 MB limit.
    done = subprocess.run(["sh", "-c", '"$@"; exit $?', "sh", sys.executable, "-m", "offload_demos.fuzz_bag",
                           "-runs=2000", "-max_len=8192", "-seed=1", "-rss_limit_mb=1024",
                           f"-artifact_prefix={tmp_path}/"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=280,
                          env={**os.environ, "TMPDIR": str(tmp_dir(tmp_path))})
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    assert not any((tmp_path / "tmp").iterdir()), "the run left files in the temporary directory"
    assert "Done 2000 runs" in done.stderr
