"""Stopping a server a test or benchmark started: a polite one exits on SIGTERM and keeps its chance to clean
up; one that ignores SIGTERM is killed after the grace period instead of hanging the caller."""
import signal
import subprocess
import sys
import time

from offload_demos.loopback import stop_process

_IGNORES_TERM = ("import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); print('ready', flush=True); "
                 "time.sleep(60)")
_CLEANS_UP = ("import signal, sys, time\n"
              "def bye(*_):\n    print('cleaned up', flush=True); sys.exit(0)\n"
              "signal.signal(signal.SIGTERM, bye); print('ready', flush=True); time.sleep(60)")


def _start(code):
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    assert process.stdout.readline().strip() == "ready"
    return process


def test_a_polite_process_gets_sigterm_and_cleans_up():
    process = _start(_CLEANS_UP)
    stop_process(process, grace_s=10.0)
    assert process.returncode == 0 and process.stdout.read().strip() == "cleaned up"
    process.stdout.close()


def test_a_process_that_ignores_sigterm_is_killed_after_the_grace():
    process = _start(_IGNORES_TERM)
    began = time.monotonic()
    stop_process(process, grace_s=0.5)
    assert process.returncode == -signal.SIGKILL and time.monotonic() - began < 30
    process.stdout.close()


def test_none_and_an_exited_process_are_left_alone():
    stop_process(None)
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    stop_process(process)
    assert process.returncode == 0
