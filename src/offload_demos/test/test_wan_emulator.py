"""The WAN emulator's loss, bandwidth and reset-on-outage through real loopback TCP, and
its refusal of absurd values. Timing checks are lower bounds only: a loaded machine
can only make things slower."""
import socket
import socketserver
import subprocess
import sys
import threading
import time

import pytest

from offload_demos.wan_emulator import LinkModel, WanEmulator

from cloud_test_helpers import free_port

pytestmark = pytest.mark.timeout(120)


class _Handler(socketserver.BaseRequestHandler):
    def handle(self):
        self.server.connections += 1
        while True:
            try:
                data = self.request.recv(65536)
            except OSError:
                return
            if not data:
                return
            self.server.received += len(data)
            if self.server.echo:
                self.request.sendall(data)


class Upstream(socketserver.ThreadingTCPServer):
    """Loopback TCP server that echoes (or only counts) what it receives."""
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, echo=True):
        super().__init__(("127.0.0.1", 0), _Handler)
        self.echo, self.connections, self.received = echo, 0, 0
        threading.Thread(target=self.serve_forever, daemon=True).start()

    @property
    def endpoint(self):
        return f"tcp://127.0.0.1:{self.server_address[1]}"

    def close(self):
        self.shutdown()
        self.server_close()


def _emulator(upstream, **link):
    emulator = WanEmulator("tcp://127.0.0.1:0", upstream.endpoint, LinkModel(**link))
    emulator.start()
    return emulator


def _round_trip_s(emulator, payload=b"x" * 100) -> float:
    with socket.create_connection(("127.0.0.1", emulator.listen_port), timeout=10) as sock:
        started = time.monotonic()
        sock.sendall(payload)
        got = b""
        while len(got) < len(payload):
            chunk = sock.recv(65536)
            assert chunk, "connection closed"
            got += chunk
        return time.monotonic() - started


def test_loss_delays_chunks_by_the_retransmission_time():
    upstream = Upstream()
    lossy = _emulator(upstream, loss=1.0, retransmission_s=0.3, seed=1)   # every chunk "lost" once
    try:
        round_trips = [_round_trip_s(lossy) for _ in range(3)]
    finally:
        lossy.stop()
        upstream.close()
    assert min(round_trips) >= 2 * 0.3 - 0.01, round_trips     # one retransmission each way


def test_bandwidth_caps_the_rate_per_direction():
    upstream = Upstream(echo=False)
    emulator = _emulator(upstream, bandwidth_bps=4e6)      # 0.5 MB/s
    payload = bytes(400_000)
    try:
        with socket.create_connection(("127.0.0.1", emulator.listen_port), timeout=10) as sock:
            started = time.monotonic()
            sock.sendall(payload)
            while upstream.received < len(payload) and time.monotonic() - started < 30:
                time.sleep(0.01)
            elapsed = time.monotonic() - started
    finally:
        emulator.stop()
        upstream.close()
    assert upstream.received == len(payload) and emulator.bytes_up == len(payload)
    assert elapsed >= 0.8 * len(payload) * 8 / 4e6, elapsed     # 0.8 s at 4 Mbit/s


def test_reset_on_outage_drops_connections_and_refuses_new_ones():
    upstream = Upstream()
    emulator = _emulator(upstream, outages=[(1.0, 2.0)], reset_on_outage=True)
    try:
        sock = socket.create_connection(("127.0.0.1", emulator.listen_port), timeout=10)
        sock.sendall(b"ping")
        assert sock.recv(16) == b"ping"
        with pytest.raises((ConnectionResetError, AssertionError)):
            while True:                                      # reset when the outage starts, at 1 s
                data = sock.recv(16)
                assert data, "closed"
        sock.close()
        reset_at = time.monotonic()
        before = upstream.connections
        refused = socket.create_connection(("127.0.0.1", emulator.listen_port), timeout=10)
        try:
            refused.sendall(b"ping")
            assert refused.recv(16) == b""                   # closed at once, never reaches the server
        except ConnectionResetError:
            pass
        finally:
            refused.close()
        assert upstream.connections == before
        time.sleep(max(0.0, 2.2 - (time.monotonic() - reset_at)))   # the outage ends at 3 s
        assert _round_trip_s(emulator) < 30                  # served again
    finally:
        emulator.stop()
        upstream.close()


@pytest.mark.parametrize("args, expected", [
    (["--outage=-5:3"], "outage needs"), (["--outage=nan:3"], "outage needs"), (["--outage=5:-1"], "outage needs"),
    (["--loss=2"], "--loss must be in [0, 1]"), (["--loss=nan"], "--loss must be in"),
    (["--rtt-ms=-10"], "--rtt-ms must be in [0, "), (["--bandwidth-mbps=-1"], "--bandwidth-mbps must be in [0, "),
    (["--jitter-ms=inf"], "--jitter-ms must be in"),
    (["--listen", "tcp://127.0.0.1:99999"], "0..65535"),
])
def test_absurd_values_are_refused_before_any_work(args, expected):
    run = subprocess.run([sys.executable, "-m", "offload_demos.wan_emulator", "--upstream",
                          "tcp://127.0.0.1:5555", "--listen", f"tcp://127.0.0.1:{free_port()}", *args],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and expected in run.stderr and "Traceback" not in run.stderr, run.stderr


def test_taken_port_is_a_clear_error_at_once():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        started = time.monotonic()
        run = subprocess.run([sys.executable, "-m", "offload_demos.wan_emulator", "--upstream",
                              "tcp://127.0.0.1:5555", "--listen", f"tcp://127.0.0.1:{port}"],
                             capture_output=True, text=True, timeout=60)
        elapsed = time.monotonic() - started
    assert run.returncode == 2 and f"cannot listen on tcp://127.0.0.1:{port}" in run.stderr
    assert "Traceback" not in run.stderr and elapsed < 9, elapsed   # the landed code waited 10 s


def test_trace_and_outages_run_from_the_schedule_origin():
    """A run's shared epoch: the trace and the outages are the same function of time since it, whenever the
    emulator itself started; before it the trace's first sample holds and no outage runs."""
    link = LinkModel(trace=[(0.0, 0.010), (10.0, 0.200)], outages=[(2.0, 3.0)], schedule_origin_s=5.0)
    assert link.round_trip_s(0.0) == 0.010     # before the origin
    assert link.round_trip_s(14.0) == 0.010    # 9 s into the trace
    assert link.round_trip_s(15.5) == 0.200    # 10.5 s into it
    assert link.outage_end(6.5) is None        # 1.5 s after the origin: not yet
    assert link.outage_end(7.5) == 10.0        # 2.5 s after: down until 5 + 2 + 3 on the emulator's clock
    assert link.outage_end(10.0) is None


def test_emulator_takes_its_schedule_origin_from_the_epoch():
    upstream = Upstream()
    epoch = time.monotonic() + 30.0
    emulator = WanEmulator("tcp://127.0.0.1:0", upstream.endpoint, LinkModel(rtt_s=0.0), epoch=epoch)
    try:
        emulator.start()
        # the emulator started a moment ago: the epoch lies about 30 s ahead on its clock
        assert 29.0 < emulator.link.schedule_origin_s <= 30.0
        # and before it the link still carries traffic
        assert _round_trip_s(emulator) < 5.0
    finally:
        emulator.stop()
        upstream.close()
    with pytest.raises(ValueError, match="epoch"):
        WanEmulator("tcp://127.0.0.1:0", upstream.endpoint, LinkModel(), epoch=float("nan"))
