#!/usr/bin/env python3
"""Hand-written mutation testing of the C++ planner core and its request contract (dijkstra.cpp,
planner_options.cpp, plan_request.cpp, map_geometry.h, the ROS wrapper planner_ros.cpp and the pybind11
bindings), and of the robot's recorder (offload_learner_py's bag_recorder.cpp, judged by its rostest
bag_recorder.test). `make mutate` runs it after the Python modules.

For each mutant of tools/cpp_mutants.yaml, one at a time: write the mutated source (its `file`, relative
to src/<its `package`>/, default offload_planner_cpp and src/dijkstra.cpp), rebuild the gtests, the recorder and the pybind11 module
(catkin_make targets test_dijkstra, test_dijkstra_waves, test_planner_modes, test_jump_point_search, test_planner_ros,
test_planner_options, test_planner_pool, test_q_network, test_serve_queue and _core), run the gtests and
the binding and contract tests (test_bindings.py, test_request_contract.py, test_q_network.py), and record whether a test
failed (killed), the build failed (does not compile) or everything passed (survived). The original source
is written back after every mutant, and on any exit (failure, Ctrl-C, SIGTERM); the devel space is then
rebuilt from it.

Needs the ROS environment (`source devel/setup.bash`) and a built workspace (`make build`).
"""
import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "offload_planner_cpp"
DEFAULT_PACKAGE, DEFAULT_FILE = "offload_planner_cpp", "src/dijkstra.cpp"
# The recorder is a node: its rostest starts it and judges the bag and its threads.
ROSTESTS = {"offload_learner_py": ["bag_recorder.test"]}
MUTANTS = Path(__file__).resolve().parent / "cpp_mutants.yaml"
GTESTS = [ROOT / "devel" / "lib" / "offload_planner_cpp" / name
          for name in ("test_dijkstra", "test_dijkstra_waves", "test_planner_modes", "test_jump_point_search",
                       "test_planner_ros", "test_planner_options", "test_planner_pool", "test_q_network",
                       "test_serve_queue")]
BINDING_TESTS = [PACKAGE / "test" / name for name in ("test_bindings.py", "test_request_contract.py",
                                                        "test_q_network.py")]
TEST_TIMEOUT_S = 300  # a mutant that loops forever is killed by this, not waited for


class Stop(Exception):
    """SIGTERM, turned into an exception so the source is restored on the way out."""


def load_mutants(path: Path) -> list:
    try:
        with open(path) as stream:
            entries = yaml.safe_load(stream)
    except (OSError, yaml.YAMLError) as error:
        sys.exit(f"{path}: cannot read the mutant list: {error}")
    if not isinstance(entries, list):
        sys.exit(f"{path}: expected a list of mutants")
    mutants = []
    for number, entry in enumerate(entries, start=1):
        if not isinstance(entry, dict):
            sys.exit(f"{path}: mutant {number} is not a mapping with name, find and replace")
        missing = {"name", "find", "replace"} - set(entry)
        if missing:
            sys.exit(f"{path}: mutant {number} lacks {sorted(missing)}")
        mutants.append(entry)
    names = [m["name"] for m in mutants]
    if len(set(names)) != len(names):
        sys.exit(f"{path}: mutant names must be unique")
    return mutants


def apply(source: str, mutant: dict) -> str:
    """The source with the mutant applied; ValueError when its text is absent or ambiguous."""
    find, count = mutant["find"], source.count(mutant["find"])
    occurrence = int(mutant.get("occurrence", 0))
    if count == 0:
        raise ValueError("its `find` text is not in the source (stale: update the list)")
    if count > 1 and not occurrence:
        raise ValueError(f"its `find` text occurs {count} times: say which with `occurrence`")
    occurrence = occurrence or 1
    if occurrence > count:
        raise ValueError(f"occurrence {occurrence} asked, the text occurs {count} times")
    start = -1
    for _ in range(occurrence):
        start = source.index(find, start + 1)
    return source[:start] + mutant["replace"] + source[start + len(find):]


def build() -> subprocess.CompletedProcess:
    return subprocess.run(["catkin_make", "--source", str(ROOT), "-j2", *(path.name for path in GTESTS), "_core",
                           "offload_bag_recorder"], cwd=ROOT, capture_output=True, text=True)


def source_key(mutant: dict) -> str:
    """The mutated file, relative to src/: its package's directory, then its path in the package."""
    return f"{mutant.get('package', DEFAULT_PACKAGE)}/{mutant.get('file', DEFAULT_FILE)}"


def run_tests(package: str = DEFAULT_PACKAGE) -> tuple:
    """(killed, which test failed): the planner's gtests and binding tests, or the package's rostests."""
    if package != DEFAULT_PACKAGE:
        for launch in ROSTESTS.get(package, []):
            try:
                rostest = subprocess.run(["rostest", "--text", package, launch], cwd=ROOT, capture_output=True,
                                         text=True, timeout=TEST_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                return True, f"{launch} (timed out)"
            output = rostest.stdout + rostest.stderr
            failed = [line.split()[1] for line in output.splitlines() if line.startswith(("FAIL:", "ERROR:"))]
            if rostest.returncode != 0 or "RESULT: FAIL" in output:   # rostest --text exits 0 on a failed test
                return True, f"{launch} " + (failed[0] if failed else f"(exit {rostest.returncode})")
        return False, ""
    for gtest_path in GTESTS:
        try:
            gtest = subprocess.run([str(gtest_path), "--gtest_brief=1"], capture_output=True, text=True,
                                   timeout=TEST_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            return True, f"{gtest_path.name} (timed out)"
        if gtest.returncode != 0:
            failed = [line.split("]", 1)[1].split()[0] for line in gtest.stdout.splitlines()
                      if line.startswith("[  FAILED  ]") and len(line.split("]", 1)[1].split()) > 0]
            return True, f"{gtest_path.name} " + (failed[0] if failed else f"(exit {gtest.returncode})")
    try:
        binding = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider"]
                                 + [str(path) for path in BINDING_TESTS], cwd=ROOT, capture_output=True, text=True,
                                 timeout=TEST_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return True, "binding tests (timed out)"
    if binding.returncode != 0:
        failed = [line.split()[1] for line in binding.stdout.splitlines() if line.startswith("FAILED")]
        return True, failed[0] if failed else f"binding tests (exit {binding.returncode})"
    return False, ""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("names", nargs="*", help="run only these mutants (default: all)")
    parser.add_argument("--list", type=Path, default=MUTANTS, help="mutant list (default tools/cpp_mutants.yaml)")
    args = parser.parse_args(argv)
    mutants = load_mutants(args.list)
    sources = {key: ROOT / "src" / key for key in {source_key(m) for m in mutants}}
    missing = [name for name, path in sources.items() if not path.is_file()]
    if missing:
        sys.exit(f"{args.list}: no such source file {missing} (file is relative to src/<package>/)")
    originals = {name: path.read_bytes() for name, path in sources.items()}

    def restore():
        for name, path in sources.items():
            path.write_bytes(originals[name])

    if args.names:
        unknown = set(args.names) - {m["name"] for m in mutants}
        if unknown:
            parser.error(f"unknown mutants {sorted(unknown)}")
        mutants = [m for m in mutants if m["name"] in args.names]

    def on_sigterm(signum, frame):
        raise Stop()

    previous = signal.signal(signal.SIGTERM, on_sigterm)
    results = []
    try:
        baseline = build()
        if baseline.returncode != 0:
            sys.exit(f"mutate_cpp: the unmutated workspace does not build:\n{baseline.stdout[-3000:]}")
        for package in sorted({m.get("package", DEFAULT_PACKAGE) for m in mutants}):
            killed, where = run_tests(package)
            if killed:
                sys.exit(f"mutate_cpp: the tests fail on the unmutated source ({where}); no mutant can be judged")
        print(f"C++ mutants of {', '.join(sorted(sources))} ({len(mutants)} from {args.list.name}); tests: "
              f"{', '.join(path.name for path in GTESTS)} (gtest), "
              f"{', '.join(path.name for path in BINDING_TESTS)}", flush=True)
        for mutant in mutants:
            began = time.monotonic()
            source = sources[source_key(mutant)]
            try:
                mutated = apply(originals[source_key(mutant)].decode(), mutant)
            except ValueError as error:
                results.append((mutant, "stale", str(error)))
                print(f"  stale     {mutant['name']}: {error}", flush=True)
                continue
            try:
                source.write_text(mutated)
                if build().returncode != 0:
                    outcome, detail = "no-build", "does not compile"
                else:
                    killed, detail = run_tests(mutant.get("package", DEFAULT_PACKAGE))
                    outcome = "killed" if killed else "SURVIVED"
            finally:
                restore()
            results.append((mutant, outcome, detail))
            print(f"  {outcome:9s} {mutant['name']}: {detail or mutant.get('why', '')} "
                  f"({time.monotonic() - began:.0f} s)", flush=True)
    except (KeyboardInterrupt, Stop):
        print("interrupted: restoring the source", file=sys.stderr)
        return_code = 130
    else:
        return_code = 0
    finally:
        restore()
        signal.signal(signal.SIGTERM, previous)
        rebuilt = build()
        if rebuilt.returncode != 0:
            print("mutate_cpp: the restored source did not rebuild; run `make build`", file=sys.stderr)
    judged = [r for r in results if r[1] in ("killed", "SURVIVED")]
    survived = [r for r in results if r[1] == "SURVIVED"]
    if judged:
        print(f"C++ core: survival {100.0 * len(survived) / len(judged):.1f} % ({len(survived)} of {len(judged)} "
              f"mutants that build survived; {sum(r[1] == 'no-build' for r in results)} do not compile, "
              f"{sum(r[1] == 'stale' for r in results)} stale)")
    for mutant, _, _ in survived:
        print(f"    survived  {mutant['name']}: {mutant.get('why', '')}")
    return return_code


if __name__ == "__main__":
    sys.exit(main())
