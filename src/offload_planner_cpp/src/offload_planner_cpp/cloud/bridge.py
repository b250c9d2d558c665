"""Robot-side bridge to the cloud planner, without ROS: the rospy node (cloud_bridge_node) only converts
messages. It answers a PlanPath request exactly as the local planner node's PlanRequestHandler does
(same checks, same order, same statuses and messages), except that the core runs in the cloud and a
silent cloud gives CLOUD_TIMEOUT."""
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Optional, Tuple

import numpy as np
import zmq

from offload_planner_cpp.cloud import protocol
from offload_planner_cpp.cloud.client import CloudClient, CloudTimeout, KnownMaps
from offload_planner_cpp.grid_geometry import MapGeometry, fmt, in_map_frame, validate_map, yaw_of
from offload_planner_cpp.cloud.protocol import PlanOptions, Status

# A child of rospy's "rosout" logger: under the node its records reach /rosout and the node's log like
# rospy.logwarn's; without ROS it is an ordinary Python logger.
LOG = logging.getLogger("rosout.offload_planner_cpp.cloud.bridge")


class PlanPathStatus:
    """offload_msgs/PlanPath response codes, repeated here so this module needs no ROS (a test checks
    they match the generated message)."""
    OK = 0
    NO_MAP = 1
    BAD_FRAME = 2
    START_OFF_MAP = 3
    GOAL_OFF_MAP = 4
    START_BLOCKED = 5
    GOAL_BLOCKED = 6
    NO_PATH = 7
    INVALID_MAP = 8
    CLOUD_TIMEOUT = 9
    CLOUD_ERROR = 10
    INVALID_REQUEST = 11


# Protocol status to PlanPath status, as toServiceStatus() maps the core's statuses.
_SERVICE_STATUS = {
    Status.OK: PlanPathStatus.OK,
    Status.EMPTY_MAP: PlanPathStatus.INVALID_MAP,
    Status.SIZE_MISMATCH: PlanPathStatus.INVALID_MAP,
    Status.START_OFF_MAP: PlanPathStatus.START_OFF_MAP,
    Status.GOAL_OFF_MAP: PlanPathStatus.GOAL_OFF_MAP,
    Status.START_BLOCKED: PlanPathStatus.START_BLOCKED,
    Status.GOAL_BLOCKED: PlanPathStatus.GOAL_BLOCKED,
    Status.NO_PATH: PlanPathStatus.NO_PATH,
    Status.INVALID_OPTIONS: PlanPathStatus.INVALID_MAP,
}


@dataclass(frozen=True)
class MapSnapshot:
    grid: np.ndarray         # int8 [y, x], a view of the message's buffer
    geometry: MapGeometry
    frame_id: str
    stamp: Any               # the map header's stamp, passed back untouched
    map_hash: bytes


@dataclass(frozen=True)
class StampedPoint:
    frame_id: str
    x: float
    y: float


@dataclass
class BridgeResult:
    status: int
    message: str = ""
    path_x_m: np.ndarray = field(default_factory=lambda: np.empty(0))   # cell centres, start to goal
    path_y_m: np.ndarray = field(default_factory=lambda: np.empty(0))
    reached_goal: bool = False       # the path ends in the requested goal cell (not a tolerance fallback)
    planning_time_s: float = 0.0
    expansions: int = 0
    cost_m: float = 0.0
    map_stamp: Any = None
    frame_id: str = ""
    link_round_trip_s: Optional[float] = None   # None when the cloud was not asked
    reachable: bool = True


@dataclass(frozen=True)
class BridgeConfig:
    endpoint: str
    keys_dir: Optional[str] = None
    insecure: bool = False
    timeout_s: float = 5.0
    retries: int = 1
    heartbeat_timeout_s: float = 1.0
    upload_retry_max_s: float = 60.0   # a failed map upload is retried after the heartbeat period, doubling to this
    lethal_threshold: int = 50
    unknown_is_obstacle: bool = True


class CloudBridge:
    """Thread safe: concurrent plan() calls each borrow their own client socket."""

    def __init__(self, config: BridgeConfig):
        self.config = config
        self._context = zmq.Context()
        self._known_maps = KnownMaps()
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
        self.upload_attempts = 0                        # map uploads started by the heartbeat (for tests)

    def _new_client(self, timeout_s: float, retries: int) -> CloudClient:
        return CloudClient(self.config.endpoint, keys_dir=self.config.keys_dir, insecure=self.config.insecure,
                           timeout_s=timeout_s, retries=retries, known_maps=self._known_maps,
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
        why = validate_map(width, height, int(np.asarray(data).size), resolution, origin_x, origin_y,
                           tuple(orientation))
        if not why and np.asarray(data).dtype != np.int8:
            why = f"map data has dtype {np.asarray(data).dtype}, expected int8"
        if why:
            with self._lock:
                self._rejected = why
            return why
        grid = np.ascontiguousarray(data).reshape(height, width)
        geometry = MapGeometry(resolution, origin_x, origin_y, yaw_of(*orientation), width, height)
        snapshot = MapSnapshot(grid, geometry, frame_id, stamp, protocol.grid_hash(grid))
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
            why = (f"no answer within {fmt(self.config.timeout_s)} s: the map may exceed the server's "
                   f"--max-message-mib (libzmq then drops the connection), or the cloud is down")
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
                        self.config.endpoint, why, fmt(self.config.upload_retry_max_s))
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

    def plan(self, start: StampedPoint, goal: StampedPoint, tolerance_m: float) -> BridgeResult:
        """The PlanPath answer for a request, checked as PlanRequestHandler::handle() checks it."""
        with self._lock:
            snapshot, rejected = self._map, self._rejected
        if snapshot is None:
            message = "no map received yet on the map topic"
            if rejected:
                message += f" (last map rejected: {rejected})"
            return BridgeResult(PlanPathStatus.NO_MAP, message)
        result = BridgeResult(PlanPathStatus.OK, map_stamp=snapshot.stamp, frame_id=snapshot.frame_id)
        for name, point in (("start", start), ("goal", goal)):
            if not in_map_frame(point.frame_id, snapshot.frame_id):
                result.status = PlanPathStatus.BAD_FRAME
                result.message = (f"{name} is in frame '{point.frame_id}' but the map is in '{snapshot.frame_id}': "
                                  f"transform it to the map frame first")
                return result
        finite = all(math.isfinite(v) for v in (start.x, start.y, goal.x, goal.y))
        # The service's tolerance is float32, as the local node reads it: a larger value is inf there.
        with np.errstate(over="ignore"):
            tolerance_m = float(np.float32(tolerance_m))
        if not finite or not math.isfinite(tolerance_m) or tolerance_m < 0.0:
            result.status = PlanPathStatus.INVALID_REQUEST
            result.message = "start and goal must be finite and tolerance a finite number >= 0 metres"
            return result
        geometry = snapshot.geometry
        start_cell = geometry.world_to_cell(start.x, start.y)
        if start_cell is None:
            result.status = PlanPathStatus.START_OFF_MAP
            result.message = f"start ({fmt(start.x)}, {fmt(start.y)}) m is off the map"
            return result
        goal_cell = geometry.world_to_cell(goal.x, goal.y)
        if goal_cell is None:
            result.status = PlanPathStatus.GOAL_OFF_MAP
            result.message = f"goal ({fmt(goal.x)}, {fmt(goal.y)}) m is off the map"
            return result

        options = PlanOptions(goal_tolerance_cells=tolerance_m / geometry.resolution,
                              lethal_threshold=self.config.lethal_threshold,
                              unknown_is_obstacle=self.config.unknown_is_obstacle)
        client = self._borrow_client()
        try:
            outcome = client.plan(snapshot.grid, start_cell, goal_cell, options, snapshot.map_hash)
        except CloudTimeout:
            result.status = PlanPathStatus.CLOUD_TIMEOUT
            result.message = (f"cloud planner at {self.config.endpoint} did not answer within "
                              f"{fmt(self.config.timeout_s)} s: plan locally")
            result.link_round_trip_s = self.config.timeout_s
            result.reachable = False
            return result
        finally:
            self._return_client(client)
        reply = outcome.reply
        # The link's share of the round trip: what the learner's b_t measures.
        result.link_round_trip_s = max(0.0, outcome.round_trip_s - reply.planning_time_s)
        if reply.status not in _SERVICE_STATUS:
            result.status = PlanPathStatus.CLOUD_ERROR
            result.message = f"cloud planner refused the request ({reply.status.name}): {reply.message}"
            return result
        result.status = _SERVICE_STATUS[reply.status]
        result.message = reply.message
        result.planning_time_s = reply.planning_time_s
        result.expansions = reply.expansions
        if reply.status != Status.OK:
            return result
        result.cost_m = reply.cost_cells * geometry.resolution
        result.path_x_m, result.path_y_m = geometry.cells_to_world(reply.path)
        result.reached_goal = tuple(reply.goal) == tuple(goal_cell)
        return result

    def _borrow_client(self) -> CloudClient:
        with self._lock:
            if self._idle_clients:
                return self._idle_clients.pop()
        return self._new_client(timeout_s=self.config.timeout_s, retries=self.config.retries)

    def _return_client(self, client: CloudClient) -> None:
        with self._lock:
            self._idle_clients.append(client)
