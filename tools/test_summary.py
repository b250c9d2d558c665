"""Adds up every JUnit XML file under a results directory (gtest, rostest, pytest) and prints one line per
file, the name and first message line of each failed test under it, and a closing total. Exits 1 when a
test failed or errored, or when none ran."""
import sys
import xml.etree.ElementTree as ET
from pathlib import Path


def counts(path):
    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else root.iter("testsuite")
    tests = failures = skipped = 0
    for suite in suites:
        tests += int(suite.get("tests", 0))
        failures += int(suite.get("failures", 0)) + int(suite.get("errors", 0))
        skipped += int(suite.get("skipped", 0) or suite.get("disabled", 0))
    return tests, failures, skipped


def failed_cases(path):
    """(test name, first line of its failure or error message) of every failed test case in the file."""
    cases = []
    for case in ET.parse(path).getroot().iter("testcase"):
        for verdict in ("failure", "error"):
            found = case.find(verdict)
            if found is not None:
                text = (found.get("message") or found.text or verdict).strip()
                name = ".".join(part for part in (case.get("classname"), case.get("name")) if part)
                cases.append((name, text.splitlines()[0][:300] if text else verdict))
                break
    return cases


def main(results_dir):
    total = failed = skipped = 0
    files = sorted(Path(results_dir).rglob("*.xml"))
    for path in files:
        try:
            tests, failures, skips = counts(path)
        except (ET.ParseError, ValueError) as error:
            print(f"unreadable result file {path}: {error}")
            tests, failures, skips = 1, 1, 0
        total, failed, skipped = total + tests, failed + failures, skipped + skips
        mark = "FAIL" if failures else "ok  "
        print(f"{mark} {path.relative_to(results_dir)}: {tests} tests, {failures} failed")
        if failures:
            try:
                for name, message in failed_cases(path):
                    print(f"       {name}: {message}")
            except ET.ParseError:
                pass
    passed = total - failed - skipped
    print(f"total: {passed} passed, {failed} failed, {skipped} skipped")
    return 0 if failed == 0 and passed > 0 else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1] if len(sys.argv) > 1 else "build/test_results"))
