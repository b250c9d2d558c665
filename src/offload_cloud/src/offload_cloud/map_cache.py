"""Bounded LRU cache of maps keyed by content hash, shared by the cloud server's worker threads, and
shared fairly between the clients that uploaded them."""
import collections
import threading
from typing import Dict, Optional

import numpy as np

# What one entry costs beyond its cells: the key, the dict and LRU links, the numpy header and the
# allocator's rounding (measured about 0.4 KiB on CPython 3.11; charged generously). Counting it keeps
# the cap honest for many tiny maps (200,000 maps of 8 cells are 1.6 MB of cells but ~80 MB of objects).
ENTRY_OVERHEAD_BYTES = 1024
# Maps up to this size are copied into a compact array of their own: a view would keep the whole
# received message (its zmq frame and libzmq buffer, several KiB) alive for a few cells.
_COPY_BELOW_BYTES = 1 << 20


class MapCache:
    """Keeps the most recently used maps whose total charge (cells + ENTRY_OVERHEAD_BYTES per map) stays
    within `capacity_bytes`; a map larger than the whole capacity is never kept (the request that brought
    it is still served).

    Each map belongs to the client that uploaded it first (`owner`). When room is needed, the least
    recently used map of the owner holding the most bytes goes first (the storing owner's own on a tie),
    so a robot that uploads many maps evicts its own, never another robot's smaller share: max-min
    fairness, each client keeps at least an equal share of the cap while it is within it."""

    def __init__(self, capacity_bytes: int):
        if capacity_bytes < 0:
            raise ValueError(f"cache capacity must be >= 0 bytes, got {capacity_bytes}")
        self.capacity_bytes = int(capacity_bytes)
        self._maps = collections.OrderedDict()    # hash -> (grid, owner), least recently used first
        self._by_owner = {}                       # owner -> OrderedDict of its hashes, LRU first
        self._owner_bytes = collections.Counter()  # owner -> charge of its maps
        self._lock = threading.Lock()
        self.size_bytes = 0      # cells plus per-entry overhead of the cached maps
        self.hits = 0
        self.misses = 0
        self.evictions = 0
        self.inserted = 0        # maps stored (uploads that were not cached yet)

    @staticmethod
    def charge(grid: np.ndarray) -> int:
        return grid.nbytes + ENTRY_OVERHEAD_BYTES

    def get(self, map_hash: bytes) -> Optional[np.ndarray]:
        with self._lock:
            entry = self._maps.get(map_hash)
            if entry is None:
                self.misses += 1
                return None
            self._touch(map_hash, entry[1])
            self.hits += 1
            return entry[0]

    def put(self, map_hash: bytes, grid: np.ndarray, owner: str = "") -> bool:
        """Stores `grid` (the caller must not modify it afterwards) for `owner`; False when it cannot fit
        at all."""
        charge = self.charge(grid)
        if charge > self.capacity_bytes:
            return False
        with self._lock:
            if map_hash in self._maps:
                self._touch(map_hash, self._maps[map_hash][1])
                return True
        if grid.nbytes < _COPY_BELOW_BYTES:
            grid = np.array(grid, dtype=np.int8, order="C", copy=True)
        with self._lock:
            if map_hash in self._maps:
                self._touch(map_hash, self._maps[map_hash][1])
                return True
            while self._maps and self.size_bytes + charge > self.capacity_bytes:
                self._evict_one(owner)
            self._maps[map_hash] = (grid, owner)
            self._by_owner.setdefault(owner, collections.OrderedDict())[map_hash] = None
            self._owner_bytes[owner] += charge
            self.size_bytes += charge
            self.inserted += 1
            return True

    def _touch(self, map_hash: bytes, owner: str) -> None:
        self._maps.move_to_end(map_hash)
        self._by_owner[owner].move_to_end(map_hash)

    def _evict_one(self, storing_owner: str) -> None:
        """Evicts the least recently used map of the heaviest owner (lock held)."""
        heaviest = max(self._by_owner, key=lambda owner: (self._owner_bytes[owner], owner == storing_owner))
        hashes = self._by_owner[heaviest]
        map_hash, _ = hashes.popitem(last=False)
        grid, _ = self._maps.pop(map_hash)
        charge = self.charge(grid)
        self.size_bytes -= charge
        self._owner_bytes[heaviest] -= charge
        if not hashes:
            del self._by_owner[heaviest]
            del self._owner_bytes[heaviest]
        self.evictions += 1

    def bytes_by_owner(self) -> Dict[str, int]:
        """Charge of the cached maps per owner (a snapshot)."""
        with self._lock:
            return dict(self._owner_bytes)

    def __len__(self) -> int:
        with self._lock:
            return len(self._maps)

    def __contains__(self, map_hash: bytes) -> bool:
        with self._lock:
            return map_hash in self._maps
