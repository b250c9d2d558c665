"""A fleet through HAProxy with a server killed mid-run (issue: fleet scale): every request answered,
every answer right for the robot's own map, the killed server's robots re-routed and their maps
uploaded again. The 50-robot version is `make bench-fleet`."""
import pytest

from offload_planner_cpp.devtools.fleet import haproxy_config, run_fleet

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
