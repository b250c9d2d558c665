"""A fleet through HAProxy with a server killed mid-run: every request answered,
every answer right for the robot's own map, the killed server's robots re-routed and their maps
uploaded again. The 50-robot version is `make bench-fleet`."""
import pytest

from offload_demos.fleet import haproxy_config, run_fleet

pytestmark = pytest.mark.timeout(300)


def test_server_killed_behind_haproxy_loses_no_request():
    result = run_fleet(robots=12, servers=2, requests=30, kill_at_s=0.5, map_size=96, think_s=0.03)
    assert result.requests == 12 * 30
    assert result.lost == 0 and result.wrong == 0 and result.errors == 0
    assert result.answered == result.requests and result.planned == result.answered
    # The robots on the killed server met a cold cache on the other one and uploaded again.
    assert result.uploads > 12
    # STATS of the surviving server: it served every robot (the killed one's re-routed), by key name.
    assert len(result.server_stats) == 1
    _, stats = result.server_stats[0]
    assert set(stats["clients"]) == {f"robot{k:02d}" for k in range(12)}
    assert stats["requests"] == sum(client["requests"] for client in stats["clients"].values()) > 0
    assert stats["cache"]["uploads"] >= 12 and stats["queue"]["depth"] == 0
    assert any(line.startswith("server 127.0.0.1:") for line in result.lines())


def test_haproxy_config_balances_every_server_with_health_checks():
    config = haproxy_config(6000, [7001, 7002, 7003])
    assert "mode tcp" in config and "bind 127.0.0.1:6000" in config
    for k, port in enumerate((7001, 7002, 7003)):
        assert f"server cloud{k} 127.0.0.1:{port} check" in config
    assert "on-marked-down shutdown-sessions" in config and "option redispatch" in config


def test_haproxy_recipe_holds_against_an_idle_flood_and_a_frozen_server(tmp_path):
    """Hundreds of idle connections that never greet (no key needed) from one address: the per-source
    limit turns most away at once and the greeting timeout closes the rest, while a fresh robot on another
    address is served. A SIGSTOPped server (its kernel still accepts TCP) fails the ZMTP health check and
    gets no robot."""
    import signal
    import socket
    import time

    from cloud_test_helpers import make_keys
    from offload_cloud.client import CloudClient
    from offload_demos.fleet import Cloud

    server_keys = make_keys(tmp_path / "keys", ["robot"])
    cloud = Cloud(2, 1, server_keys, True, tmp_path)
    port = int(cloud.endpoint.rsplit(":", 1)[1])
    flood = []
    try:
        for _ in range(300):
            sock = socket.socket()
            sock.bind(("127.0.0.2", 0))
            sock.settimeout(2.0)
            try:
                sock.connect(("127.0.0.1", port))
                flood.append(sock)
            except OSError:
                sock.close()
        client = CloudClient(cloud.endpoint, keys_dir=str(tmp_path / "keys" / "robot"), timeout_s=5.0, retries=0)
        try:
            assert client.ping() > 0                       # a fresh robot is served during the flood
        finally:
            client.close()
        deadline = time.monotonic() + 20
        open_sockets = list(flood)
        while open_sockets and time.monotonic() < deadline:   # all closed: rejected at once or after 10 s
            still = []
            for sock in open_sockets:
                try:
                    sock.settimeout(0.05)
                    if sock.recv(1) == b"":
                        continue
                except socket.timeout:
                    still.append(sock)
                except OSError:
                    continue
            open_sockets = still
        assert not open_sockets, f"{len(open_sockets)} idle connections still held after the greeting timeout"

        cloud.processes[0].send_signal(signal.SIGSTOP)
        try:
            time.sleep(2.0)                                 # inter 250 ms, fall 2: marked down by now
            for _ in range(10):                             # leastconn would send half of them to the frozen one
                client = CloudClient(cloud.endpoint, keys_dir=str(tmp_path / "keys" / "robot"), timeout_s=3.0,
                                     retries=0)
                try:
                    assert client.ping() > 0
                finally:
                    client.close()
        finally:
            cloud.processes[0].send_signal(signal.SIGCONT)
    finally:
        for sock in flood:
            sock.close()
        cloud.close()
