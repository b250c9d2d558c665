"""Bounded coverage-guided fuzz runs (atheris) of the protocol decoders and the map loaders: every input
decodes or is refused with the module's own error. `make fuzz` runs the same targets for longer."""
import os
import subprocess
import sys

import pytest

RUNS = {"protocol": 30000, "movingai": 1500, "map_yaml": 1500, "map_image": 1500}


def tmp_dir(tmp_path):
    (tmp_path / "tmp").mkdir()
    return tmp_path / "tmp"


@pytest.mark.timeout(300)
@pytest.mark.parametrize("target", sorted(RUNS))
def test_fuzz_target_finds_no_crash(target, tmp_path):
    done = subprocess.run([sys.executable, "-m", "offload_demos.fuzz", target, f"-runs={RUNS[target]}",
                           "-max_len=4096", "-seed=1", f"-artifact_prefix={tmp_path}/"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=280,
                          env={**os.environ, "TMPDIR": str(tmp_dir(tmp_path))})
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    assert not any((tmp_path / "tmp").iterdir()), "the run left files in the temporary directory"
    assert f"Done {RUNS[target]} runs" in done.stderr


def test_the_harness_reports_a_crash(tmp_path):
    """A target that raises something other than the module's own error is a crash (exit non-zero)."""
    code = ("import atheris, sys\n"
            "def target(data):\n"
            "    if len(data) > 3: raise KeyError('boom')\n"
            "atheris.Setup(sys.argv, target)\n"
            "atheris.Fuzz()\n")
    done = subprocess.run([sys.executable, "-c", code, "-runs=10000", f"-artifact_prefix={tmp_path}/"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode != 0 and "KeyError" in done.stdout + done.stderr
