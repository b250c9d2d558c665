"""The planner's options everywhere: each keyword of the pybind11 module changes what the core does, the
cloud protocol carries every option and the server plans with it, cost-aware planning is exact against
scipy on the same weighted graph (inflated Husky playpen), and any-angle paths are shorter than the
8-connected optimum without crossing an obstacle."""
import dataclasses

import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse import csgraph

import offload_planner_cpp
from offload_planner_cpp import PlanStatus, inflate, path_clear, plan, plan_raw
from offload_cloud import protocol
from offload_cloud.client import CloudClient, reply_problem
from offload_cloud.protocol import PlanOptions, Status
from offload_demos.grid_graph import grid_graph
from offload_planner_cpp.maps import load_map

from cloud_test_helpers import start_server


def corridor_grid():
    """60 x 40 cells: a wall with a gap, and a band of occupancy 40 along the straight line."""
    grid = np.zeros((40, 60), np.int8)
    grid[5:35, 30] = 100
    grid[18:22, :] = np.maximum(grid[18:22, :], 40)
    grid[18:22, 30] = 100
    return grid


START, GOAL = (2, 20), (57, 20)


def test_every_keyword_reaches_the_core():
    grid = corridor_grid()
    base = plan(grid, START, GOAL)
    astar = plan(grid, START, GOAL, algorithm="astar")
    assert astar.cost == pytest.approx(base.cost) and astar.expansions < base.expansions
    pulled = plan(grid, START, GOAL, any_angle=True)
    assert pulled.cost < base.cost - 1 and len(pulled.path) < len(base.path)
    aware = plan(grid, START, GOAL, cost_factor=3.0)
    assert aware.weighted_cost > aware.cost and not np.array_equal(aware.path, base.path)
    rescaled = plan(grid, START, GOAL, cost_factor=3.0, neutral_cost=100.0)
    assert rescaled.weighted_cost != pytest.approx(aware.weighted_cost)
    # A start beside the wall is inside the robot's radius once the map is inflated.
    near_wall = (29, 10)
    assert plan_raw(grid, near_wall, GOAL, robot_radius_cells=1.5)["status"] == PlanStatus.START_BLOCKED
    assert plan_raw(grid, near_wall, GOAL)["status"] == PlanStatus.OK
    graded = inflate(grid, 1.0, 6.0)
    steeper = inflate(grid, 1.0, 6.0, inflation_decay=2.0)
    assert (graded >= steeper).all() and (graded > steeper).any()
    inflated = plan(grid, START, GOAL, inflation_radius_cells=6.0, cost_factor=3.0)
    assert inflated.weighted_cost > aware.weighted_cost    # the same path costs more on the inflated grid
    with pytest.raises(ValueError, match="algorithm"):
        plan_raw(grid, START, GOAL, algorithm="bfs")
    assert plan_raw(grid, START, GOAL, cost_factor=-1.0)["status"] == PlanStatus.INVALID_REQUEST
    assert plan_raw(grid, START, GOAL, robot_radius_cells=float("nan"))["status"] == PlanStatus.INVALID_REQUEST


def clearance(free: np.ndarray, path: np.ndarray) -> float:
    """Smallest distance (cells, centre to centre) from the path's cells to a blocked cell."""
    distance = ndimage.distance_transform_edt(free)
    return float(distance[path[:, 1], path[:, 0]].min())


def test_cost_aware_on_the_inflated_husky_playpen_is_exact_and_keeps_its_distance(bundled_maps):
    m = load_map(bundled_maps / "husky_playpen" / "playpen_map.yaml")
    grid = m.grid
    free = offload_planner_cpp.free_cells(grid, 50, True)   # the known free space
    labels, _ = ndimage.label(free, structure=np.ones((3, 3)))
    biggest = np.argmax(np.bincount(labels.ravel())[1:]) + 1
    # Starts and goals in the open (8 cells from any obstacle), so a path's clearance is its own doing.
    open_space = (labels == biggest) & (ndimage.distance_transform_edt(free) >= 8)
    cells = np.argwhere(open_space)[:, ::-1]
    rng = np.random.default_rng(4)
    inflation = dict(robot_radius_cells=2.0, inflation_radius_cells=12.0)
    inflated = inflate(grid, 2.0, 12.0)
    inflated_free = offload_planner_cpp.free_cells(inflated, 50, True)
    graph = grid_graph(inflated, cost_factor=3.0, neutral_cost=50.0)
    # Beyond the inflation radius nothing costs more, so clearance counts up to that radius.
    reach = 12.0
    pairs = []
    for _ in range(200):
        s, g = (tuple(int(v) for v in cells[k]) for k in rng.choice(len(cells), 2, replace=False))
        if not (inflated_free[s[1], s[0]] and inflated_free[g[1], g[0]]) or np.hypot(*np.subtract(s, g)) < 60:
            continue
        uniform = plan(grid, s, g)
        aware = plan(grid, s, g, cost_factor=3.0, **inflation)
        width = grid.shape[1]
        expected = csgraph.dijkstra(graph, indices=s[1] * width + s[0])[g[1] * width + g[0]]
        assert aware.weighted_cost == pytest.approx(expected, rel=1e-9)
        pairs.append((min(clearance(free, uniform.path), reach), min(clearance(free, aware.path), reach)))
        if len(pairs) == 8:
            break
    print("clearance (uniform, cost-aware), cells:", [(round(u, 2), round(a, 2)) for u, a in pairs])
    assert len(pairs) == 8
    assert all(a >= u for u, a in pairs), "a cost-aware path never comes closer to an obstacle"
    close = [(u, a) for u, a in pairs if u < reach]
    assert len(close) >= 3 and all(a > u for u, a in close), "where the uniform path hugs a wall, the cost-aware one keeps away"


def random_grid(rng, size=160, blocked=0.2):
    grid = np.where(rng.random((size, size)) < blocked, 100, 0).astype(np.int8)
    return grid


def test_any_angle_paths_are_clear_and_at_least_4_percent_shorter_on_random_maps():
    rng = np.random.default_rng(9)
    octile, pulled = [], []
    for _ in range(12):
        grid = random_grid(rng)
        free = np.argwhere(grid == 0)[:, ::-1]
        for _ in range(6):
            s, g = (tuple(int(v) for v in free[k]) for k in rng.choice(len(free), 2, replace=False))
            if np.hypot(*np.subtract(s, g)) < 60:
                continue
            raw = plan_raw(grid, s, g)
            if raw["status"] != PlanStatus.OK:
                continue
            tight = plan(grid, s, g, any_angle=True)
            assert path_clear(grid, tight.path) == -1
            assert tight.cost == pytest.approx(np.hypot(*np.diff(tight.path, axis=0).T).sum())
            octile.append(raw["cost"])
            pulled.append(tight.cost)
    assert len(octile) > 40
    saving = 1.0 - np.mean(pulled) / np.mean(octile)
    print(f"any-angle: mean length {np.mean(pulled):.1f} against {np.mean(octile):.1f} cells, {100 * saving:.2f} % shorter")
    assert saving >= 0.04


def test_path_clear_follows_the_corner_rule():
    grid = np.zeros((5, 5), np.int8)
    grid[1, 2] = 100
    assert path_clear(grid, np.array([[0, 0], [4, 0]])) == -1
    assert path_clear(grid, np.array([[0, 0], [4, 2]])) == 0          # crosses (2, 1)
    # Through the vertex between (1, 1) and (2, 2): it touches (2, 1), which is blocked.
    assert path_clear(grid, np.array([[0, 0], [1, 1], [3, 3]])) == 1
    grid[1, 2] = 0
    assert path_clear(grid, np.array([[0, 0], [1, 1], [3, 3]])) == -1


OPTIONS = PlanOptions(goal_tolerance_cells=1.5, lethal_threshold=60, unknown_is_obstacle=False, stop_at_goal=True,
                      algorithm="astar", any_angle=True, cost_factor=3.0, neutral_cost=40.0, robot_radius_cells=1.0,
                      inflation_radius_cells=5.0, inflation_decay=0.8)


def test_the_protocol_carries_every_option_and_keeps_the_default_body():
    frames = protocol.encode_plan(7, b"h" * 16, START, GOAL, OPTIONS)
    decoded = protocol.decode_plan(7, frames[1:], 1 << 20)
    assert decoded.options == OPTIONS
    for field in dataclasses.fields(PlanOptions):   # each option on its own, so none can be dropped unseen
        default = getattr(PlanOptions(), field.name)
        changed = {"algorithm": "astar", "unknown_is_obstacle": False, "stop_at_goal": False, "any_angle": True,
                   "lethal_threshold": 70}.get(field.name, default + 1.25 if isinstance(default, float) else default)
        options = dataclasses.replace(PlanOptions(), **{field.name: changed})
        assert protocol.decode_plan(1, protocol.encode_plan(1, b"h" * 16, START, GOAL, options)[1:], 1 << 20).options \
            == options, field.name
    assert len(protocol.encode_plan(1, b"h" * 16, START, GOAL)[1]) == protocol.PLAN_BODY.size == 43
    body = bytearray(frames[1])
    body[protocol.PLAN_BODY.size] = 9
    with pytest.raises(protocol.ProtocolError, match="algorithm"):
        protocol.decode_plan(1, [bytes(body)], 1 << 20)


def test_the_server_plans_with_every_option_as_the_binding_does():
    grid = corridor_grid()
    server = start_server()
    try:
        with CloudClient(server.endpoint, insecure=True, timeout_s=10.0) as client:
            for options in (OPTIONS, dataclasses.replace(OPTIONS, any_angle=False, algorithm="dijkstra"),
                            dataclasses.replace(OPTIONS, cost_factor=0.0, robot_radius_cells=0.0,
                                                inflation_radius_cells=0.0)):
                outcome = client.plan(grid, START, GOAL, options)
                assert outcome.reply.status == Status.OK, outcome.reply.message
                local = plan_raw(grid, START, GOAL, **options.planner_kwargs())
                assert outcome.reply.path.tolist() == local["path"].tolist()
                assert outcome.reply.cost_cells == pytest.approx(local["cost"])
                assert reply_problem(outcome.reply, grid, START, GOAL, options, 10.0) == ""
    finally:
        server.stop()


def test_the_client_refuses_an_any_angle_path_through_a_wall():
    grid = corridor_grid()
    options = PlanOptions(any_angle=True)
    straight = np.array([START, GOAL], np.int32)
    forged = protocol.Reply(1, Status.OK, "", straight, GOAL, 10, 0.001, float(np.hypot(*np.subtract(GOAL, START))))
    assert "crosses an obstacle" in reply_problem(forged, grid, START, GOAL, options, 1.0)


def test_the_server_inflates_a_map_once_for_all_requests_that_ask_the_same():
    """Inflation is a whole-map pass: the server keeps the inflated map in its map cache (same budget, same
    eviction), so a second request with the same options adds nothing to it, and answers as the binding does."""
    grid = corridor_grid()
    server = start_server()
    options = PlanOptions(cost_factor=3.0, robot_radius_cells=1.0, inflation_radius_cells=5.0)
    try:
        with CloudClient(server.endpoint, insecure=True, timeout_s=10.0) as client:
            first = client.plan(grid, START, GOAL, options)
            cached = len(server.cache)
            second = client.plan(grid, START, GOAL, options)
            other = client.plan(grid, START, GOAL, dataclasses.replace(options, inflation_radius_cells=7.0))
            assert len(server.cache) == cached + 1                 # one more inflated map for the new radius
            assert cached == 2                                     # the map and its inflation
            local = plan_raw(grid, START, GOAL, **options.planner_kwargs())
            for reply in (first.reply, second.reply):
                assert reply.status == Status.OK and reply.path.tolist() == local["path"].tolist()
            assert other.reply.status == Status.OK
            bad = client.plan(grid, START, GOAL, dataclasses.replace(options, robot_radius_cells=float("nan")))
            assert bad.reply.status == Status.INVALID_REQUEST       # bad radii: the core's verdict, nothing cached
            assert len(server.cache) == cached + 1
    finally:
        server.stop()
