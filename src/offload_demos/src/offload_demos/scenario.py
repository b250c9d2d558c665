"""bench-policies' scenarios (`SCENARIO=`): the conditions a run's requests meet, from one YAML file.

A scenario names the link (a round-trip trace file of `time_s rtt_ms` lines, or one of the demo's link profiles),
the robot's other work (a CPU-load schedule of `[time_s, level]` steps, or the demo's seeded random levels) and the
map list (each map for a number of requests, cycled). The shipped ones are in `scenarios/` beside this module; a
user's own file works the same (paths in it are relative to the file, `package://pkg/...` to a ROS package).

How a schedule meets the same request in every policy's run. The link and the load are produced by processes
that never see a request (the WAN emulator delays bytes, the workload burns CPU), so they are keyed to the run's
clock: the driver sets one CLOCK_MONOTONIC epoch for the emulator, the workload and the goal generator, and the
goal generator sends request k open-loop at its nominal time (`request_times`), whatever the policy's answers
took. The map is keyed to the request index, by the goal generator that draws the goals: a new map's first request
comes `map_settle_s` later than open-loop arrivals alone would send it (a fixed pause, in every run alike, which the
nominal times include), and the goal generator publishes the map half-way through it (the previous request's
slower side has started on its own map; the planners, the bridge and the learner have the rest to take the new one). `per_request` is that schedule, request by
request: it is what every policy's run is given, and a test checks that bench-policies gives it to each alike."""
import math
import pathlib
from dataclasses import dataclass, replace
from typing import List, Optional, Tuple, Union

import yaml

from offload_demos.wan_emulator import LinkModel, read_trace
from offload_demos.workload import LoadSchedule, StepLoad

SCENARIO_DIR = pathlib.Path(__file__).resolve().parent / "scenarios"
NAMED = ("stationary", "handover", "load-shift", "map-switch", "drift")
LINK_DIR = pathlib.Path(__file__).resolve().parents[4] / "launch" / "config"   # the demo's link profiles, workload
KEYS = {"description", "link", "rtt_trace", "load", "maps", "map_settle_s", "steps"}


class ScenarioError(ValueError):
    """A scenario file that cannot make a run: the message says which file, which key and why."""


@dataclass(frozen=True)
class Scenario:
    name: str
    path: pathlib.Path
    description: str
    link: str                                  # a demo link profile, or "" when rtt_trace is given
    rtt_trace: Optional[pathlib.Path]          # a trace file, looped as the WAN emulator loops it
    load: Union[None, LoadSchedule, StepLoad]  # None: the demo's workload.yaml
    maps: Tuple[Tuple[str, int], ...]          # (map_server YAML, requests); () : the launch's map
    map_settle_s: float
    steps: int

    @property
    def trace_file(self) -> pathlib.Path:
        return self.rtt_trace or LINK_DIR / f"link_{self.link}.txt"

    def map_index(self, request: int) -> int:
        """Which of `maps` request k (from 0) plans on: each map for its requests, the list cycled."""
        cycle = sum(count for _, count in self.maps)
        k = request % cycle
        for index, (_, count) in enumerate(self.maps):
            if k < count:
                return index
            k -= count
        raise AssertionError("unreachable")

    def switches_before(self, request: int) -> int:
        """Map switches the goal generator makes before sending request k (a pause of map_settle_s each)."""
        if len(self.maps) < 2:
            return 0
        return sum(self.map_index(j) != self.map_index(j - 1) for j in range(1, request + 1))

    def request_times(self, steps: int, rate_hz: float) -> List[float]:
        """Each request's nominal send time, seconds after the run's epoch (open-loop at rate_hz)."""
        if not rate_hz > 0:
            raise ValueError("a scenario's schedules meet the same request only with open-loop arrivals (rate > 0)")
        return [k / rate_hz + self.map_settle_s * self.switches_before(k) for k in range(steps)]

    def load_schedule(self, seed: int, otherwise: Optional[LoadSchedule] = None):
        """The load the workload runs: the scenario's (random levels seeded by the run), else `otherwise` (the
        workload node's own parameters), else the demo's workload.yaml levels seeded by the run."""
        if isinstance(self.load, LoadSchedule):
            return replace(self.load, seed=seed)
        if self.load is not None:
            return self.load
        if otherwise is not None:
            return otherwise
        demo = yaml.safe_load((LINK_DIR / "workload.yaml").read_text()) or {}
        return LoadSchedule(tuple(demo.get("levels", LoadSchedule.levels)), demo.get("phase_s", LoadSchedule.phase_s),
                            seed)

    def per_request(self, steps: int, rate_hz: float, seed: int) -> List[tuple]:
        """(time_s, base round trip s, load level, map) of every request: what its run gives request k."""
        link = LinkModel(trace=read_trace(str(self.trace_file)), loop_trace=True)
        load = self.load_schedule(seed)
        maps = [path for path, _ in self.maps] or [""]
        return [(t, link.round_trip_s(t), load.level_at(t), maps[self.map_index(k) if self.maps else 0])
                for k, t in enumerate(self.request_times(steps, rate_hz))]


def resolve(name_or_path: str) -> pathlib.Path:
    """A named scenario's shipped file, or the user's path."""
    if name_or_path in NAMED:
        return SCENARIO_DIR / f"{name_or_path}.yaml"
    path = pathlib.Path(name_or_path)
    if not path.is_file():
        raise ScenarioError(f"scenario {name_or_path!r}: neither one of {', '.join(NAMED)} nor a file")
    return path.resolve()


def _path(value, where: str, base: pathlib.Path) -> pathlib.Path:
    if not isinstance(value, str) or not value:
        raise ScenarioError(f"{where}: expected a file path, got {value!r}")
    if value.startswith("package://"):
        package, _, rest = value[len("package://"):].partition("/")
        import rospkg
        try:
            path = pathlib.Path(rospkg.RosPack().get_path(package)) / rest
        except rospkg.ResourceNotFound:
            raise ScenarioError(f"{where}: no ROS package {package!r}") from None
    else:
        path = (base / value).resolve()
    if not path.is_file():
        raise ScenarioError(f"{where}: {path}: no such file")
    return path


def _load(value, where: str):
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) - {"schedule", "levels", "phase_s"} or not value:
        raise ScenarioError(f"{where}: expected {{schedule: [[time_s, level], ...]}} or {{levels: [...], "
                            f"phase_s: s}}, got {value!r}")
    try:
        if "schedule" in value:
            if set(value) != {"schedule"}:
                raise ValueError("schedule takes no levels or phase_s beside it")
            steps = value["schedule"]
            if not isinstance(steps, list) or not all(isinstance(s, list) and len(s) == 2 for s in steps):
                raise ValueError(f"schedule must be a list of [time_s, level] pairs, got {steps!r}")
            return StepLoad(tuple((float(t), float(level)) for t, level in steps))
        return LoadSchedule(tuple(float(level) for level in value.get("levels", LoadSchedule.levels)),
                            float(value.get("phase_s", LoadSchedule.phase_s)))
    except (TypeError, ValueError) as error:
        raise ScenarioError(f"{where}: {error}") from None


def _maps(value, where: str, base: pathlib.Path) -> Tuple[Tuple[str, int], ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not value:
        raise ScenarioError(f"{where}: expected a list of {{map: file, requests: n}}, got {value!r}")
    maps = []
    for k, entry in enumerate(value):
        at = f"{where}[{k}]"
        if not isinstance(entry, dict) or set(entry) - {"map", "requests"} or "map" not in entry:
            raise ScenarioError(f"{at}: expected {{map: file, requests: n}}, got {entry!r}")
        requests = entry.get("requests", 1)
        if isinstance(requests, bool) or not isinstance(requests, int) or requests < 1:
            raise ScenarioError(f"{at}.requests: expected a positive integer, got {requests!r}")
        path = _path(entry["map"], f"{at}.map", base)
        from offload_planner_cpp.maps import MapFormatError, load_map_server_yaml
        try:
            load_map_server_yaml(str(path))
        except (MapFormatError, OSError, ValueError) as error:
            raise ScenarioError(f"{at}.map: {error}") from None
        maps.append((str(path), requests))
    return tuple(maps)


def load_scenario(name_or_path: str) -> Scenario:
    """The scenario, checked whole before anything starts: every problem is a ScenarioError naming the key."""
    path = resolve(name_or_path)
    try:
        raw = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as error:
        raise ScenarioError(f"scenario {path}: not readable YAML: {error}") from None
    if not isinstance(raw, dict):
        raise ScenarioError(f"scenario {path}: expected a mapping of {', '.join(sorted(KEYS))}")
    unknown = sorted(set(raw) - KEYS)
    if unknown:
        raise ScenarioError(f"scenario {path}: unknown keys {unknown}; expected some of {sorted(KEYS)}")
    where = f"scenario {path}"
    if ("link" in raw) == ("rtt_trace" in raw):
        raise ScenarioError(f"{where}: name exactly one of link (edge or wan) and rtt_trace (a `time_s rtt_ms` file)")
    link, trace = raw.get("link", ""), None
    if "link" in raw and link not in ("edge", "wan"):
        raise ScenarioError(f"{where}: link: expected edge or wan, got {link!r}")
    if "rtt_trace" in raw:
        trace = _path(raw["rtt_trace"], f"{where}: rtt_trace", path.parent)
        try:
            LinkModel(trace=read_trace(str(trace)), loop_trace=True)
        except ValueError as error:
            raise ScenarioError(f"{where}: rtt_trace: {error}") from None
    settle, steps = raw.get("map_settle_s", 2.0), raw.get("steps", 200)
    if isinstance(settle, bool) or not isinstance(settle, (int, float)) or not (0 <= settle < 600) or math.isnan(settle):
        raise ScenarioError(f"{where}: map_settle_s: expected seconds in [0, 600), got {settle!r}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 10:
        raise ScenarioError(f"{where}: steps: expected an integer >= 10, got {steps!r}")
    description = raw.get("description", "")
    if not isinstance(description, str):
        raise ScenarioError(f"{where}: description: expected text, got {description!r}")
    return Scenario(name=path.stem, path=path, description=description.strip(), link=link, rtt_trace=trace,
                    load=_load(raw.get("load"), f"{where}: load"), maps=_maps(raw.get("maps"), f"{where}: maps",
                                                                                    path.parent),
                    map_settle_s=float(settle), steps=steps)
