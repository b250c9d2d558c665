"""The connection guard's edges that the guard tests pass through without looking (found by `make mutate` over
connection_guard.py, #31: 96 of 288 survived): a revoked key loses its open connections and only those, the
total bound is met exactly, and the largest holders go first among those that said whose they are."""
from test_cloud_admission import guard


def connected(g, tcp, users):
    for fd, user in users.items():
        tcp.received[fd] = 0
        g.accepted(fd)
        g.connections[fd].user = user


def test_a_revoked_key_loses_its_open_connections_and_no_other_does():
    g, tcp = guard()
    connected(g, tcp, {3: b"robot1-key", 4: b"robot2-key", 5: b"robot1-key", 6: None})
    g.cut_revoked({b"robot2-key"})
    assert sorted(tcp.cut) == [3, 5]            # not 6: a connection yet to say whose it is is not revoked
    tcp.cut.clear()
    g.cut_revoked({b"robot1-key", b"robot2-key"})
    assert tcp.cut == []


def test_holders_exactly_at_the_total_are_left_alone():
    g, tcp = guard(total=2400)
    connected(g, tcp, {3: b"a", 4: b"b", 5: b"c"})
    tcp.received.update({3: 800, 4: 800, 5: 800})     # 2400 of 2400
    g.check()
    assert tcp.cut == []
    tcp.received[5] = 801
    g.check()
    assert len(tcp.cut) == 1


def test_over_the_total_the_largest_identified_holder_goes_first():
    g, tcp = guard(total=2000)
    connected(g, tcp, {3: b"a", 4: b"b", 5: b"c"})
    tcp.received.update({3: 500, 4: 900, 5: 700})     # 2100: cutting the largest (900) is enough
    g.check()
    assert tcp.cut == [4] and set(g.connections) == {3, 5}


def test_the_snapshot_counts_connections_by_state_bytes_held_and_cuts_by_bound():
    """What STATS and the metrics show of the guard: connections identified or not and those cut but not yet
    closed, the bytes held against each bound at the last check, and each cut under the bound that made it."""
    g, tcp = guard(limit=1000, total=2500, per_key=1500)
    connected(g, tcp, {3: b"a", 4: b"a", 5: b"b", 6: None})
    for fd in (3, 4, 5):
        g.delivered(fd)
    tcp.received.update({3: 700, 4: 600, 5: 300, 6: 50})    # key a holds 1300 of its 1500; 1650 of 2500 in all
    g.check()
    snapshot = g.snapshot()
    assert snapshot["connections"] == {"identified": 3, "unidentified": 1, "closing": 0}
    assert snapshot["held_bytes"] == {"all": 1650, "largest_key": 1300, "unidentified": 50}
    assert snapshot["bounds_bytes"] == {"all": 2500, "largest_key": 1500, "unidentified": 64 << 20}
    assert snapshot["cuts"] == {} and snapshot["accepted"] == 4
    tcp.received[5] = 1001                                     # over one connection's bound
    tcp.received.update({3: 900, 4: 700})                      # key a: 1600 over its 1500
    g.check()
    g.forget(6)                                                # a revoked key's message
    snapshot = g.snapshot()
    assert snapshot["cuts"] == {"message_bytes": 1, "key_bytes": 1, "revoked": 1} and g.cuts == 3
    assert snapshot["connections"] == {"identified": 1, "unidentified": 0, "closing": 3}
