"""tools/test_summary.py, the last step of `make test` and CI: a failure names the failed test and its first
message line, so a test that fails once on a CI machine can be found from the log alone."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

ROSUNIT = """<?xml version="1.0" encoding="utf-8"?>
<testsuite name="planner_node" tests="2" errors="0" failures="1">
  <testcase classname="pkg.PlannerNodeTest" name="test_fine" time="1.0"/>
  <testcase classname="pkg.PlannerNodeTest" name="test_long_plans" time="2.0">
    <failure type="AssertionError">AssertionError: 3.2 not less than 3.1 : the short plan waited
  File "rtest_planner_node.py", line 330</failure>
  </testcase>
</testsuite>
"""
PYTEST = """<testsuites><testsuite name="pytest" tests="1" errors="1" failures="0">
  <testcase classname="test_x" name="test_error"><error message="OSError: disk full"/></testcase>
</testsuite></testsuites>
"""


def run(results: Path):
    return subprocess.run([sys.executable, str(ROOT / "tools" / "test_summary.py"), str(results)],
                          capture_output=True, text=True)


def test_a_failed_test_is_named_with_its_message(tmp_path):
    (tmp_path / "rosunit").mkdir()
    (tmp_path / "rosunit" / "planner_node.xml").write_text(ROSUNIT)
    (tmp_path / "pytest.xml").write_text(PYTEST)
    result = run(tmp_path)
    assert result.returncode == 1
    assert "pkg.PlannerNodeTest.test_long_plans: AssertionError: 3.2 not less than 3.1 : the short plan waited" \
        in result.stdout
    assert "test_x.test_error: OSError: disk full" in result.stdout
    assert "test_fine" not in result.stdout
    assert "total: 1 passed, 2 failed, 0 skipped" in result.stdout


def test_all_passed_exits_zero(tmp_path):
    (tmp_path / "ok.xml").write_text('<testsuite tests="1" failures="0"><testcase name="t"/></testsuite>')
    result = run(tmp_path)
    assert result.returncode == 0 and "total: 1 passed, 0 failed" in result.stdout
