"""The request contract through the binding, as the cloud bridge uses it: the same C++ functions the
ROS planner node calls (test_planner_ros.cpp covers them from C++). Codes and numbers, not wording."""
import math

import numpy as np
import pytest

from offload_planner_cpp import PlanStatus
from offload_planner_cpp._core import check_map, in_map_frame, no_map_outcome, path_poses, resolve_request
from offload_cloud import protocol

IDENTITY = (0.0, 0.0, 0.0, 1.0)


def geometry(width=10, height=4, resolution=0.5, origin=(-1.0, 2.0), orientation=IDENTITY):
    outcome, checked = check_map(width, height, width * height, resolution, *origin, orientation)
    assert outcome.ok, outcome
    return checked


def test_world_to_cell_convention():
    g = geometry()
    assert g.world_to_cell(-1.0, 2.0) == (0, 0)
    assert g.world_to_cell(3.99, 3.99) == (9, 3)
    assert g.world_to_cell(4.0, 2.0) is None          # the right edge is off the map
    assert g.world_to_cell(-1.01, 2.0) is None
    assert g.cell_to_world(0, 0) == (-0.75, 2.25)
    turned = geometry(5, 5, 1.0, (0.0, 0.0), (0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)))
    assert turned.world_to_cell(-0.5, 2.5) == (2, 0)  # grid x runs along world y
    x, y = turned.cell_to_world(2, 0)
    assert (round(x, 9), round(y, 9)) == (-0.5, 2.5)


def test_yaw_of_a_quaternion_of_any_length():
    assert geometry(orientation=(0, 0, 10, 10)).origin_yaw == pytest.approx(math.pi / 2, abs=1e-12)
    assert geometry(orientation=(0, 0, 0.02 * math.sin(-1), 0.02 * math.cos(-1))).origin_yaw == \
        pytest.approx(-2.0, abs=1e-12)
    outcome, checked = check_map(3, 2, 6, 0.05, 0, 0, (0, 0, 0, 0))
    assert outcome.status == PlanStatus.INVALID_MAP and checked is None


@pytest.mark.parametrize("point", [(1e308, 2.5), (-1e308, 2.5), (0.0, 1e308), (1e300, -1e300), (math.inf, 0.0),
                                   (0.0, -math.inf), (math.nan, 0.0), (0.0, math.nan)])
def test_points_far_off_or_not_finite_are_off_the_map(point):
    for yaw in (0.0, 0.7):
        g = geometry(resolution=0.05, orientation=(0, 0, math.sin(yaw / 2), math.cos(yaw / 2)))
        assert g.world_to_cell(*point) is None


@pytest.mark.parametrize("args", [
    (0, 5, 0, 0.05, 0, 0, IDENTITY),                   # empty
    (3, 2, 5, 0.05, 0, 0, IDENTITY),                   # 5 cells for 3 x 2
    (3, 2, 6, 0.0, 0, 0, IDENTITY),                    # resolution 0
    (3, 2, 6, -0.1, 0, 0, IDENTITY),
    (3, 2, 6, math.nan, 0, 0, IDENTITY),
    (3, 2, 6, 0.05, math.nan, 0, IDENTITY),
    (3, 2, 6, 0.05, 0, math.inf, IDENTITY),
    (3, 2, 6, 0.05, 0, 0, (math.nan, 0, 0, 1)),
    (3, 2, 6, 0.05, 0, 0, (0, 0, math.inf, 1)),
    (100001, 1, 100001, 0.05, 0, 0, IDENTITY),         # wider than the planner accepts
])
def test_malformed_maps_are_invalid_map(args):
    outcome, checked = check_map(*args)
    assert outcome.status == PlanStatus.INVALID_MAP and outcome.message and checked is None


def test_map_cell_limit():
    assert check_map(10, 10, 100, 0.05, 0, 0, IDENTITY, max_cells=99)[0].status == PlanStatus.INVALID_MAP
    assert check_map(10, 10, 100, 0.05, 0, 0, IDENTITY, max_cells=100)[0].ok


def test_request_checks_in_order():
    g = geometry()
    assert resolve_request(g, "map", "map", -0.75, 2.25, "/map", 3.75, 3.75, 0.5) == (None, (0, 0), (9, 3), 1.0)
    assert resolve_request(g, "map", "", 0, 2.5, "", 1, 2.5, 0)[0] is None      # empty frame: the map's

    def status(*args):
        refusal, *cells = resolve_request(g, "map", *args)
        assert (refusal is None or refusal.message) and (cells == [None] * 3) == (refusal is not None)
        return PlanStatus.OK if refusal is None else refusal.status
    assert status("odom", 0, 2.5, "map", 1, 2.5, 0) == PlanStatus.BAD_FRAME
    assert status("map", 0, 2.5, "odom", 1, 2.5, 0) == PlanStatus.BAD_FRAME
    assert status("odom", math.nan, 2.5, "map", 1, 2.5, 0) == PlanStatus.BAD_FRAME   # frames first
    assert status("map", math.nan, 2.5, "map", 1, 2.5, 0) == PlanStatus.INVALID_REQUEST
    assert status("map", 0, 2.5, "map", 1, math.inf, 0) == PlanStatus.INVALID_REQUEST
    assert status("map", 0, 2.5, "map", 1, 2.5, -0.1) == PlanStatus.INVALID_REQUEST
    assert status("map", 0, 2.5, "map", 1, 2.5, 1e308) == PlanStatus.INVALID_REQUEST  # inf as float32
    assert status("map", 0, 2.5, "map", 1, 2.5, 3e38) == PlanStatus.OK               # finite as float32
    assert status("map", -5, 2.5, "map", 100, 2.5, 0) == PlanStatus.START_OFF_MAP     # start before goal
    assert status("map", 0, 2.5, "map", 1e308, 2.5, 0) == PlanStatus.GOAL_OFF_MAP
    assert in_map_frame("", "map") and in_map_frame("/map", "map") and not in_map_frame("odom", "map")
    assert no_map_outcome("").status == PlanStatus.NO_MAP
    assert "too small" in no_map_outcome("too small").message


def test_path_poses():
    g = geometry()
    path = np.array([[0, 0], [1, 1], [2, 1], [3, 1]], np.int32)
    start = (-0.7, 2.2, 0.1, 0.0, 0.0, 0.0, 0.0)   # a caller's zero quaternion stays the caller's
    goal = (0.8, 2.8, 0.0, 0.0, 0.0, 0.0, 1.0)
    poses = path_poses(g, path, start, goal, True)
    assert poses.shape == (4, 7)
    assert tuple(poses[0]) == start and tuple(poses[-1]) == goal
    # Interior poses: cell centres, facing the next cell.
    assert tuple(poses[1, :2]) == g.cell_to_world(1, 1) and tuple(poses[2, :2]) == g.cell_to_world(2, 1)
    yaw = 2 * np.arctan2(poses[1:3, 5], poses[1:3, 6])
    assert np.allclose(yaw, 0.0) and np.allclose(np.linalg.norm(poses[1:3, 3:], axis=1), 1.0)
    # A tolerance fallback ends in the cell it reached, facing along the last step.
    fallback = path_poses(g, path, start, goal, False)
    assert tuple(fallback[-1, :2]) == g.cell_to_world(3, 1) and fallback[-1, 6] == pytest.approx(1.0)
    diagonal = path_poses(g, np.array([[0, 0], [1, 1], [2, 2]], np.int32), start, goal, False)
    assert 2 * np.arctan2(diagonal[1, 5], diagonal[1, 6]) == pytest.approx(math.pi / 4)


def test_path_poses_of_a_long_path_and_as_rows():
    """Every pose as the one rule gives it (cell centre; heading of the step to the next cell), bit for bit, on a rotated
    map, with runs of equal steps (whose heading is computed once per run); with row_prefix, the same doubles after
    the prefix in each row, after a uint32 count."""
    g = geometry(600, 600, 0.05, (1.5, -2.0), (0.0, 0.0, math.sin(0.35), math.cos(0.35)))
    rng = np.random.default_rng(3)
    moves = np.array([(1, 0), (1, 1), (0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1)])
    steps = moves[np.repeat(rng.integers(0, 8, 40), rng.integers(1, 6, 40))]
    path = (np.vstack([[0, 0], np.cumsum(steps, axis=0)]) + 200).astype(np.int32)
    start, goal = (0.0,) * 7, (1.0,) * 7
    poses = path_poses(g, path, start, goal, False)
    for k in range(1, len(path)):
        assert tuple(poses[k, :2]) == g.cell_to_world(*path[k])
        dx, dy = (path[min(k + 1, len(path) - 1)] - path[k]) if k + 1 < len(path) else (path[k] - path[k - 1])
        heading = g.origin_yaw + math.atan2(dy, dx)
        assert tuple(poses[k, 2:]) == (0.0, 0.0, 0.0, math.sin(0.5 * heading), math.cos(0.5 * heading)), k
    prefix = b"header of a row"
    rows = path_poses(g, path, start, goal, False, row_prefix=prefix)
    assert isinstance(rows, bytes) and int.from_bytes(rows[:4], "little") == len(path)
    table = np.frombuffer(rows[4:], np.uint8).reshape(len(path), len(prefix) + 56)
    assert all(bytes(row[:len(prefix)]) == prefix for row in table)
    assert table[:, len(prefix):].copy().view("<f8").tobytes() == poses.astype("<f8").tobytes()
    assert path_poses(g, path[:0], start, goal, False, row_prefix=prefix) == bytes(4)


def test_status_codes_are_the_services_and_the_wires():
    """The codes are typed once, in the C++ core: the generated PlanPath message and the protocol's
    Status agree with the binding's PlanStatus name for name and value."""
    core = {name: int(code) for name, code in PlanStatus.__members__.items()}
    assert core["OK"] == 0 and len(core) == len(set(core.values()))
    srv = pytest.importorskip("offload_msgs.srv")
    service = {name: getattr(srv.PlanPathResponse, name) for name in dir(srv.PlanPathResponse)
               if name.isupper() and isinstance(getattr(srv.PlanPathResponse, name), int)}
    assert service == core
    for name, code in core.items():
        assert protocol.Status[name] == code and protocol.is_planner_status(code)
    link = [s for s in protocol.Status if s.name not in core]
    assert link and not any(protocol.is_planner_status(s) for s in link)
