"""Model versions on the cloud host: content-addressed files, a history, the fleet's current version and per-robot
pins, in one directory that operator commands and the running service share.

    STORE/models/<version>.npz   a model file; its name is the SHA-256 of its bytes (model_file.model_version)
    STORE/history.jsonl          one JSON line per event: a training round ("trained": version, parent, time,
                                 rows used per robot, gate figures per robot, published or not) or an operator's
                                 or robot's pin / rollback / unpin
    STORE/state.json             {"current": version, "fleet_pinned": bool, "pins": {robot: version},
                                 "rolled_back": {robot: [version, ...]},
                                 "rollback_pins": {robot: the version its own rollback pinned it to, until the gate
                                 publishes a newer one}}
    STORE/lock                   flock'ed around every read-modify-write of state.json and history appends

Every write is atomic (a temporary file in the same directory, fsync, os.replace), so a running service reads
either the old state or the new one; it re-reads state.json whenever the file changed."""
import fcntl
import json
import os
import time
from contextlib import contextmanager
from typing import Dict, List, Optional, Sequence

from offload_learner_py.core.model_file import MAX_MODEL_BYTES, ModelFileError, load_model, model_version

EMPTY_STATE = {"current": "", "fleet_pinned": False, "pins": {}, "rolled_back": {}, "rollback_pins": {}}
MAX_HISTORY_BYTES = 64 << 20


def _make_current(state: dict, entry: dict) -> None:
    """`entry`'s version becomes the fleet's current (a gate-passed round's or an operator's import)."""
    state["current"] = entry["version"]
    entry["published"] = True
    # A robot that rolled a version back was pinned where it went back to: a newer version the gate published
    # replaces that pin (its guard judges it live); an operator's pins stay.
    for robot in state["rollback_pins"]:
        state["pins"].pop(robot, None)
    entry["rollback_pins_lapsed"] = sorted(state["rollback_pins"])
    state["rollback_pins"] = {}


class StoreError(ValueError):
    """An operator command that cannot be carried out (unknown version, nothing to roll back to)."""


def atomic_write(path: str, data: bytes) -> None:
    temporary = f"{path}.tmp{os.getpid()}"
    with open(temporary, "wb") as out:
        out.write(data)
        out.flush()
        os.fsync(out.fileno())
    os.replace(temporary, path)


class ModelStore:
    def __init__(self, root: str):
        self.root = root
        self.models = os.path.join(root, "models")
        os.makedirs(self.models, exist_ok=True)
        self.state_path = os.path.join(root, "state.json")
        self.history_path = os.path.join(root, "history.jsonl")
        self._cached = (None, dict(EMPTY_STATE))

    # --- files -------------------------------------------------------------------------------------------------
    def put(self, data: bytes) -> str:
        if len(data) > MAX_MODEL_BYTES:
            raise StoreError(f"a model file is at most {MAX_MODEL_BYTES} bytes")
        version = model_version(data)
        path = os.path.join(self.models, f"{version}.npz")
        if not os.path.exists(path):
            atomic_write(path, data)
        return version

    def get(self, version: str) -> Optional[bytes]:
        """The file of `version`, or None when the store has none (or a damaged one: its hash differs)."""
        path = os.path.join(self.models, f"{version}.npz")
        if not (len(version) == 64 and os.path.isfile(path)) or os.path.getsize(path) > MAX_MODEL_BYTES:
            return None
        with open(path, "rb") as source:
            data = source.read(MAX_MODEL_BYTES + 1)
        return data if model_version(data) == version else None

    def has(self, version: str) -> bool:
        return len(version) == 64 and os.path.isfile(os.path.join(self.models, f"{version}.npz"))

    # --- state and history -------------------------------------------------------------------------------------
    @contextmanager
    def _locked(self):
        with open(os.path.join(self.root, "lock"), "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    def state(self) -> dict:
        """state.json as it is on disk now (re-read only when the file changed)."""
        try:
            info = os.stat(self.state_path)
        except FileNotFoundError:
            return json.loads(json.dumps(EMPTY_STATE))
        key = (info.st_ino, info.st_mtime_ns, info.st_size)
        if self._cached[0] != key:
            with open(self.state_path) as source:
                self._cached = (key, {**EMPTY_STATE, **json.load(source)})
        return json.loads(json.dumps(self._cached[1]))

    def _update(self, change, event: dict) -> dict:
        with self._locked():
            state = self.state()
            change(state)
            atomic_write(self.state_path, json.dumps(state, sort_keys=True, indent=1).encode())
            self._append({"time": time.time(), **event})
            return state

    def _append(self, entry: dict) -> None:
        with open(self.history_path, "a") as out:
            out.write(json.dumps(entry, sort_keys=True, allow_nan=False, default=str) + "\n")
            out.flush()
            os.fsync(out.fileno())

    def history(self, event: Optional[str] = None) -> List[dict]:
        if not os.path.exists(self.history_path):
            return []
        with open(self.history_path) as source:
            lines = source.read(MAX_HISTORY_BYTES).splitlines()
        entries = []
        for line in lines:
            try:
                entries.append(json.loads(line))
            except ValueError:
                continue   # a line cut by a crash
        return [e for e in entries if event is None or e.get("event") == event]

    def parent(self, version: str) -> str:
        for entry in reversed(self.history()):
            if entry.get("event") in ("trained", "imported") and entry.get("version") == version:
                return entry.get("parent", "")
        return ""

    # --- what training and robots do ---------------------------------------------------------------------------
    def record_round(self, entry: dict, data: Optional[bytes]) -> bool:
        """Logs a training round; with data (the gate passed) stores the file and makes it the fleet's current
        version unless an operator pinned the fleet. True when published."""
        def publish(state):
            if data is not None and not state["fleet_pinned"] and state["current"] == entry["parent"]:
                _make_current(state, entry)
        entry = {**entry, "event": "trained", "published": False}
        if data is not None:
            self.put(data)
        self._update(publish, entry)
        return entry["published"]

    def version_for(self, robot: str, current: str, rolled_back: Sequence[str]) -> str:
        """The version `robot` should run: its pin, else the fleet's current, never one it rolled back (then the
        one it runs). A rollback it reports pins it to the version it went back to until the gate publishes a newer
        fleet version (its guard judges that one live) or an operator pins or unpins it; a robot an operator pinned
        stays on the operator's pin."""
        state = self.state()
        known = set(state["rolled_back"].get(robot, []))
        new = [v for v in rolled_back if v not in known]
        if new:
            def pin(state):
                state["rolled_back"][robot] = sorted(known | set(new))[-64:]
                # An operator's pin for this robot outranks its own rollback: the pin stays (a version it
                # rolled back is still never served to it, below).
                operator_pinned = robot in state["pins"] and robot not in state["rollback_pins"]
                if current and current not in new and not operator_pinned:
                    state["pins"][robot] = current
                    state["rollback_pins"][robot] = current
            state = self._update(pin, {"event": "robot_rollback", "robot": robot, "rolled_back": new,
                                       "pinned": current})
        refused = set(rolled_back) | set(state["rolled_back"].get(robot, []))
        answer = state["pins"].get(robot) or state["current"]
        return current if answer in refused or not self.has(answer) and answer else answer

    # --- operator commands -------------------------------------------------------------------------------------
    def import_model(self, data: bytes, source: str, publish: bool = False) -> dict:
        """Adds an operator's model file (a model retrained from bags, say) to the store, checked as a robot would
        check it (model_file.load_model: weights only, shapes, this code's state schema). With publish it becomes
        the fleet's current version as a gate-passed round would (not pinned: training warm-starts from it, judges
        candidates against it and publishes over it; `rollback` returns to the version it replaced)."""
        try:
            load_model(data)
        except ModelFileError as error:
            raise StoreError(f"{source}: {error}") from None
        version = self.put(data)
        entry = {"event": "imported", "version": version, "source": source, "published": False}

        def change(state):
            current = state["current"]
            # The version in use imported again keeps the parent that made it current: not itself, so that
            # rollback still goes somewhere.
            entry["parent"] = current if current != version else self.parent(version)
            if not publish:
                return
            if state["fleet_pinned"]:
                raise StoreError(f"the fleet is pinned to {current[:16]}: `pin {version}` runs the imported "
                                 "version pinned, or `unpin` first")
            if current != version:
                _make_current(state, entry)
        return {**self._update(change, entry), "imported": version}

    def pin(self, version: str, robot: Optional[str] = None) -> dict:
        if not self.has(version):
            raise StoreError(f"no version {version} in {self.models}")
        def change(state):
            if robot:   # an operator's word: the learner no longer holds the robot's rollback of it against it
                state["pins"][robot] = version
                state["rollback_pins"].pop(robot, None)
                state["rolled_back"][robot] = [v for v in state["rolled_back"].get(robot, []) if v != version]
            else:
                state["current"], state["fleet_pinned"] = version, True
        return self._update(change, {"event": "pin", "version": version, "robot": robot or ""})

    def rollback(self, robot: Optional[str] = None) -> dict:
        state = self.state()
        running = (state["pins"].get(robot) if robot else None) or state["current"]
        previous = self.parent(running) if running else ""
        if not previous:
            raise StoreError(f"{running or 'no version'} has no previous version to roll back to")
        def change(state):
            if robot:
                state["pins"][robot] = previous
                state["rollback_pins"].pop(robot, None)
                state["rolled_back"][robot] = sorted(set(state["rolled_back"].get(robot, [])) | {running})
            else:
                state["current"], state["fleet_pinned"] = previous, True
        return self._update(change, {"event": "rollback", "from": running, "to": previous, "robot": robot or ""})

    def unpin(self, robot: Optional[str] = None) -> dict:
        def change(state):
            if robot:
                state["pins"].pop(robot, None)
                state["rolled_back"].pop(robot, None)
                state["rollback_pins"].pop(robot, None)
            else:
                state["fleet_pinned"] = False
        return self._update(change, {"event": "unpin", "robot": robot or ""})

    def summary(self) -> Dict:
        state = self.state()
        trained = self.history("trained")
        return {**state, "versions": sum(1 for e in trained if e.get("published")), "rounds": len(trained),
                "last_round": trained[-1] if trained else None}
