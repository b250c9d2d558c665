#!/usr/bin/env python3
"""Mutation testing, with cosmic-ray (pinned in requirements.txt), of the learner's reward, state and DQN
modules and the cloud protocol, and of every module that decides, routes, admits or evaluates: the policies,
the router, the breaker, the fleet robot's model guard, the off-policy comparison that gates models, the
server's admission and connection guard, and the fleet learner's gate. `make mutate` runs it all (about an
hour on two cores); `tools/mutate_py.py router breaker` runs some.

For each module: copy its package and the tests that cover it into build/mutate/<module>/ (the
work tree is never mutated, so Ctrl-C or a crash cannot leave a mutant behind), let cosmic-ray list
the mutants, drop the operators that only produce noise (bit operators, `is`), split the rest into
--jobs shards run side by side, each mutant followed by the module's own tests (stop at the first
failure), within a time budget per module. Then print, per module, the survival rate (survived /
mutants run) and each survivor with its diff.

A surviving mutant is a change to the code that no test noticed: either a missing test (write it) or
an equivalent mutant (the change does not alter behaviour; list it). Mutants not run within the
budget are reported as such, never counted as killed.
"""
import argparse
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Tuple

ROOT = Path(__file__).resolve().parents[1]
LEARNER = ROOT / "src" / "offload_learner_py"
PLANNER = ROOT / "src" / "offload_planner_cpp"
CLOUD = ROOT / "src" / "offload_cloud"

# Operators excluded before any run: replacing arithmetic by bit operations, `x == y` by `x is y`, and
# unary `~`/`+` almost always crash at once on floats and arrays (killed, but at the cost of a test
# run each) or are equivalent; they would double the run time and teach nothing.
EXCLUDED_OPERATORS = [
    r"core/ReplaceBinaryOperator_.*_(BitAnd|BitOr|BitXor|LShift|RShift|Mod|FloorDiv|Pow)",
    r"core/ReplaceBinaryOperator_(BitAnd|BitOr|BitXor|LShift|RShift|Mod|FloorDiv|Pow)_.*",
    r"core/ReplaceComparisonOperator_.*_(Is|IsNot)",
    r"core/ReplaceUnaryOperator_.*_(Invert|UAdd)",
]


class NotJudged(Exception):
    """A module whose mutants cannot be judged (its tests fail without any mutation)."""


@dataclass(frozen=True)
class Target:
    name: str
    package_dir: Path          # the importable package directory, copied whole
    module: str                # the file to mutate, relative to the package directory
    tests: Tuple[str, ...]     # test files run after each mutation (first failure stops the run)
    test_dir: Path
    test_support: Tuple[str, ...] = ("conftest.py",)
    budget_s: float = 120.0
    pytest_args: Tuple[str, ...] = ()


TARGETS = {
    "reward": Target("reward", LEARNER / "src" / "offload_learner_py", "core/reward.py",
                     ("test_reward.py", "test_synthetic.py"), LEARNER / "test", budget_s=90),
    "state": Target("state", LEARNER / "src" / "offload_learner_py", "core/state.py",
                    ("test_state.py", "test_state_schema.py", "test_trace.py"), LEARNER / "test", budget_s=360,
                    # test_trace imports a helper from test_dataset, test_state_schema from recordtools
                    test_support=("conftest.py", "test_dataset.py", "recordtools.py"),
                    # the end-to-end trace test needs the built planner, not this module's copy
                    pytest_args=("--deselect=test/test_trace.py::"
                                 "test_trace_command_records_the_real_planner_on_a_real_map",)),
    "dqn": Target("dqn", LEARNER / "src" / "offload_learner_py", "core/dqn.py",
                  ("test_dqn.py", "test_checkpoint.py"), LEARNER / "test", budget_s=540,
                  # one seed per state feature: the other two seeds repeat the same check at 1.5 s each
                  pytest_args=tuple(f"--deselect=test/test_dqn.py::test_greedy_action_follows_each_state_feature"
                                    f"[{feature}-{seed}]" for feature in ("cpu_availability", "input_size",
                                                                          "round_trip_s") for seed in (23, 37))),
    "protocol": Target("protocol", CLOUD / "src" / "offload_cloud", "protocol.py",
                       ("test_cloud_protocol.py",), CLOUD / "test", test_support=("conftest.py",), budget_s=180),
    # What decides, routes, admits and evaluates (#31): each with the tests that exercise it.
    "policies": Target("policies", LEARNER / "src" / "offload_learner_py", "core/policies.py",
                       ("test_policies.py", "test_policies_edges.py", "test_policies_boundaries.py"),
                       LEARNER / "test", budget_s=300),
    "router": Target("router", LEARNER / "src" / "offload_learner_py", "online/router.py",
                     ("test_router.py", "test_router_modes.py", "test_router_cancel.py", "test_router_accounting.py"),
                     LEARNER / "test",
                     test_support=("conftest.py", "routertools.py"), budget_s=420),
    "sides": Target("sides", LEARNER / "src" / "offload_learner_py", "online/sides.py",
                    ("test_side_workers.py", "test_router_cancel.py", "test_router_accounting.py", "test_router.py",
                     "test_router_modes.py"), LEARNER / "test",
                    test_support=("conftest.py", "routertools.py"), budget_s=420),
    "breaker": Target("breaker", LEARNER / "src" / "offload_learner_py", "online/breaker.py",
                      ("test_breaker.py", "test_breaker_edges.py", "test_router_modes.py"), LEARNER / "test",
                      test_support=("conftest.py", "routertools.py"), budget_s=240),
    "model_guard": Target("model_guard", LEARNER / "src" / "offload_learner_py", "online/model_guard.py",
                          ("test_fleet_robot.py", "test_fleet_robot_guard.py", "test_model_guard_welch.py",
                           "test_model_guard_window.py", "test_model_guard_drift.py"), LEARNER / "test",
                          test_support=("conftest.py", "routertools.py", "fleettools.py"),
                          budget_s=240),
    "off_policy_combined": Target("off_policy_combined", LEARNER / "src" / "offload_learner_py",
                                  "offline/off_policy_combined.py",
                                  ("test_off_policy_gate.py", "test_off_policy.py", "test_off_policy_strata.py",
                                   "test_off_policy_boundaries.py"),
                                  LEARNER / "test", test_support=("conftest.py", "bagtools.py", "ope_rows.py", "data"),
                                  budget_s=420),
    "admission": Target("admission", CLOUD / "src" / "offload_cloud", "admission.py",
                        ("test_cloud_admission.py", "test_cloud_admission_edges.py"), CLOUD / "test",
                        test_support=("conftest.py", "cloud_test_helpers.py"), budget_s=300),
    "connection_guard": Target("connection_guard", CLOUD / "src" / "offload_cloud", "connection_guard.py",
                               ("test_cloud_admission.py", "test_cloud_connections.py", "test_cloud_guard_edges.py"),
                               CLOUD / "test",
                               test_support=("conftest.py", "cloud_test_helpers.py"), budget_s=300),
    "fleet_gate": Target("fleet_gate", CLOUD / "src" / "offload_cloud", "learner/training.py",
                         ("test_fleet_learner.py", "test_fleet_training.py", "test_fleet_training_gate.py"), CLOUD / "test",
                         test_support=("conftest.py", "fleet_helpers.py"), budget_s=420),
}


def _compiled_core() -> List[Path]:
    """The planner's pybind11 module from the devel space (the package imports it at start)."""
    devel = ROOT / "devel" / "lib"
    return sorted(devel.glob("python3*/dist-packages/offload_planner_cpp/_core*.so"))


# A pytest plugin written into each copy: the baseline run records every test's duration, and each
# mutant's run then goes fastest first, so `-x` stops a killed mutant after the quick tests and only
# the survivors pay for the slow learning tests.
ORDER_PLUGIN = """
import json
import os

DURATIONS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "durations.json")


def pytest_collection_modifyitems(config, items):
    if os.path.exists(DURATIONS):
        with open(DURATIONS) as source:
            durations = json.load(source)
        items.sort(key=lambda item: durations.get(item.nodeid, 0.0))


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    if os.environ.get("MUTATE_RECORD_DURATIONS"):
        durations = {}
        for reports in terminalreporter.stats.values():
            for report in reports:
                if getattr(report, "nodeid", None) and hasattr(report, "duration"):
                    durations[report.nodeid] = durations.get(report.nodeid, 0.0) + report.duration
        with open(DURATIONS, "w") as out:
            json.dump(durations, out)
"""


def target_tests(target: Target) -> List[str]:
    return [f"test/{name}" for name in target.tests] + list(target.pytest_args)


def copy_local_imports(test_dir: Path, copy_dir: Path) -> None:
    """Copies the helper modules of test_dir that the copied tests import, and theirs, so a test that gains a
    helper import cannot leave a target unjudged (its tests failing on the unmutated copy)."""
    pending = list(copy_dir.glob("*.py"))
    while pending:
        text = pending.pop().read_text()
        for name in re.findall(r"^\s*(?:from|import)\s+(\w+)", text, re.MULTILINE):
            source, copy = test_dir / f"{name}.py", copy_dir / f"{name}.py"
            if source.is_file() and not copy.exists():
                shutil.copy2(source, copy)
                pending.append(copy)


def prepare_shard(target: Target, shard_dir: Path) -> None:
    if shard_dir.exists():
        shutil.rmtree(shard_dir)
    package_copy = shard_dir / "src" / target.package_dir.name
    shutil.copytree(target.package_dir, package_copy, ignore=shutil.ignore_patterns("__pycache__"))
    if target.package_dir.name == "offload_planner_cpp":
        cores = _compiled_core()
        if not cores:
            sys.exit("mutate: the planner's compiled module is missing: run `make build` first")
        shutil.copy2(cores[0], package_copy)
    (shard_dir / "test").mkdir()
    for name in target.tests + target.test_support:   # a support entry may be a directory (test data)
        source = target.test_dir / name
        if source.is_dir():
            shutil.copytree(source, shard_dir / "test" / name)
        else:
            shutil.copy2(source, shard_dir / "test" / name)
    copy_local_imports(target.test_dir, shard_dir / "test")
    # Its own pytest.ini, so the workspace's (found by walking up) is not used.
    (shard_dir / "pytest.ini").write_text("[pytest]\naddopts = -p no:cacheprovider -p mutate_order\n")
    (shard_dir / "mutate_order.py").write_text(ORDER_PLUGIN)
    tests = " ".join(target_tests(target))
    excluded = ",\n".join(f'  "{pattern}"' for pattern in EXCLUDED_OPERATORS).replace("\\", "\\\\")
    (shard_dir / "cosmic-ray.toml").write_text(
        "[cosmic-ray]\n"
        f'module-path = "src/{target.package_dir.name}/{target.module}"\n'
        "timeout = 120.0\n"
        "excluded-modules = []\n"
        f'test-command = "{sys.executable} -m pytest -x -q {tests}"\n\n'
        "[cosmic-ray.distributor]\n"
        'name = "local"\n\n'
        "[cosmic-ray.filters.operators-filter]\n"
        f"exclude-operators = [\n{excluded}\n]\n")


def _path(shard: Path) -> str:
    """The shard's mutated copy first, then the devel space for the packages it imports (the planner's
    compiled module under offload_cloud)."""
    return os.pathsep.join([str(shard / "src")] + [str(p) for p in sorted((ROOT / "devel" / "lib").glob("python3*/dist-packages"))])


def _run(command: List[str], cwd: Path, env: Dict[str, str]) -> None:
    result = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"mutate: {' '.join(command)} failed in {cwd}:\n{result.stdout}{result.stderr}")


def _tool(name: str) -> str:
    return str(Path(sys.executable).parent / name)


def run_target(target: Target, work_dir: Path, jobs: int, budget_s: float) -> dict:
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    shards = [work_dir / target.name / f"shard{i}" for i in range(jobs)]
    for shard in shards:
        prepare_shard(target, shard)
    env = dict(os.environ, PYTHONPATH=_path(shards[0]), PYTHONDONTWRITEBYTECODE="1")
    first = shards[0]
    # Baseline: the tests must pass on the unmutated copy, or every mutant would count as killed.
    baseline = subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", *target_tests(target)], cwd=first,
                              env=dict(env, MUTATE_RECORD_DURATIONS="1"), capture_output=True, text=True)
    if baseline.returncode != 0:
        raise NotJudged(f"the tests fail on the unmutated copy in {first}, so no mutant can be judged:\n"
                        f"{baseline.stdout[-3000:]}{baseline.stderr[-2000:]}")
    for shard in shards[1:]:
        shutil.copy2(first / "durations.json", shard / "durations.json")
    _run([_tool("cosmic-ray"), "init", "cosmic-ray.toml", "session.sqlite"], first, env)
    _run([_tool("cr-filter-operators"), "session.sqlite", "cosmic-ray.toml"], first, env)
    for shard in shards[1:]:
        shutil.copy2(first / "session.sqlite", shard / "session.sqlite")
    # Shard i runs every jobs-th pending mutant, the others are marked skipped in its session.
    for i, shard in enumerate(shards):
        with use_db(str(shard / "session.sqlite"), WorkDB.Mode.open) as db:
            pending = sorted(item.job_id for item in db.pending_work_items)
            for index, job_id in enumerate(pending):
                if index % jobs != i:
                    db.set_result(job_id, WorkResult(worker_outcome=WorkerOutcome.SKIPPED, output="other shard"))
    processes = []
    for shard in shards:
        shard_env = dict(env, PYTHONPATH=_path(shard))
        processes.append(subprocess.Popen([_tool("cosmic-ray"), "exec", "cosmic-ray.toml", "session.sqlite"],
                                          cwd=shard, env=shard_env, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL, start_new_session=True))
    deadline = time.monotonic() + budget_s
    out_of_time = False
    try:
        for process in processes:
            remaining = deadline - time.monotonic()
            try:
                process.wait(timeout=max(remaining, 0.1))
            except subprocess.TimeoutExpired:
                out_of_time = True
                break
    finally:
        for process in processes:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
                try:
                    process.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    os.killpg(process.pid, signal.SIGKILL)
                    process.wait()
    return collect(target, shards, out_of_time)


def collect(target: Target, shards: List[Path], out_of_time: bool) -> dict:
    from cosmic_ray.work_db import WorkDB, use_db
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    killed, survived, total, filtered = 0, [], 0, 0
    results = {}
    for shard in shards:
        with use_db(str(shard / "session.sqlite"), WorkDB.Mode.open) as db:
            total = db.num_work_items
            for item, result in db.completed_work_items:
                if result.worker_outcome == WorkerOutcome.SKIPPED:
                    if result.output != "other shard":
                        filtered = filtered + 1 if shard == shards[0] else filtered
                    continue
                results[item.job_id] = (item, result)
    for item, result in results.values():
        if result.worker_outcome == WorkerOutcome.NORMAL and result.test_outcome == TestOutcome.SURVIVED:
            survived.append((item, result))
        else:
            killed += 1  # killed by a failing test, or incompetent (the mutant cannot even run)
    run = killed + len(survived)
    return {"target": target, "total": total, "filtered": filtered, "run": run, "killed": killed,
            "survived": survived, "not_run": total - filtered - run, "out_of_time": out_of_time}


def report(summary: dict) -> None:
    target = summary["target"]
    run, survived = summary["run"], summary["survived"]
    rate = f"{100.0 * len(survived) / run:.1f} %" if run else "n/a"
    print(f"{target.name:9s} {target.module}: survival {rate} ({len(survived)} of {run} mutants run survived; "
          f"{summary['filtered']} excluded by operator, {summary['not_run']} not run"
          f"{' (time budget reached)' if summary['out_of_time'] else ''}; tests: {', '.join(target.tests)})")
    for item, result in sorted(survived, key=lambda pair: pair[0].mutations[0].start_pos):
        mutation = item.mutations[0]
        changed = [line for line in (result.diff or "").splitlines()
                   if line[:1] in "+-" and not line.startswith(("+++", "---"))]
        print(f"    survived  {target.module}:{mutation.start_pos[0]}  {mutation.operator_name}  "
              f"{' | '.join(line.strip() for line in changed)}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("modules", nargs="*", help=f"modules to mutate, of {', '.join(TARGETS)} (default: all)")
    parser.add_argument("--jobs", type=int, default=2, help="shards run side by side (default 2, one per core)")
    parser.add_argument("--budget-scale", type=float, default=1.0,
                        help="multiply every module's time budget (default budgets total 15 min)")
    parser.add_argument("--work", type=Path, default=ROOT / "build" / "mutate", help="scratch directory")
    args = parser.parse_args(argv)
    if args.jobs < 1 or args.budget_scale <= 0:
        parser.error("--jobs must be >= 1 and --budget-scale > 0")
    modules = args.modules or list(TARGETS)
    unknown = sorted(set(modules) - set(TARGETS))
    if unknown:
        parser.error(f"unknown modules {unknown}; choose from {', '.join(TARGETS)}")
    print(f"mutation testing with cosmic-ray, {args.jobs} shard(s); survival = survived / mutants run "
          f"(lower is better; read each survivor)", flush=True)
    summaries, failed = [], []
    for name in modules:
        target = TARGETS[name]
        began = time.monotonic()
        try:
            summary = run_target(target, args.work, args.jobs, target.budget_s * args.budget_scale)
        except NotJudged as error:
            print(f"{name:9s} {target.module}: NOT JUDGED: {error}", flush=True)
            failed.append(name)
            continue
        summaries.append(summary)
        report(summary)
        print(f"    ({time.monotonic() - began:.0f} s)", flush=True)
    print("summary: " + ", ".join(
        f"{s['target'].name} {100.0 * len(s['survived']) / s['run']:.1f} % ({len(s['survived'])}/{s['run']})"
        if s["run"] else f"{s['target'].name} n/a" for s in summaries)
        + "".join(f", {name} NOT JUDGED" for name in failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
