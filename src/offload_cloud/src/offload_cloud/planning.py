"""What a cloud worker does with one PLAN or UPLOAD message: decode it, take the map from the cache or store
the one it carries, plan with the C++ core through the one request contract, and encode the reply. Never
raises: a bad message costs one reply."""
import dataclasses
import hashlib
import logging
import struct
import time
from typing import Callable

import numpy as np

from offload_planner_cpp import PlanStatus, inflate, plan_raw
from offload_cloud import protocol
from offload_cloud.map_cache import MapCache
from offload_cloud.protocol import Kind, ProtocolError, Reply, Status

LOG = logging.getLogger("offload_cloud.server")


class Planning:
    def __init__(self, cache: MapCache, max_cells: int, log_limited: Callable[..., None]):
        self.cache, self.max_cells, self.log_limited = cache, max_cells, log_limited

    def handle(self, payload, client: str) -> list:
        """Reply frames for a PLAN or UPLOAD message (envelope first) of `client`; never raises."""
        request_id = None
        started = time.perf_counter()
        try:
            kind, request_id = protocol.decode_envelope(payload[0].buffer)
            if kind == Kind.UPLOAD:
                return protocol.encode_reply(self._upload(request_id, payload[1:], client))
            return protocol.encode_reply(self._plan(request_id, payload[1:], started, client))
        except ProtocolError as error:
            request_id = protocol.request_id_of(payload[0].buffer) if request_id is None else request_id
            self.log_limited(logging.WARNING, ("request", error.status), "request %d: %s: %s", request_id,
                                  error.status.name, error)
            return protocol.encode_reply(Reply(request_id, error.status, str(error)))
        except Exception as error:   # a bug must cost one reply, never the server
            request_id = protocol.request_id_of(payload[0].buffer) if request_id is None else request_id
            LOG.exception("request %d failed", request_id)
            return protocol.encode_reply(Reply(request_id, Status.SERVER_ERROR, f"server error: {error}"))

    def _store(self, map_hash: bytes, grid: np.ndarray, client: str) -> None:
        if self.cache.put(map_hash, grid, client):
            LOG.info("map %s (%d x %d) cached; %d maps, %.1f MiB", map_hash.hex()[:12], grid.shape[1],
                     grid.shape[0], len(self.cache), self.cache.size_bytes / 2**20)
        else:
            LOG.warning("map %s of %d bytes exceeds the whole cache; served uncached", map_hash.hex()[:12],
                        grid.nbytes)

    def _upload(self, request_id: int, frames, client: str) -> Reply:
        if len(frames) < 2:
            raise ProtocolError(Status.BAD_REQUEST, f"upload needs a metadata frame and the map's cell frames after "
                                                    f"the envelope, got {len(frames)} frames")
        map_hash, grid = protocol.decode_map(frames[0].buffer, [frame.buffer for frame in frames[1:]], self.max_cells)
        self._store(map_hash, grid, client)
        return Reply(request_id, Status.OK, map_hash.hex())

    def _plan(self, request_id: int, frames, started: float, client: str) -> Reply:
        request = protocol.decode_plan(request_id, [frame.buffer for frame in frames], self.max_cells)
        grid = request.grid
        if grid is None:
            grid = self.cache.get(request.map_hash)
            if grid is None:
                LOG.info("request %d: map %s not cached: asking for an upload", request_id,
                         request.map_hash.hex()[:12])
                return Reply(request_id, Status.MAP_UNKNOWN, f"map {request.map_hash.hex()} is not cached: upload it")
            source = "cache hit"
        else:
            self._store(request.map_hash, grid, client)
            source = "uploaded"
        options = request.options
        if options.robot_radius_cells > 0 or options.inflation_radius_cells > 0:
            grid, options = self._inflated(request.map_hash, grid, options, client)
        raw = protocol_plan(grid, request, options)
        status = Status(int(raw["status"]))
        if LOG.isEnabledFor(logging.INFO):   # not even the arguments when the line is not written
            LOG.info("request %d: map %s %s, %s -> %s: %s, plan %.2f ms, %d expansions, %.2f ms in server",
                     request_id, request.map_hash.hex()[:12], source, request.start, request.goal, raw["status"],
                     raw["seconds"] * 1e3, raw["expansions"], (time.perf_counter() - started) * 1e3)
        return Reply(request_id, status, raw["message"], raw["path"], raw["goal"], raw["expansions"],
                     raw["seconds"], raw["cost"])


    def _inflated(self, map_hash: bytes, grid: np.ndarray, options: protocol.PlanOptions, client: str):
        """The map inflated as `options` ask, from the map cache when an earlier request asked the same (a
        whole-map distance transform per request would cost more than the plan), and the options that plan on
        it as it is. Inflated maps share the cache's byte budget and eviction with the maps themselves."""
        settings = struct.pack("<3dh?", options.robot_radius_cells, options.inflation_radius_cells,
                               options.inflation_decay, options.lethal_threshold, options.unknown_is_obstacle)
        key = hashlib.blake2b(map_hash + settings, digest_size=protocol.HASH_SIZE, person=b"inflated").digest()
        inflated = self.cache.get(key)
        if inflated is None:
            try:
                inflated = inflate(grid, options.robot_radius_cells, options.inflation_radius_cells,
                                   options.inflation_decay, options.lethal_threshold, options.unknown_is_obstacle)
            except ValueError:
                return grid, options   # the planner reports what is wrong with the options
            self.cache.put(key, inflated, client)
        return inflated, dataclasses.replace(options, robot_radius_cells=0.0, inflation_radius_cells=0.0)


def protocol_plan(grid: np.ndarray, request: protocol.PlanRequest, options: protocol.PlanOptions) -> dict:
    """plan_raw() with the request's options; malformed option values come back as a status, not a raise."""
    try:
        return plan_raw(grid, request.start, request.goal, **options.planner_kwargs())
    except ValueError as error:
        return {"status": PlanStatus.INVALID_REQUEST, "message": str(error), "path": np.empty((0, 2), np.int32),
                "goal": request.goal, "expansions": 0, "seconds": 0.0, "cost": 0.0}
