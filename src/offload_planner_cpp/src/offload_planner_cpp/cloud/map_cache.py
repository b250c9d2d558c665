"""Bounded LRU cache of maps keyed by content hash, shared by the cloud server's worker threads."""
import collections
import threading
from typing import Optional

import numpy as np


class MapCache:
    """Keeps the most recently used maps whose total size stays within `capacity_bytes`; a map larger
    than the whole capacity is never kept (the request that brought it is still served)."""

    def __init__(self, capacity_bytes: int):
        self.capacity_bytes = int(capacity_bytes)
        self._maps = collections.OrderedDict()
        self._lock = threading.Lock()
        self.size_bytes = 0
        self.hits = 0
        self.misses = 0
        self.evictions = 0

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
        if grid.nbytes > self.capacity_bytes:
            return False
        with self._lock:
            if map_hash in self._maps:
                self._maps.move_to_end(map_hash)
                return True
            while self._maps and self.size_bytes + grid.nbytes > self.capacity_bytes:
                _, evicted = self._maps.popitem(last=False)
                self.size_bytes -= evicted.nbytes
                self.evictions += 1
            self._maps[map_hash] = grid
            self.size_bytes += grid.nbytes
            return True

    def __len__(self) -> int:
        with self._lock:
            return len(self._maps)

    def __contains__(self, map_hash: bytes) -> bool:
        with self._lock:
            return map_hash in self._maps
