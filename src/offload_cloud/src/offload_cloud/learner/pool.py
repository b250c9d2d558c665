"""The experience pool: every robot's rows as ROS 1 bags under POOL/<robot>/, so `retrain`, `report` and
`off_policy` read the pool (or one robot's directory) unchanged.

Bounded like the planner server: per key a token bucket of rows (rate and burst) and one of bytes; the pool as a
whole a disk budget, kept by deleting the oldest closed bag files first (any robot's; counted); one robot's
directory its own share of it (its oldest first). A batch that a bucket cannot take, or that the budget cannot
make room for, gets BUSY and the robot keeps it. A robot's bag is closed (indexed, renamed from `.bag.active` to
`.bag`) when it passes the rotation size or the robot's definitions change; a bag a killed learner left open
stays a readable `.bag.active`."""
import os
import re
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

from offload_cloud.learner.rows import PoolBag, check_rows, typed

# What a batch may add on disk beyond its rows' bytes (ROS 1 bag records): per message its record header and index
# entry; per batch a chunk's header, its connection records and index records; and, when it opens a bag, the bag's
# 4 KiB header record, plus the index a sealed bag gets (its connections again). An upper bound, so the budget holds
# on disk and not only in row bytes (a bag of 20 rows of 234 bytes is 12.8 KiB).
MESSAGE_OVERHEAD = 64
BATCH_OVERHEAD = 1024
BAG_OVERHEAD = 4096 + 1024
SEED_ROBOT = "_seed"   # a learning run's bag given with --seed-bag; no key name starts with "_"
_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")


@dataclass
class PoolLimits:
    bag_bytes: int = 16 << 20           # rotation size of a robot's bag
    total_bytes: int = 1 << 30          # the pool's disk budget
    robot_bytes: int = 256 << 20        # one robot's share of it
    rows_per_s: float = 50.0            # per key; 0: no rate limit
    rows_burst: float = 2048.0
    bytes_per_s: float = 256 << 10
    bytes_burst: float = 16 << 20


class _Bucket:
    def __init__(self, rate: float, burst: float):
        self.rate, self.burst, self.level, self.at = rate, burst, burst, time.monotonic()

    def take(self, amount: float) -> bool:
        if self.rate <= 0:
            return True
        now = time.monotonic()
        self.level = min(self.burst, self.level + (now - self.at) * self.rate)
        self.at = now
        if amount > self.level:
            return False
        self.level -= amount
        return True


@dataclass
class KeyCounts:
    accepted: int = 0
    refused: Counter = field(default_factory=Counter)   # rows by reason
    busy: int = 0                                       # batches answered BUSY
    bytes: int = 0                                      # accepted bytes

    def to_dict(self) -> dict:
        return {"accepted": self.accepted, "refused": dict(self.refused), "refused_rows": sum(self.refused.values()),
                "busy": self.busy, "bytes": self.bytes}


class ExperiencePool:
    def __init__(self, root: str, limits: PoolLimits = PoolLimits()):
        self.root = root
        self.limits = limits
        self.scratch = os.path.join(root, ".scratch")
        os.makedirs(self.scratch, exist_ok=True)
        self.counts: Dict[str, KeyCounts] = {}
        self.evicted_bags = 0
        self.evicted_bytes = 0
        self._open: Dict[str, PoolBag] = {}
        self._buckets: Dict[str, Tuple[_Bucket, _Bucket]] = {}
        self._lock = threading.Lock()   # the service thread writes, the trainer reads the file list

    # --- writing ---------------------------------------------------------------------------------------------
    def add(self, robot: str, definitions: dict, md5: dict, rows: Sequence[Tuple[bytes, bytes]]
            ) -> Tuple[Optional[str], int, int]:
        """(BUSY reason or None, rows accepted, rows refused). Rows the bag reader refuses are counted per key."""
        if not _NAME.match(robot):
            raise ValueError(f"robot name {robot!r}")
        counts = self.counts.setdefault(robot, KeyCounts())
        size = sum(len(d) + len(o) for d, o in rows)
        connections = sum(len(str(text)) + 256 for text in definitions.values()) if isinstance(definitions, dict) \
            else 0
        growth = size + 2 * MESSAGE_OVERHEAD * len(rows) + BATCH_OVERHEAD + BAG_OVERHEAD + 3 * connections
        rows_bucket, bytes_bucket = self._buckets.setdefault(robot, (
            _Bucket(self.limits.rows_per_s, self.limits.rows_burst),
            _Bucket(self.limits.bytes_per_s, self.limits.bytes_burst)))
        if not rows_bucket.take(len(rows)) or not bytes_bucket.take(size):
            counts.busy += 1
            return f"over the rate of {self.limits.rows_per_s:g} rows/s or {self.limits.bytes_per_s:g} B/s for " \
                   f"{robot}", 0, 0
        with self._lock:
            if not self._make_room(robot, growth):
                counts.busy += 1
                return "the pool's disk budget is full", 0, 0
            types = typed(definitions, md5)
            accepted, refused = check_rows(types, rows, self.scratch)
            counts.refused.update(refused)
            if accepted:
                self._write(robot, types, [rows[i] for i in accepted])
        counts.accepted += len(accepted)
        counts.bytes += sum(len(rows[i][0]) + len(rows[i][1]) for i in accepted)
        return None, len(accepted), len(rows) - len(accepted)

    def _write(self, robot: str, types, rows) -> None:
        bag = self._open.get(robot)
        if bag is not None and (bag.types != types or bag.size() >= self.limits.bag_bytes):
            self._seal(robot)
            bag = None
        if bag is None:
            directory = os.path.join(self.root, robot)
            os.makedirs(directory, exist_ok=True)
            bag = PoolBag(os.path.join(directory, f"{robot}-{time.time_ns():020d}.bag.active"), types)
            self._open[robot] = bag
        bag.write(rows)

    def _seal(self, robot: str) -> None:
        bag = self._open.pop(robot)
        bag.close()
        os.replace(bag.path, bag.path[:-len(".active")])

    def close(self) -> None:
        with self._lock:
            for robot in list(self._open):
                self._seal(robot)

    def _make_room(self, robot: str, size: int) -> bool:
        """Deletes the oldest closed bags until `size` more bytes fit the robot's share and the pool's budget."""
        for scope, budget in ((robot, self.limits.robot_bytes), (None, self.limits.total_bytes)):
            files = self._files(scope)
            used = sum(bytes_ for _, bytes_, _ in files)
            writing = {bag.path for bag in self._open.values()}
            for path, bytes_, _ in sorted(files, key=lambda f: f[2]):
                if used + size <= budget:
                    break
                if path in writing:
                    continue   # the bag being written: sealed by rotation, deleted in a later round
                os.unlink(path)
                self.evicted_bags += 1
                self.evicted_bytes += bytes_
                used -= bytes_
            if used + size > budget:
                return False
        return True

    # --- reading ---------------------------------------------------------------------------------------------
    def robots(self) -> List[str]:
        return sorted(name for name in os.listdir(self.root)
                      if _NAME.match(name) and os.path.isdir(os.path.join(self.root, name)))

    def _files(self, robot: Optional[str] = None) -> List[Tuple[str, int, int]]:
        """(path, bytes, name order) of the bags of one robot or all; a bag's name carries its start time."""
        found = []
        for name in ([robot] if robot else self.robots()):
            directory = os.path.join(self.root, name)
            if not os.path.isdir(directory):
                continue
            for entry in os.scandir(directory):
                if entry.name.endswith((".bag", ".bag.active")):
                    stamp = re.search(r"-(\d{20})\.bag", entry.name)
                    found.append((entry.path, entry.stat().st_size, int(stamp.group(1)) if stamp else 0))
        return found

    def bag_paths(self, robot: str) -> List[str]:
        with self._lock:
            return [path for path, _, _ in sorted(self._files(robot), key=lambda f: f[2])]

    def disk_bytes(self) -> int:
        return sum(self.disk_bytes_by_robot().values())

    def disk_bytes_by_robot(self) -> Dict[str, int]:
        """Bytes of each robot's bags; under the lock, so a metrics scrape never stats a bag being evicted."""
        with self._lock:
            return {robot: sum(bytes_ for _, bytes_, _ in self._files(robot)) for robot in self.robots()}

    def add_seed_bag(self, path: str) -> Optional[str]:
        """Pools a learning run's bag as the robot SEED_ROBOT (once: a restarted learner keeps its copy)."""
        import shutil

        directory = os.path.join(self.root, SEED_ROBOT)
        target = os.path.join(directory, f"{SEED_ROBOT}-{0:020d}.bag")
        if os.path.exists(target):
            return None
        os.makedirs(directory, exist_ok=True)
        shutil.copyfile(path, target + ".tmp")
        os.replace(target + ".tmp", target)
        return target
