"""The suite's own timeout ends a test whose main thread can never run Python again (issue 31: a deadlock
in the binding, the GIL lost, hung a run past its pytest timeout): the run stops with the test named."""
import subprocess
import sys
import time
from pathlib import Path

WORKSPACE = Path(__file__).resolve().parents[1]

HUNG = '''
import signal, time
def test_stuck():
    # SIGALRM never arrives, as a signal-method timeout cannot act on a thread stuck in C++.
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
    time.sleep(120)
'''


def test_a_test_stuck_beyond_signals_is_ended_by_the_suites_timeout(tmp_path):
    (tmp_path / "test_hung.py").write_text(HUNG)
    began = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-c",
                           str(WORKSPACE / "pytest.ini"), "--rootdir", str(tmp_path), "-o", "timeout=3",
                           str(tmp_path / "test_hung.py")], capture_output=True, text=True, timeout=90)
    assert time.monotonic() - began < 60
    assert done.returncode != 0 and "Timeout" in done.stdout + done.stderr and "test_stuck" in done.stdout + done.stderr
