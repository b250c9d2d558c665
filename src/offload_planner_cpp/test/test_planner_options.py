"""The planner's options everywhere: each keyword of the pybind11 module changes what the core does, the
cloud protocol carries every option and the server plans with it, cost-aware planning is exact against
scipy on the same weighted graph (inflated Husky playpen), and any-angle paths are shorter than the
8-connected optimum without crossing an obstacle."""
import dataclasses
import inspect
import re

import numpy as np
import pytest
from scipy import ndimage
from scipy.sparse import csgraph

import offload_planner_cpp
from offload_planner_cpp import PlanStatus, inflate, path_clear, plan, plan_raw
from offload_cloud import protocol
from offload_cloud.client import CloudClient
from offload_cloud.reply_check import reply_problem
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
    waves = plan(grid, START, GOAL, algorithm="dijkstra")
    astar = plan(grid, START, GOAL, algorithm="astar")
    assert astar.cost == pytest.approx(waves.cost) and astar.expansions < waves.expansions
    assert base.cost == pytest.approx(waves.cost) and base.expansions < astar.expansions   # auto: jump points
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


# --- the one options table of the core (planner_options.h), through the binding ---

INF = float("inf")
# Written out by hand: a name missing, a default or a bound changed in the core fails here.
# name: (type, scope, node parameter, default, min, max, min_open, unit, in_cells, resolution_power)
EXPECTED_TABLE = {
    "lethal_threshold": ("int", "cells", True, 50, 1, 101, False, "occupancy", None, 0),
    "unknown_is_obstacle": ("bool", "cells", True, True, 0, 1, False, "", None, 0),
    "goal_tolerance_cells": ("float", "cells", False, 0.0, 0, INF, False, "cells", None, 0),
    "stop_at_goal": ("bool", "cells", False, True, 0, 1, False, "", None, 0),
    "cost_factor": ("float", "cells", True, 0.0, 0, INF, False, "", None, 0),
    "neutral_cost": ("float", "cells", True, 50.0, 0, INF, True, "", None, 0),
    "robot_radius_cells": ("float", "cells", False, 0.0, 0, 10000, False, "cells", None, 0),
    "inflation_radius_cells": ("float", "cells", False, 0.0, 0, 10000, False, "cells", None, 0),
    "inflation_decay": ("float", "cells", False, 0.5, 0, INF, False, "1/cell", None, 0),
    "algorithm": ("algorithm", "cells", True, "auto", 0, 3, False, "", None, 0),
    "any_angle": ("bool", "cells", True, False, 0, 1, False, "", None, 0),
    "robot_radius": ("float", "metres", True, 0.0, 0, INF, False, "m", "robot_radius_cells", -1),
    "inflation_radius": ("float", "metres", True, 0.0, 0, INF, False, "m", "inflation_radius_cells", -1),
    "cost_scaling_factor": ("float", "metres", True, 10.0, 0, INF, False, "1/m", "inflation_decay", 1),
}
FIELDS = ("type", "scope", "node_parameter", "default", "min", "max", "min_open", "unit", "in_cells",
          "resolution_power")


def test_the_options_table_holds_every_option_with_its_default_and_bounds():
    table = offload_planner_cpp.options_table()
    assert [row["name"] for row in table] == list(EXPECTED_TABLE)
    for row in table:
        assert tuple(row[field] for field in FIELDS) == EXPECTED_TABLE[row["name"]], row["name"]
        assert type(row["default"]) is type(EXPECTED_TABLE[row["name"]][3]), row["name"]
        assert row["meaning"] and row["rule"], row["name"]
    assert offload_planner_cpp.ALGORITHM_NAMES == ("dijkstra", "astar", "jps", "auto")
    assert table[[row["name"] for row in table].index("algorithm")]["choices"] == ("dijkstra", "astar", "jps", "auto")
    assert offload_planner_cpp.OPTION_DEFAULTS == {name: spec[3] for name, spec in EXPECTED_TABLE.items()}


def keyword_defaults(function) -> dict:
    """Keyword defaults of a pybind11 function, read from the signature line of its docstring."""
    signature = function.__doc__.splitlines()[0]
    return {name: eval(value) for name, value in re.findall(r"(\w+): \w+ = ([^,)]+)", signature)}


def test_every_keyword_default_is_the_tables():
    defaults = offload_planner_cpp.OPTION_DEFAULTS
    cell_options = {name for name, spec in EXPECTED_TABLE.items() if spec[1] == "cells"}
    keyword = {"goal_tolerance_cells": "goal_tolerance"}   # plan()'s and plan_raw()'s name for it
    for function in (plan_raw, plan):
        if function is plan:
            found = {name: p.default for name, p in inspect.signature(plan).parameters.items()
                     if p.default is not inspect.Parameter.empty}
        else:
            found = keyword_defaults(plan_raw)
        assert found == {keyword.get(name, name): defaults[name] for name in cell_options}, function.__name__
    assert keyword_defaults(offload_planner_cpp.free_cells) == {
        name: defaults[name] for name in ("lethal_threshold", "unknown_is_obstacle")}
    assert keyword_defaults(inflate) == {
        name: defaults[name] for name in ("inflation_decay", "lethal_threshold", "unknown_is_obstacle")}


def beyond(spec, side):
    """A value just outside (or at, for an open bound) a numeric row's bound."""
    kind, _, _, _, low, high, open_low = spec[:7]
    if side == "low":
        return low if open_low else (low - 1 if kind == "int" else low - 1e-9)
    return high + 1 if kind == "int" else high * (1 + 1e-12)


@pytest.mark.parametrize("name", [name for name, spec in EXPECTED_TABLE.items() if spec[0] in ("int", "float")])
def test_validate_options_refuses_just_beyond_each_bound_in_the_cores_words(name):
    spec = EXPECTED_TABLE[name]
    kind, low, high, open_low = spec[0], spec[4], spec[5], spec[6]
    validate = offload_planner_cpp.validate_options
    if not open_low:
        assert validate(**{name: low})[name] == low
    if high != INF:
        assert validate(**{name: high})[name] == high
    rule = {"int": f"an integer in {low}..{high}"}.get(kind, f"a finite number {'>' if open_low else '>='} {low}"
                                                       if high == INF else f"a finite number in {low}..{high}")
    bad = [beyond(spec, "low"), float("nan"), -INF] + ([beyond(spec, "high")] if high != INF else [INF])
    if kind == "int":
        bad.append(low + 0.5)
    for value in bad:
        with pytest.raises(ValueError) as error:
            validate(**{name: value})
        assert str(error.value) == f"{name} must be {rule}, got {value!r}", value
    if spec[1] == "cells":   # the planner refuses the same values with the same message
        keyword = "goal_tolerance" if name == "goal_tolerance_cells" else name
        raw = plan_raw(np.zeros((4, 4), np.int8), (0, 0), (3, 3), **{keyword: bad[0]})
        assert raw["status"] == PlanStatus.INVALID_REQUEST
        with pytest.raises(ValueError) as error:
            validate(**{name: bad[0]})
        assert raw["message"] == str(error.value)


def test_validate_options_checks_names_types_and_algorithms():
    validate = offload_planner_cpp.validate_options
    assert validate() == offload_planner_cpp.OPTION_DEFAULTS
    values = validate(lethal_threshold=101, algorithm="astar", any_angle=True, robot_radius=1000.0)
    assert values["lethal_threshold"] == 101 and values["algorithm"] == "astar" and values["any_angle"] is True
    assert values["robot_radius"] == 1000.0, "metres have no upper bound: the cells are per map"
    with pytest.raises(ValueError, match=r'^algorithm must be one of dijkstra, astar, jps, auto, got "bfs"$'):
        validate(algorithm="bfs")
    with pytest.raises(ValueError, match=r'^algorithm must be one of dijkstra, astar, jps, auto, got "bfs"$'):
        plan_raw(np.zeros((4, 4), np.int8), (0, 0), (3, 3), algorithm="bfs")
    for name, value in (("algorithm", 1), ("any_angle", "yes"), ("neutral_cost", "5"), ("lethal_threshold", True)):
        with pytest.raises(ValueError, match=f"^{name} must be .*, got {re.escape(repr(value))}$"):
            validate(**{name: value})
    with pytest.raises(TypeError, match="unknown planner option 'bogus'"):
        validate(bogus=1)
    jps_weighted = r"^algorithm jps is exact only where every passable cell costs the same: cost_factor must be 0, got 3$"
    with pytest.raises(ValueError, match=jps_weighted):
        validate(algorithm="jps", cost_factor=3.0)
    assert plan_raw(np.zeros((4, 4), np.int8), (0, 0), (3, 3), algorithm="jps", cost_factor=3.0)["message"] == \
        jps_weighted[1:-1]
    assert validate(algorithm="auto", cost_factor=3.0)["algorithm"] == "auto"
    for function in (offload_planner_cpp.free_cells, inflate):
        with pytest.raises(ValueError, match=r"^lethal_threshold must be an integer in 1\.\.101, got 0$"):
            function(np.zeros((4, 4), np.int8), *((1.0, 2.0) if function is inflate else ()), lethal_threshold=0)
    with pytest.raises(ValueError, match=r"^robot_radius_cells must be a finite number in 0\.\.10000, got nan$"):
        inflate(np.zeros((4, 4), np.int8), float("nan"), 2.0)


def test_options_in_cells_divides_radii_and_multiplies_the_decay_by_the_resolution():
    in_cells = offload_planner_cpp.options_in_cells
    assert in_cells(0.05, robot_radius=0.22, inflation_radius=0.55, cost_scaling_factor=3.0) == {
        "robot_radius_cells": 0.22 / 0.05, "inflation_radius_cells": 0.55 / 0.05, "inflation_decay": 3.0 * 0.05}
    assert in_cells(0.05) == {"robot_radius_cells": 0.0, "inflation_radius_cells": 0.0, "inflation_decay": 10.0 * 0.05}
    assert in_cells(0.05)["inflation_decay"] == pytest.approx(offload_planner_cpp.OPTION_DEFAULTS["inflation_decay"])
    for resolution in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="^resolution must be a finite number > 0, got "):
            in_cells(resolution)
    with pytest.raises(TypeError, match="not a parameter in metres"):
        in_cells(0.05, robot_radius_cells=1.0)
    with pytest.raises(TypeError, match="unknown planner option"):
        in_cells(0.05, robot_radius_m=1.0)


def test_the_protocol_takes_the_algorithm_codes_and_defaults_from_the_core():
    assert protocol.ALGORITHMS is offload_planner_cpp.ALGORITHM_NAMES
    defaults = offload_planner_cpp.OPTION_DEFAULTS
    assert dataclasses.asdict(PlanOptions()) == {field.name: defaults[field.name]
                                                 for field in dataclasses.fields(PlanOptions)}
    for code, name in enumerate(offload_planner_cpp.ALGORITHM_NAMES):
        # jps plans at uniform cost only: its algorithm alone differs from the defaults.
        changed = PlanOptions(algorithm=name, cost_factor=0.0 if name == "jps" else 1.0)
        body = protocol.encode_plan(1, b"h" * 16, START, GOAL, changed)[1]
        assert body[protocol.PLAN_BODY.size] == code
    with pytest.raises(ValueError, match=r'^algorithm must be one of dijkstra, astar, jps, auto, got "bfs"$'):
        protocol.encode_plan(1, b"h" * 16, START, GOAL, PlanOptions(algorithm="bfs"))
