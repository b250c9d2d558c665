"""The default demo scenario is one a robot would meet: goals in the known free space of a bundled real map,
the planners and the goal generator agreeing on what free means, and a named link profile."""
import re
import xml.etree.ElementTree as ElementTree
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import yaml

from offload_cloud.bridge import BridgeConfig
from offload_planner_cpp import OPTION_DEFAULTS, free_cells
from offload_planner_cpp.maps import load_map_server_yaml
from offload_demos.driver import LINK_PROFILES
from offload_demos.goal_generator import GoalGeneratorConfig
from offload_demos.goals import GoalSampler, default_start_cell

WORKSPACE = Path(__file__).resolve().parents[1]
LAUNCH = WORKSPACE / "launch"
CONFIG = LAUNCH / "config"


def launch_defaults(name: str) -> dict:
    root = ElementTree.parse(LAUNCH / name).getroot()
    return {arg.get("name"): arg.get("default") for arg in root.iter("arg") if arg.get("default") is not None}


def default_map_path() -> Path:
    default = launch_defaults("offload_demo.launch")["map"]
    match = re.fullmatch(r"\$\(find offload_planner_cpp\)/(.+)", default)
    assert match, default
    return WORKSPACE / "src" / "offload_planner_cpp" / match.group(1)


def test_every_free_space_rule_agrees_that_unknown_cells_block():
    """The planner, the cloud bridge (the cloud planner's rule) and the goal generator read one rule: by
    default unknown cells block in all three, and the demo and robot.launch leave it alone unless told (then
    they pass one value to all three)."""
    assert OPTION_DEFAULTS["unknown_is_obstacle"] is True and BridgeConfig.unknown_is_obstacle is True
    assert GoalGeneratorConfig.unknown_is_obstacle is True
    for name in ("planner.yaml", "cloud_bridge.yaml", "goal_generator.yaml"):
        assert "unknown_is_obstacle" not in (CONFIG / name).read_text()
    assert launch_defaults("offload_demo.launch")["unknown_is_obstacle"] == ""
    assert launch_defaults("robot.launch")["unknown_is_obstacle"] == ""


def test_the_default_map_is_bundled_and_large_in_its_known_free_space():
    path = default_map_path()
    assert path.is_file(), path
    for launch in ("robot.launch", "planner.launch"):
        assert launch_defaults(launch)["map"] == launch_defaults("offload_demo.launch")["map"]
    known_free = int(free_cells(load_map_server_yaml(str(path)).grid, 50, True).sum())
    assert known_free > 1_000_000   # a full wave several times the Husky playpen's known area (149 k)


def test_the_demo_goals_lie_in_known_free_cells_of_the_default_map():
    """The goal generator's own path with the demo's values: every goal is a known cell below the lethal
    threshold. With unknown cells free (the earlier default) many goals fall in unknown space."""
    config = {**asdict(GoalGeneratorConfig()), **yaml.safe_load((CONFIG / "goal_generator.yaml").read_text())}
    grid = load_map_server_yaml(str(default_map_path())).grid

    def goals(unknown_is_obstacle: bool) -> np.ndarray:
        free = free_cells(grid, config["lethal_threshold"], unknown_is_obstacle)
        sampler = GoalSampler(free, default_start_cell(free), seed=1)
        cells = np.array([sampler.draw() for _ in range(2000)])
        return grid[cells[:, 1], cells[:, 0]]

    values = goals(config["unknown_is_obstacle"])
    assert ((values >= 0) & (values < config["lethal_threshold"])).all()
    assert (goals(False) == -1).any()


@pytest.mark.parametrize("link", LINK_PROFILES)
def test_each_named_link_profile_is_a_round_trip_trace(link):
    rows = [line.split() for line in (CONFIG / f"link_{link}.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    times = [float(row[0]) for row in rows]
    rtts = [float(row[1]) for row in rows]
    assert times[0] == 0 and times == sorted(times) and len(rows) >= 4
    assert all(0 < rtt < 1000 for rtt in rtts)
    assert launch_defaults("offload_demo.launch")["link"] in LINK_PROFILES
