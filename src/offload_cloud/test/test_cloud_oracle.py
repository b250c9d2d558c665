"""Plans through the real cloud server checked against an independent oracle:
scipy's Dijkstra on the planner's move graph (offload_demos.grid_graph), and values known by construction.
Each request option must reach the planner: the lethal threshold, unknown_is_obstacle and stop_at_goal."""
import itertools
import math

import numpy as np
import pytest
from scipy.sparse.csgraph import dijkstra

from offload_cloud import protocol
from offload_cloud.client import CloudClient
from offload_cloud.protocol import PlanOptions, Status
from offload_demos.grid_graph import grid_graph, oracle_free_mask

from cloud_test_helpers import start_server

pytestmark = pytest.mark.timeout(120)


def banded_map() -> np.ndarray:
    """40 x 30 cells: walls of cost 30, 60 and 90 across the map with gaps of unknown (-1) cells, so each
    lethal threshold and unknown setting opens a different set of passages."""
    grid = np.zeros((30, 40), np.int8)
    grid[8, :] = 30
    grid[15, :] = 60
    grid[22, :] = 90
    grid[15, 35:37] = -1        # the only way past the 60 wall when it is lethal, if unknown is free
    grid[22, 3] = -1            # likewise for the 90 wall
    grid[8, 20] = 100           # always lethal
    grid[4, 5:30] = -1          # a strip of unknown across the top part
    return grid


@pytest.fixture(scope="module")
def client():
    server = start_server(None, workers=2)
    with CloudClient(server.endpoint, insecure=True, timeout_s=10.0) as client:
        yield client
    server.stop()


def _oracle(grid, start, goal, lethal_threshold, unknown_is_obstacle):
    """(status, cost in cells) from scipy: statuses checked in the planner's order."""
    free = oracle_free_mask(grid, lethal_threshold=lethal_threshold, unknown_is_obstacle=unknown_is_obstacle)
    if not free[start[1], start[0]]:
        return Status.START_BLOCKED, None
    if not free[goal[1], goal[0]]:
        return Status.GOAL_BLOCKED, None
    graph = grid_graph(grid, lethal_threshold=lethal_threshold, unknown_is_obstacle=unknown_is_obstacle)
    width = grid.shape[1]
    distance = dijkstra(graph, indices=start[1] * width + start[0])[goal[1] * width + goal[0]]
    return (Status.NO_PATH, None) if math.isinf(distance) else (Status.OK, float(distance))


@pytest.mark.parametrize("lethal_threshold, unknown_is_obstacle",
                         list(itertools.product([25, 50, 75, 101], [True, False])))
def test_cost_and_status_through_the_server_match_scipy(client, lethal_threshold, unknown_is_obstacle):
    grid = banded_map()
    options = PlanOptions(lethal_threshold=lethal_threshold, unknown_is_obstacle=unknown_is_obstacle)
    pairs = [((0, 0), (3, 3)), ((0, 0), (39, 29)), ((2, 2), (37, 12)), ((10, 0), (10, 29)), ((0, 29), (39, 0)), ((6, 2), (35, 15)),
             ((3, 28), (3, 10)), ((10, 4), (20, 20))]
    outcomes = set()
    for start, goal in pairs:
        status, cost = _oracle(grid, start, goal, lethal_threshold, unknown_is_obstacle)
        reply = client.plan(grid, start, goal, options).reply
        assert reply.status == status, (start, goal, reply.message)
        if status == Status.OK:
            assert reply.cost_cells == pytest.approx(cost, abs=1e-9), (start, goal)
            assert tuple(reply.path[0]) == start and tuple(reply.path[-1]) == goal
        outcomes.add(status)
    assert Status.OK in outcomes


def test_each_option_changes_the_answer_as_the_oracle_says(client):
    """Pairs whose answer differs between option values, so an option lost on the way fails here."""
    grid = banded_map()
    for options in (PlanOptions(lethal_threshold=50), PlanOptions(lethal_threshold=70),
                    PlanOptions(lethal_threshold=50, unknown_is_obstacle=False),
                    PlanOptions(lethal_threshold=95, unknown_is_obstacle=True)):
        status, cost = _oracle(grid, (0, 0), (39, 29), options.lethal_threshold, options.unknown_is_obstacle)
        reply = client.plan(grid, (0, 0), (39, 29), options).reply
        assert reply.status == status and (cost is None or reply.cost_cells == pytest.approx(cost, abs=1e-9))
    # By construction: threshold 50 with unknown lethal seals the 60 wall (NO_PATH); threshold 70 opens it;
    # unknown free opens the gap at x 35..36; the 90 wall is then passable only through (3, 22).
    assert client.plan(grid, (0, 0), (39, 29), PlanOptions(lethal_threshold=50)).reply.status == Status.NO_PATH
    assert client.plan(grid, (0, 0), (39, 29), PlanOptions(lethal_threshold=70)).reply.status == Status.NO_PATH
    open_reply = client.plan(grid, (0, 0), (39, 29), PlanOptions(lethal_threshold=50, unknown_is_obstacle=False)).reply
    assert open_reply.status == Status.OK
    assert any(tuple(cell) in ((35, 15), (36, 15)) for cell in open_reply.path)
    assert any(tuple(cell) == (3, 22) for cell in open_reply.path)


def test_cost_in_an_empty_map_is_the_octile_distance(client):
    """Exact values by construction: on a free map the cost is max + (sqrt 2 - 1) min of the offsets."""
    grid = np.zeros((50, 70), np.int8)
    for goal in ((69, 49), (10, 0), (0, 30), (33, 7)):
        dx, dy = goal
        reply = client.plan(grid, (0, 0), goal).reply
        assert reply.status == Status.OK
        assert reply.cost_cells == pytest.approx(max(dx, dy) + (math.sqrt(2) - 1) * min(dx, dy), abs=1e-9)
        assert len(reply.path) == max(dx, dy) + 1


def test_stop_at_goal_travels_to_the_planner(client):
    """stop_at_goal=False expands every reachable cell (the count known by construction); True stops early.
    The same request differs only in that flag."""
    grid = banded_map()
    options = PlanOptions(lethal_threshold=50, unknown_is_obstacle=True)
    free = oracle_free_mask(grid, lethal_threshold=50, unknown_is_obstacle=True)
    graph = grid_graph(grid, lethal_threshold=50, unknown_is_obstacle=True)
    reachable = int(np.isfinite(dijkstra(graph, indices=0)).sum())
    assert reachable < int(free.sum())      # the walls leave some free cells out of reach
    full = client.plan(grid, (0, 0), (2, 1), PlanOptions(lethal_threshold=50, stop_at_goal=False)).reply
    early = client.plan(grid, (0, 0), (2, 1), options).reply
    assert full.status == early.status == Status.OK and full.cost_cells == early.cost_cells
    assert full.expansions == reachable
    assert early.expansions < reachable // 4


def test_decoder_keeps_every_option_and_flag_combination():
    """The decoder itself: every flag combination and threshold comes back as sent."""
    digest = bytes(16)
    for lethal, unknown, stop in itertools.product([1, 50, 101], [True, False], [True, False]):
        options = PlanOptions(goal_tolerance_cells=1.5, lethal_threshold=lethal, unknown_is_obstacle=unknown,
                              stop_at_goal=stop)
        frames = protocol.encode_plan(3, digest, (1, 2), (3, 4), options)
        request = protocol.decode_plan(3, [bytes(f) for f in frames[1:]], 1 << 20)
        assert request.options == options
