"""The requests the cloud server admitted and that wait for a worker, and the one upload of each map: when many
robots send the same map at once, one request uploads it and the others wait (parked) behind it, then go
ahead on the cached map. Every change is told to the admission's accounting."""
import collections
from dataclasses import dataclass
from typing import List, Optional

from offload_cloud import protocol
from offload_cloud.admission import Admission, Client
from offload_cloud.map_cache import MapCache
from offload_cloud.protocol import Kind


@dataclass(eq=False)   # compared by identity: removed from the queue as itself
class Request:
    frames: list                          # route + payload
    nbytes: int                           # payload bytes, counted in queued_bytes while waiting
    fd: Optional[int]                     # the connection it came on (dropped when that closes)
    request_id: int
    route_frames: int
    arrived: float                        # time.monotonic() when the broker admitted it
    client: Client = None                 # who sent it (fair share, counts)
    kind: Kind = Kind.PLAN
    uploads: Optional[bytes] = None       # hash of the map it carries and is the one to store
    carries_map: bool = False             # a plan with its map attached


def plan_hash(kind: Kind, payload) -> Optional[bytes]:
    """The map hash a plan names (for one that carries its map, the worker checks the claim), else None."""
    if kind != Kind.PLAN or len(payload) == 3 or len(payload) < 2 or len(payload[1]) != protocol.PLAN_BODY.size:
        return None
    return bytes(payload[1].buffer[:protocol.HASH_SIZE])


class RequestQueue:
    def __init__(self, admission: Admission, cache: MapCache):
        self.admission, self.cache = admission, cache
        self.queued = collections.deque()   # Request waiting for a worker
        self.parked = {}                    # map hash -> [Request] waiting for the one upload of that map

    def add(self, request: Request, payload) -> None:
        self.admission.enqueued(request)
        wanted = plan_hash(request.kind, payload)
        if wanted is not None:
            request.carries_map = len(payload) >= 4   # envelope, body, metadata and the cells' frames
            if wanted in self.cache:         # cached already: plan on the cached map, skip any upload
                if request.carries_map:
                    self._strip_map(request)
            elif wanted in self.parked:      # being uploaded by another request: wait for that one
                self.parked[wanted].append(request)
                return
            elif request.carries_map:        # the one upload of this map
                request.uploads = wanted
                self.parked[wanted] = []
        self.queued.append(request)

    def pop(self) -> Request:
        request = self.queued.popleft()
        self.admission.dequeued(request)
        return request

    def remove(self, request: Request) -> None:
        self.queued.remove(request)
        self.admission.dequeued(request)

    def drop_connection(self, fd: int) -> List[Request]:
        """Forgets the waiting requests of a connection that closed: its client gave up (Lazy Pirate closes
        the socket after a timeout and resends on a new one), so planning them would be wasted work."""
        dropped = [request for request in self.queued if request.fd == fd]
        if not dropped and not any(request.fd == fd for waiting in self.parked.values() for request in waiting):
            return []
        kept = [request for request in self.queued if request.fd != fd]
        self.queued.clear()
        self.queued.extend(kept)
        for map_hash in list(self.parked):
            dropped += [request for request in self.parked[map_hash] if request.fd == fd]
            self.parked[map_hash] = [request for request in self.parked[map_hash] if request.fd != fd]
        for request in dropped:
            self.admission.dequeued(request)
        for request in dropped:
            if request.uploads is not None:   # the carrier of a map is gone: the next waiting one carries it
                self.release(request.uploads)
        return dropped

    def release(self, map_hash: bytes) -> None:
        """The upload of `map_hash` finished or was dropped: requests parked behind it go to the front of
        the queue, without their copy of the map when it is cached now, else the first one carries it."""
        waiting = self.parked.pop(map_hash, [])
        if not waiting:
            return
        if map_hash in self.cache:
            for request in waiting:
                if request.carries_map:
                    self._strip_map(request)
        else:
            # The next request that carries the map uploads it; plans that carry only the hash go ahead
            # and get MAP_UNKNOWN (their client uploads); the rest keep waiting for the new carrier.
            carrier = next((request for request in waiting if request.carries_map), None)
            if carrier is not None:
                carrier.uploads = map_hash
                self.parked[map_hash] = [request for request in waiting if request.carries_map and request is not carrier]
            waiting = [request for request in waiting if request is carrier or not request.carries_map]
        self.queued.extendleft(reversed(waiting))

    def _strip_map(self, request: Request) -> None:
        """Turns a plan that carries a map the cache holds into a plan on the cached map."""
        kept = request.frames[:request.route_frames + 2]   # route, envelope and body
        self.admission.resized(request, sum(len(frame) for frame in kept[request.route_frames:]))
        request.frames, request.uploads, request.carries_map = kept, None, False
