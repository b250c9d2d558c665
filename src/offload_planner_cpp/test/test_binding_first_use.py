"""The binding's first use from many threads at once (issue 31, High 4).

Debian's pybind11 2.10 initialises the numpy API on first use in a function-local static; a thread that
releases the GIL inside that initialisation (numpy's import) while another waits for the static holding
the GIL deadlocks the interpreter. Each run is a fresh interpreter, so the first calls really are first.
"""
import subprocess
import sys
import textwrap

import pytest

FIRST_USE = textwrap.dedent(
    """
    import threading
    import numpy as np
    import offload_planner_cpp
    barrier = threading.Barrier(16)
    grid = np.zeros((64, 64), np.int8)
    results = []

    def first_plan():
        barrier.wait()
        results.append(offload_planner_cpp.plan_raw(grid, (0, 0), (63, 63))["status"])

    threads = [threading.Thread(target=first_plan) for _ in range(16)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 16 and all(s == offload_planner_cpp.PlanStatus.OK for s in results), results
    print("ok")
    """
)


@pytest.mark.parametrize("run", range(6))
def test_sixteen_threads_first_concurrent_plans_never_hang(run):
    try:
        done = subprocess.run([sys.executable, "-c", FIRST_USE], capture_output=True, text=True, timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail("sixteen threads' first concurrent plan_raw calls hung a fresh interpreter")
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr
