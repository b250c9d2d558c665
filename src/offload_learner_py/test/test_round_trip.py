"""Round-trip variants (core/round_trip.py): a measured cloud plan moved to the other round trips the robot met,
in the learner node's replay and in training from bags. The behaviour they exist for (#33's held-out load pulse):
a round trip met only while the robot was loaded, where the cloud still won, comes back while the robot is idle,
where its local plans are faster."""
from typing import Optional

import numpy as np
import pytest

from offload_planner_cpp import PlanStatus
from offload_learner_py import CLOUD, LOCAL
from offload_learner_py.core.config import DQNConfig
from offload_learner_py.core.dqn import DQNAgent
from offload_learner_py.core.policies import DQNPolicy
from offload_learner_py.core.round_trip import ROUND_TRIP, RoundTripPool, at_round_trips, draw_above, table_variants
from offload_learner_py.core.state import STATE_SCHEMA, State
from offload_learner_py.data.dataset import TransitionTable
from offload_learner_py.data.records import cloud_answered, pair_records, transition_table
from offload_learner_py.online.learning import OnlineLearner
from offload_learner_py.offline.retrain import train_offline
from test_learning import outcome
from recordtools import decision as record_decision, outcome as record_outcome
from routertools import OK, STATUSES, TIMEOUT

RATE = 2e7
IDLE, LOADED = 0.9, 0.15
BIG, SMALL = 1.0, 0.01
# Where the round trip came back: idle, a big request, the loaded phase's round trip. Local 40 ms, cloud 80.
QUERY = State(BIG, IDLE, 0.07, RATE)


def requests(n=300, seed=0):
    """A robot's requests while its link was fast (15-17 ms) as long as it was idle and slow (60-80 ms) while it was
    loaded, as when a link spike meets a load pulse: big ones idle (the cloud, round trip + 10 ms, beats the local
    40 ms), big ones loaded (the cloud beats the local 200 ms), and small ones (local 2 ms, always faster). The
    robot never met the slow link while idle."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n):
        idle = k % 2 == 0
        b = rng.uniform(0.015, 0.017) if idle else rng.uniform(0.060, 0.080)
        if k % 3 == 2:
            rows.append((State(SMALL, IDLE if idle else LOADED, b, RATE), 0.002, b + 0.003))
        else:
            rows.append((State(BIG, IDLE if idle else LOADED, b, RATE), 0.040 if idle else 0.200, b + 0.010))
    return rows


def online_choice(variants: Optional[int], seed: int = 1) -> int:
    """What the learner node's DQN, trained online on `requests()` probes, chooses at QUERY (variants None: the
    DQNConfig default, which is what the node runs when its YAML sets none)."""
    config = DQNConfig(seed=seed) if variants is None else DQNConfig(seed=seed, round_trip_variants=variants)
    agent = DQNAgent(config)
    learner = OnlineLearner(DQNPolicy(config, agent=agent, explore=False), STATUSES, agent=agent)
    for state, local_s, cloud_s in requests():
        learner.learn(outcome(local=(OK, local_s), cloud=(OK, cloud_s), state=state))
    learner.policy.flush()
    return agent.greedy_action(QUERY.as_array())


def table_of(rows) -> TransitionTable:
    states = np.array([s.as_array() for s, _, _ in rows])
    n = len(rows)
    return TransitionTable(t=np.arange(n), **{f: states[:, i] for i, f in enumerate(STATE_SCHEMA.names)},
                           local_s=np.array([r[1] for r in rows]), cloud_s=np.array([r[2] for r in rows]),
                           action=np.zeros(n, dtype=np.int64), action_propensity=np.ones(n), reward=np.zeros(n))


SEEDS = (1, 2, 3, 4)


@pytest.mark.parametrize("seed", SEEDS)
def test_the_online_learner_carries_a_round_trip_to_an_idle_robot(seed):
    assert online_choice(1, seed) == LOCAL


@pytest.mark.parametrize("seed", SEEDS)
def test_the_shipped_config_carries_a_round_trip_to_an_idle_robot(seed):
    """The variants are on as the learner ships (#33: measured on every scenario with them on, 2026-11-28)."""
    assert online_choice(None, seed) == LOCAL


def test_without_variants_the_online_learner_offloads_there():
    """The failure the variants fix: the network saw the slow link only where the cloud won, and how it
    extrapolates to an idle robot is down to its initial weights (2 of these 4 seeds offload)."""
    assert sum(online_choice(0, seed) == CLOUD for seed in SEEDS) >= 2


def test_training_from_bags_carries_a_round_trip_to_an_idle_robot():
    """retrain's and the fleet learner's training: the same variants, from the table's own round trips."""
    table = table_of(requests())

    def choice(variants, seed):
        return train_offline(table, DQNConfig(seed=seed, round_trip_variants=variants)).agent.greedy_action(
            QUERY.as_array())
    assert [choice(1, seed) for seed in SEEDS] == [LOCAL] * len(SEEDS)
    assert sum(choice(0, seed) == CLOUD for seed in SEEDS) >= 2


def test_a_variant_moves_the_cloud_latency_with_the_round_trip():
    states = np.array([State(0.5, 0.3, 0.020, RATE).as_array(), State(0.5, 0.3, 0.050, RATE).as_array()])
    moved, cloud = at_round_trips(states, [0.035, 0.040], [0.080, 0.010])
    assert cloud == pytest.approx([0.080 + 0.015, 0.010])   # work 15 ms; below its round trip: work 0, not < 0
    assert moved[:, ROUND_TRIP] == pytest.approx([0.080, 0.010])
    others = [i for i in range(len(STATE_SCHEMA)) if i != ROUND_TRIP]
    assert np.array_equal(moved[:, others], states[:, others])
    assert states[0, ROUND_TRIP] == 0.020   # the input is not changed


def test_table_variants_draw_the_tables_own_round_trips_above_each_rows():
    rng = np.random.default_rng(3)
    round_trips = rng.uniform(0.01, 0.1, 30)
    states = np.array([State(0.1 + k, 0.5, b, RATE).as_array() for k, b in enumerate(round_trips)])   # d_t: the row
    local, cloud = rng.uniform(0.01, 0.2, 30), round_trips + rng.uniform(0.0, 0.05, 30)
    moved, moved_local, moved_cloud = table_variants(states, local, cloud, 3, np.random.default_rng(0))
    assert len(moved) == 87   # 3 a row but none for the row with the highest round trip
    assert set(moved[:, ROUND_TRIP]) <= set(round_trips)
    source = np.round(moved[:, 0] - 0.1).astype(int)
    assert np.bincount(source, minlength=30)[np.argsort(round_trips)].tolist() == [3] * 29 + [0]
    assert np.all(moved[:, ROUND_TRIP] > round_trips[source])
    others = [i for i in range(len(STATE_SCHEMA)) if i != ROUND_TRIP]
    assert np.array_equal(moved[:, others], states[source][:, others])
    assert np.array_equal(moved_local, local[source])
    assert moved_cloud - moved[:, ROUND_TRIP] == pytest.approx(cloud[source] - round_trips[source])
    assert len(table_variants(states, local, cloud, 0, np.random.default_rng(0))[0]) == 0


def test_draw_above_is_uniform_over_the_higher_round_trips():
    ordered = np.array([0.01, 0.02, 0.03, 0.04])
    drawn = draw_above(ordered, np.full(4000, 0.015), np.random.default_rng(0))
    values, counts = np.unique(drawn, return_counts=True)
    assert list(values) == [0.02, 0.03, 0.04] and counts.min() > 1200
    assert np.isnan(draw_above(ordered, [0.04, 0.05], np.random.default_rng(0))).all()


def test_the_pool_keeps_the_last_round_trips_only():
    pool = RoundTripPool(capacity=4, seed=0)
    assert len(pool.draw_above(0.0, 3)) == 0
    for b in range(10):
        pool.add(b / 1000)
    assert len(pool) == 4
    assert set(pool.draw_above(0.0, 200)) == {0.006, 0.007, 0.008, 0.009}
    assert set(pool.draw_above(0.0075, 200)) == {0.008, 0.009}
    assert len(pool.draw_above(0.009, 5)) == 0
    with pytest.raises(ValueError):
        RoundTripPool(capacity=0, seed=0)


def test_only_an_answered_cloud_side_gets_variants_and_they_are_not_steps():
    config = DQNConfig(seed=1, round_trip_variants=2)
    agent = DQNAgent(config)
    learner = OnlineLearner(DQNPolicy(config, agent=agent, explore=False), STATUSES, agent=agent)
    learner.round_trips.add(0.09)   # a slower link met before
    learner.learn(outcome(local=(OK, 0.04), cloud=(OK, 0.03), state=State(BIG, IDLE, 0.02, RATE)))
    # one transition stored (the other waits for its successor), one step; two variants in replay, not steps
    assert (len(agent.memory), agent.steps) == (3, 1)
    variants = slice(1, 3)
    assert list(agent.memory.actions[variants]) == [CLOUD, CLOUD]
    assert set(agent.memory.states[variants, ROUND_TRIP]) == {np.float32(0.09)}   # the one round trip above
    assert agent.memory.rewards[variants] == pytest.approx([(0.04 - 0.10) / 0.14] * 2)   # l_cloud 90 + 10 ms
    learner.learn(outcome(local=(OK, 0.04), cloud=(TIMEOUT, 5.0), state=State(BIG, IDLE, 0.02, RATE)))
    assert (len(agent.memory), agent.steps) == (5, 3)   # a timed-out cloud: its transitions, no variant
    learner.learn(outcome(local=(OK, 0.04), cloud=(OK, 0.10), state=State(BIG, IDLE, 0.09, RATE)))
    assert (len(agent.memory), agent.steps) == (7, 5)   # no round trip met above 90 ms: no variant


def test_the_config_bounds_the_variants():
    for bad in (-1, 9):
        with pytest.raises(ValueError, match="round_trip_variants"):
            DQNConfig(round_trip_variants=bad)
    # a model saved before the field reads the default; how it trains on is the node's (session.TRAINING_SCHEDULE)
    assert DQNConfig.from_dict({}).round_trip_variants == 1


def test_training_from_bags_gives_variants_only_to_the_cloud_sides_the_outcomes_say_answered(monkeypatch):
    """A robot that ran with a 2 s cloud timeout: a timed-out row holds l_cloud = 2 s, under the paper's 5 s, and a
    cloud error costs what the robot measured. Neither is a round trip plus the cloud's work, so neither is moved
    to other round trips; the outcomes' own status and timeout flag say so, not a timeout the trainer assumes."""
    log = pair_records([record_decision(k, b=0.02 * k) for k in (1, 2, 3, 4)], timed_out_and_failed())
    answered = cloud_answered(log)
    assert list(answered) == [True, False, False, True]
    table = transition_table(log)
    config = DQNConfig(seed=1, round_trip_variants=2)
    from offload_learner_py.offline import retrain as retrain_module
    added = []

    class Counted(retrain_module.ReplayMemory):   # training's replay, emptied after it: count what went in
        def add(self, *row):
            added.append(row)
            super().add(*row)
    monkeypatch.setattr(retrain_module, "ReplayMemory", Counted)
    train_offline(table, config, 1, cloud_answered=answered)
    # 4 rows x 2 actions, and two variants of row 1 at the round trip of row 4 (row 4 has none above it)
    assert len(added) == 8 + 2
    added.clear()
    train_offline(table, config, 1)
    assert len(added) == 8 + 2 * 3   # by the 5 s rule, rows 2 and 3 too
    with pytest.raises(ValueError, match="cloud_answered"):
        train_offline(table, config, 1, cloud_answered=answered[:3])


def timed_out_and_failed():
    """Four outcomes: answered, timed out at a robot's 2 s timeout (an older record: no status, its timeout flag),
    a cloud error, answered."""
    outcomes = [record_outcome(1, cloud_s=0.03), record_outcome(2, cloud_s=2.0, timeout=True),
                record_outcome(3, cloud_s=0.5), record_outcome(4, cloud_s=0.09)]
    outcomes[1].cloud_status = 0
    outcomes[2].cloud_status = int(PlanStatus.CLOUD_ERROR)
    return outcomes


def test_retrain_tells_training_which_cloud_sides_answered(tmp_path, monkeypatch):
    """offline/retrain's caller of train_offline hands it the outcomes' verdict for its training rows."""
    from offload_learner_py.data.bag_report import ReadReport
    from offload_learner_py.data.bags import BagData
    from offload_learner_py.offline import retrain as retrain_module
    outcomes = [o for _ in range(5) for o in timed_out_and_failed()]
    for k, o in enumerate(outcomes):
        o.request_id = k + 1
    log = pair_records([record_decision(k + 1, b=0.02 * (k % 4 + 1)) for k in range(20)], outcomes)
    seen = []
    original = retrain_module.train_offline
    monkeypatch.setattr(retrain_module, "train_offline",
                        lambda *a, **kw: seen.append(kw.get("cloud_answered")) or original(*a, **kw))
    retrain_module.retrain(BagData(log, ReadReport(bags=[])), str(tmp_path), DQNConfig(seed=1, round_trip_variants=1),
                           gradient_steps=1, test_fraction=0.2)
    assert list(seen[0]) == [True, False, False, True] * 4   # the 16 training rows of 20, in order
