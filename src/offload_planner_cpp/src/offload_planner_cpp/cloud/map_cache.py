"""Bounded LRU cache of maps keyed by content hash, shared by the cloud server's worker threads."""
import collections
import threading
from typing import Optional

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
    it is still served)."""

    def __init__(self, capacity_bytes: int):
        if capacity_bytes < 0:
            raise ValueError(f"cache capacity must be >= 0 bytes, got {capacity_bytes}")
        self.capacity_bytes = int(capacity_bytes)
        self._maps = collections.OrderedDict()
        self._lock = threading.Lock()
        self.size_bytes = 0      # cells plus per-entry overhead of the cached maps
        self.hits = 0
        self.misses = 0
        self.evictions = 0

    @staticmethod
    def charge(grid: np.ndarray) -> int:
        return grid.nbytes + ENTRY_OVERHEAD_BYTES

    def get(self, map_hash: bytes) -> Optional[np.ndarray]:
        with self._lock:
            grid = self._maps.get(map_hash)
            if grid is None:
                self.misses += 1
                return None
            self._maps.move_to_end(map_hash)
            self.hits += 1
            return grid

    def put(self, map_hash: bytes, grid: np.ndarray) -> bool:
        """Stores `grid` (the caller must not modify it afterwards); False when it cannot fit at all."""
        charge = self.charge(grid)
        if charge > self.capacity_bytes:
            return False
        with self._lock:
            if map_hash in self._maps:
                self._maps.move_to_end(map_hash)
                return True
        if grid.nbytes < _COPY_BELOW_BYTES:
            grid = np.array(grid, dtype=np.int8, order="C", copy=True)
        with self._lock:
            if map_hash in self._maps:
                self._maps.move_to_end(map_hash)
                return True
            while self._maps and self.size_bytes + charge > self.capacity_bytes:
                _, evicted = self._maps.popitem(last=False)
                self.size_bytes -= self.charge(evicted)
                self.evictions += 1
            self._maps[map_hash] = grid
            self.size_bytes += charge
            return True

    def __len__(self) -> int:
        with self._lock:
            return len(self._maps)

    def __contains__(self, map_hash: bytes) -> bool:
        with self._lock:
            return map_hash in self._maps
