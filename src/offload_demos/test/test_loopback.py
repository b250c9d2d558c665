"""Loopback ports that stay free until a server binds them, and stopping a server a test or benchmark started: a
polite one exits on SIGTERM and keeps its chance to clean up; one that ignores SIGTERM is killed after the grace
period instead of hanging the caller."""
import signal
import socket
import subprocess
import sys
import time

from offload_demos.loopback import LOOPBACK, ephemeral_ports, free_port, stop_process

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


def test_a_free_port_is_below_the_range_outgoing_connections_draw_from():
    """A port from bind(0) lies in the ephemeral range, where a launch's own connections could take it before the
    server binds it (a cloud server died with "Address already in use" in a bench run)."""
    low, high = ephemeral_ports()
    ports = {free_port() for _ in range(50)}
    assert all(port < low for port in ports), sorted(ports)
    assert len(ports) > 1, "the same port every time: not drawn"
    for port in list(ports)[:5]:
        with socket.socket() as server:
            server.bind((LOOPBACK, port))     # free: a server can take it


def test_the_ephemeral_range_is_read_and_a_missing_file_falls_back(tmp_path):
    path = tmp_path / "range"
    path.write_text("40000\t50000\n")
    assert ephemeral_ports(str(path)) == (40000, 50000)
    assert ephemeral_ports(str(tmp_path / "missing")) == (32768, 60999)
