"""Robot-side bridge to the cloud planner, without ROS: the rospy node (nodes.cloud_bridge) only converts
messages. The request contract (map validation, frames, request checks, world <-> cell conversion, the
poses of a path) is the C++ core's, called through the binding exactly as the local planner node calls
it, so both answer a request alike; only the planning runs in the cloud, and a silent cloud gives
CLOUD_TIMEOUT."""
import logging
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, NamedTuple, Optional, Tuple

import numpy as np
import zmq

from offload_planner_cpp import OPTION_DEFAULTS, PlanStatus
from offload_planner_cpp._core import (MapGeometry, check_map, no_map_outcome, options_in_cells, options_table,
                                      path_poses, resolve_request, validate_options)
from offload_cloud import protocol
from offload_cloud.client import CloudClient, CloudTimeout, KnownMaps, PlannedGrids
from offload_cloud.protocol import PlanOptions, Status
from offload_cloud.reply_check import PathRows

# A child of rospy's "rosout" logger: under the node its records reach /rosout and the node's log like
# rospy.logwarn's; without ROS it is an ordinary Python logger.
LOG = logging.getLogger("rosout.offload_cloud.bridge")


@dataclass(frozen=True)
class MapSnapshot:
    grid: np.ndarray         # int8 [y, x], a view of the message's buffer
    geometry: MapGeometry
    frame_id: str
    stamp: Any               # the map header's stamp, passed back untouched
    map_hash: bytes
    resolution: float        # geometry.resolution as a Python float: a bound attribute costs a pybind11 call


class StampedPose(NamedTuple):
    """A geometry_msgs/PoseStamped in plain types; the orientation only matters for the path's ends. (A NamedTuple,
    not a frozen dataclass, whose __init__ sets each field through object.__setattr__: two per cloud plan.)"""
    frame_id: str
    x: float
    y: float
    z: float = 0.0
    orientation: Tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)   # qx, qy, qz, qw

    def pose(self) -> Tuple[float, ...]:
        return (self.x, self.y, self.z, *self.orientation)


_NO_POSES = np.empty((0, 7))
_NO_POSES.flags.writeable = False   # viewed by every result without poses: one C call, not a lambda and np.empty


@dataclass
class BridgeResult:
    status: PlanStatus
    message: str = ""
    poses: np.ndarray = field(default_factory=_NO_POSES.view)   # x, y, z, qx, qy, qz, qw per pose
    reached_goal: bool = False       # the path ends in the requested goal cell (not a tolerance fallback)
    planning_time_s: float = 0.0
    expansions: int = 0
    cost_m: float = 0.0
    map_stamp: Any = None
    frame_id: str = ""
    link_round_trip_s: Optional[float] = None   # None when the cloud was not asked
    reachable: bool = True
    bytes_sent: int = 0              # link payload bytes of this request, map re-uploads included
    bytes_received: int = 0
    # With plan(row_prefix=...): the poses as path_poses' rows (a uint32 count, then each pose's 7 doubles after
    # the prefix) instead of `poses`, and the prefix they were written with.
    pose_rows: bytes = b""
    pose_row_prefix: bytes = b""


_DEFAULT = OPTION_DEFAULTS   # the core's (planner_options.h)
# The node parameters of the core's options table, and BridgeConfig's field for those it names otherwise.
_PLANNER_PARAMETERS = [row["name"] for row in options_table() if row["node_parameter"]]
_FIELD_OF = {"robot_radius": "robot_radius_m", "inflation_radius": "inflation_radius_m"}


@dataclass(frozen=True)
class BridgeConfig:
    endpoint: str
    keys_dir: Optional[str] = None
    insecure: bool = False
    timeout_s: float = 5.0
    retries: int = 1
    heartbeat_timeout_s: float = 1.0
    upload_retry_max_s: float = 60.0   # a failed map upload is retried after the heartbeat period, doubling to this
    lethal_threshold: int = _DEFAULT["lethal_threshold"]
    unknown_is_obstacle: bool = _DEFAULT["unknown_is_obstacle"]
    max_map_cells: int = 64_000_000   # larger maps are refused, as by the local planner node
    # The planner options, as the local planner node's parameters (radii in metres, decay per metre).
    algorithm: str = _DEFAULT["algorithm"]
    any_angle: bool = _DEFAULT["any_angle"]
    cost_factor: float = _DEFAULT["cost_factor"]
    neutral_cost: float = _DEFAULT["neutral_cost"]
    robot_radius_m: float = _DEFAULT["robot_radius"]
    inflation_radius_m: float = _DEFAULT["inflation_radius"]
    cost_scaling_factor: float = _DEFAULT["cost_scaling_factor"]

    def planner_parameters(self) -> dict:
        """The planner options by the names of the core's table (its node parameters: radii in metres), for
        validate_options."""
        return {name: getattr(self, _FIELD_OF.get(name, name)) for name in _PLANNER_PARAMETERS}

    @staticmethod
    def planner_fields(parameters: dict) -> dict:
        """BridgeConfig's keyword arguments for planner parameters named as in the core's table."""
        return {_FIELD_OF.get(name, name): value for name, value in parameters.items()}


class CloudBridge:
    """Thread safe: concurrent plan() calls each borrow their own client socket."""

    def __init__(self, config: BridgeConfig):
        self.config = config
        self._context = zmq.Context()
        self._known_maps = KnownMaps()
        self._planned_grids = PlannedGrids()   # one inflated map for every thread's client
        self._lock = threading.Lock()
        self._idle_clients = []
        self._map: Optional[MapSnapshot] = None
        self._rejected = ""
        # Fails now, not at the first request, when the keys are missing.
        self._heartbeat_client = self._new_client(timeout_s=config.heartbeat_timeout_s, retries=0)
        # Map uploads run beside the heartbeat (an upload the cloud never answers must not hold up the
        # pings), one at a time, on their own client; a failed one is retried with backoff.
        self._upload_client = self._new_client(timeout_s=config.timeout_s, retries=0)
        self._upload_thread: Optional[threading.Thread] = None
        self._failed_upload: Optional[bytes] = None   # hash of the map whose last upload failed
        self._upload_retry_at = 0.0
        self._upload_retry_s = 0.0
        self._last_heartbeat_at: Optional[float] = None
        self._heartbeat_period_s = 1.0                  # measured between heartbeat() calls
        self._non_pong_warned = False
        self._measured: Optional[Tuple[float, float]] = None   # (monotonic time, link round trip) of the last answer
        self.upload_attempts = 0                        # map uploads started by the heartbeat (for tests)
        self._last_options = None                       # (config, (resolution, tolerance cells), PlanOptions)

    def _new_client(self, timeout_s: float, retries: int) -> CloudClient:
        return CloudClient(self.config.endpoint, keys_dir=self.config.keys_dir, insecure=self.config.insecure,
                           timeout_s=timeout_s, retries=retries, known_maps=self._known_maps,
                           planned_grids=self._planned_grids,
                           context=self._context)

    def close(self) -> None:
        self.wait_for_upload(self.config.timeout_s + 1.0)
        with self._lock:
            clients, self._idle_clients = self._idle_clients, []
        for client in clients + [self._heartbeat_client, self._upload_client]:
            client.close()
        self._context.term()

    # -- map -------------------------------------------------------------------------------------------

    def set_map(self, data: np.ndarray, width: int, height: int, resolution: float, origin_x: float,
                origin_y: float, orientation: Tuple[float, float, float, float], frame_id: str, stamp) -> str:
        """Takes a new map (data: the message's int8 array, not copied); keeps the previous one and returns
        why when it is malformed, else returns ""."""
        data = np.asarray(data)
        checked, geometry = check_map(width, height, int(data.size), resolution, origin_x, origin_y,
                                      tuple(orientation), self.config.max_map_cells)
        why = checked.message
        if checked.ok and data.dtype != np.int8:
            why = f"map data has dtype {data.dtype}, expected int8"
        if why:
            with self._lock:
                self._rejected = why
            return why
        grid = np.ascontiguousarray(data).reshape(height, width)
        snapshot = MapSnapshot(grid, geometry, frame_id, stamp, protocol.grid_hash(grid), geometry.resolution)
        with self._lock:
            self._map = snapshot
        return ""

    @property
    def map(self) -> Optional[MapSnapshot]:
        with self._lock:
            return self._map

    # -- heartbeat ------------------------------------------------------------------------------------

    def heartbeat(self) -> Tuple[bool, float]:
        """(reachable, round trip s) of one ping. The round trip is always measured: reachable is True
        whenever the server answered at all (a non-pong answer too); only when nothing answered within
        heartbeat_timeout_s is it (False, heartbeat_timeout_s). Then, when the cloud answered and has not
        acknowledged the current map, starts its upload in the background (so the next plan carries only
        the hash); a failed upload is retried after the heartbeat period, doubling up to
        upload_retry_max_s, not at every heartbeat. Call from one thread only."""
        now = time.monotonic()
        if self._last_heartbeat_at is not None:
            self._heartbeat_period_s = max(0.01, now - self._last_heartbeat_at)
        self._last_heartbeat_at = now
        try:
            reply, round_trip_s = self._heartbeat_client.ping_reply()
        except CloudTimeout:
            return False, self.config.heartbeat_timeout_s
        if reply.status != Status.OK and not self._non_pong_warned:
            self._non_pong_warned = True
            LOG.warning("cloud planner at %s answers pings with %s: %s", self.config.endpoint, reply.status.name,
                        reply.message)
        self._upload_if_due()
        return True, round_trip_s

    def recent_round_trip(self, within_s: float) -> Optional[float]:
        """The link round trip a cloud answer to a plan measured within the last `within_s` seconds, else None.
        The heartbeat skips its ping then: at a few cloud requests a second the ping only repeats what the plans
        measure, and costs the robot a round trip, a publish and the learner's decoding of it (#30). Never while the
        cloud lacks the current map: the ping is what uploads it beside the plans."""
        measured, snapshot = self._measured, self.map
        if measured is None or time.monotonic() - measured[0] > within_s or \
                (snapshot is not None and snapshot.map_hash not in self._known_maps):
            return None
        return measured[1]

    def _upload_if_due(self) -> None:
        snapshot = self.map
        if snapshot is None or snapshot.map_hash in self._known_maps:
            return
        if self._upload_thread is not None and self._upload_thread.is_alive():
            return
        if snapshot.map_hash == self._failed_upload and time.monotonic() < self._upload_retry_at:
            return
        self.upload_attempts += 1
        self._upload_thread = threading.Thread(target=self._upload, args=(snapshot,), name="map-upload",
                                               daemon=True)
        self._upload_thread.start()

    def _upload(self, snapshot: MapSnapshot) -> None:
        why = ""
        try:
            reply = self._upload_client.upload(snapshot.grid, snapshot.map_hash, timeout_s=self.config.timeout_s)
            if reply.status != Status.OK:
                why = f"the cloud answered {reply.status.name}: {reply.message}"
        except CloudTimeout:
            why = (f"no answer within {self.config.timeout_s:g} s: the cloud is down, or it predates maps in "
                   f"frames of 1 MiB and drops a map of more than a few frames unanswered")
        except Exception as error:   # never let the upload thread die silently
            why = f"{type(error).__name__}: {error}"
        short_hash = snapshot.map_hash.hex()[:12]
        if not why:
            if self._failed_upload == snapshot.map_hash:
                LOG.info("map %s uploaded to the cloud after earlier failures", short_hash)
                self._failed_upload = None
            return
        if self._failed_upload != snapshot.map_hash:
            LOG.warning("upload of map %s (%d bytes) to %s failed: %s; retrying with backoff up to every %s s, "
                        "plans on this map carry it along meanwhile", short_hash, snapshot.grid.nbytes,
                        self.config.endpoint, why, f"{self.config.upload_retry_max_s:g}")
            self._failed_upload = snapshot.map_hash
            self._upload_retry_s = self._heartbeat_period_s
        else:
            self._upload_retry_s = min(2.0 * self._upload_retry_s, self.config.upload_retry_max_s)
        self._upload_retry_at = time.monotonic() + self._upload_retry_s

    def wait_for_upload(self, timeout_s: Optional[float] = None) -> None:
        """Waits for a map upload the heartbeat started, if any."""
        thread = self._upload_thread
        if thread is not None:
            thread.join(timeout_s)

    # -- plan -----------------------------------------------------------------------------------------

    def plan(self, start: StampedPose, goal: StampedPose, tolerance_m: float,
             row_prefix: Optional[Callable[[str], bytes]] = None) -> BridgeResult:
        """The PlanPath answer for a request: checked and converted by the core's request contract,
        planned in the cloud. With row_prefix (the path's frame id -> bytes, called once the path is back), a path's
        poses come as `pose_rows` for a caller that serializes them (the ROS node), not as `poses`."""
        with self._lock:
            snapshot, rejected = self._map, self._rejected
        if snapshot is None:
            outcome = no_map_outcome(rejected)
            return BridgeResult(outcome.status, outcome.message)
        result = BridgeResult(PlanStatus.OK, map_stamp=snapshot.stamp, frame_id=snapshot.frame_id)
        # tolerance_m becomes float32, as the service carries it (a larger value is inf, so refused).
        refusal, start_cell, goal_cell, tolerance_cells = resolve_request(
            snapshot.geometry, snapshot.frame_id, start.frame_id, start.x, start.y, goal.frame_id, goal.x, goal.y,
            tolerance_m)
        if refusal is not None:
            result.status, result.message = refusal.status, refusal.message
            return result

        options = self._options(snapshot.resolution, tolerance_cells)
        # With row_prefix, the reply's check writes the path's rows in its own call into the core.
        rows = None if row_prefix is None else PathRows(snapshot.geometry, start.pose(), goal.pose(),
                                                        snapshot.frame_id, row_prefix)
        client = self._borrow_client()
        sent_before, received_before = client.bytes_sent, client.bytes_received
        try:
            outcome = client.plan(snapshot.grid, start_cell, goal_cell, options, snapshot.map_hash, rows)
        except CloudTimeout:
            result.status = PlanStatus.CLOUD_TIMEOUT
            result.message = (f"cloud planner at {self.config.endpoint} did not answer within "
                              f"{self.config.timeout_s:g} s: plan locally")
            result.link_round_trip_s = self.config.timeout_s
            result.reachable = False
            return result
        finally:
            result.bytes_sent = client.bytes_sent - sent_before
            result.bytes_received = client.bytes_received - received_before
            self._return_client(client)
        reply = outcome.reply
        # The link's share of the round trip: what the learner's b_t measures.
        result.link_round_trip_s = max(0.0, outcome.round_trip_s - reply.planning_time_s)
        self._measured = (time.monotonic(), result.link_round_trip_s)   # one assignment: thread safe
        if not protocol.is_planner_status(reply.status):
            result.status = PlanStatus.CLOUD_ERROR
            result.message = f"cloud planner refused the request ({reply.status.name}): {reply.message}"
            return result
        # The planner's outcome codes are the core's: the cloud's answer reaches the robot untranslated.
        result.status = PlanStatus(int(reply.status))
        result.message = reply.message
        result.planning_time_s = reply.planning_time_s
        result.expansions = reply.expansions
        if result.status != PlanStatus.OK:
            return result
        result.cost_m = reply.cost_cells * snapshot.resolution
        result.reached_goal = tuple(reply.goal) == goal_cell
        if rows is None:
            result.poses = path_poses(snapshot.geometry, reply.path, start.pose(), goal.pose(), result.reached_goal)
        else:
            result.pose_row_prefix, result.pose_rows = rows.prefix, rows.rows
        return result

    def _options(self, resolution: float, tolerance_cells: float) -> PlanOptions:
        """The request's planner options; the last ones are kept, as a robot asks with the same map resolution and
        tolerance over and over (building them took a few microseconds of the bridge's CPU per request)."""
        last, config = self._last_options, self.config
        if last is not None and last[0] is config and last[1] == (resolution, tolerance_cells):
            return last[2]
        options = PlanOptions(goal_tolerance_cells=tolerance_cells, lethal_threshold=config.lethal_threshold,
                              unknown_is_obstacle=config.unknown_is_obstacle, algorithm=config.algorithm,
                              any_angle=config.any_angle, cost_factor=config.cost_factor,
                              neutral_cost=config.neutral_cost,
                              # metres -> cells at this map's resolution, as the local planner node converts
                              **options_in_cells(resolution, robot_radius=config.robot_radius_m,
                                                 inflation_radius=config.inflation_radius_m,
                                                 cost_scaling_factor=config.cost_scaling_factor))
        self._last_options = (config, (resolution, tolerance_cells), options)   # one assignment: thread safe
        return options

    def set_planner_parameters(self, parameters: dict) -> dict:
        """Plans from the next request on with `parameters` (planner options by the core table's node parameter
        names, radii in metres: the local planner's dynamic_reconfigure values) over those in force; returns
        {name: value} of the ones that changed. ValueError, in the core's words, for a value the core refuses (TypeError
        for a name that is none of its options): then nothing changes."""
        current = self.config.planner_parameters()
        unknown = sorted(set(parameters) - set(current))
        if unknown:
            raise TypeError(f"no planner node parameter {', '.join(unknown)}; they are {', '.join(current)}")
        validate_options(**{**current, **parameters})
        changed = {name: value for name, value in parameters.items() if value != current[name]}
        if changed:   # a new config object: _options builds the next request's options from it
            self.config = replace(self.config, **BridgeConfig.planner_fields(changed))
        return changed

    def _borrow_client(self) -> CloudClient:
        with self._lock:
            if self._idle_clients:
                return self._idle_clients.pop()
        return self._new_client(timeout_s=self.config.timeout_s, retries=self.config.retries)

    def _return_client(self, client: CloudClient) -> None:
        with self._lock:
            self._idle_clients.append(client)
