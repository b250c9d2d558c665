"""launch/config/offload.rviz reads at a glance on the demo's default map (the view shows its known area,
markers sized to it), offload_demos.rviz_view fits views correctly, and its headless mode fails clearly
when RViz shows nothing. The topics, types and frames of the displays are checked by rviz_config.test."""
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from offload_demos import rviz_view
from offload_planner_cpp.maps import OccupancyMap, load_map

WORKSPACE = Path(__file__).resolve().parents[1]


def demo_default_map() -> Path:
    launch = (WORKSPACE / "launch" / "offload_demo.launch").read_text()
    default = re.search(r'<arg name="map" default="([^"]+)"', launch).group(1)
    return Path(default.replace("$(find offload_planner_cpp)", str(WORKSPACE / "src" / "offload_planner_cpp")))


def config():
    return yaml.safe_load((WORKSPACE / "launch" / "config" / "offload.rviz").read_text())


def test_the_view_shows_the_known_area_of_the_default_map():
    known = rviz_view.known_extent_m(load_map(demo_default_map()))
    shown = rviz_view.shown_extent_m(config())
    fix = f"run: .venv/bin/python -m offload_demos.rviz_view fit --map {demo_default_map().relative_to(WORKSPACE)}"
    assert shown[0] <= known[0] and shown[1] >= known[1] and shown[2] <= known[2] and shown[3] >= known[3], \
        f"the view {shown} cuts the known area {known} off: {fix}"
    # ...and fills the window: the known area spans most of the tighter side.
    fill = max((known[1] - known[0]) / (shown[1] - shown[0]), (known[3] - known[2]) / (shown[3] - shown[2]))
    assert fill > 0.8, f"the known area fills only {fill:.0%} of the view: {fix}"


def test_markers_are_sized_to_the_known_area():
    known = rviz_view.known_extent_m(load_map(demo_default_map()))
    size_m = max(known[1] - known[0], known[3] - known[2])
    by_class = {}
    for display in rviz_view.displays(config()):
        by_class.setdefault(display["Class"], []).append(display)
    (goal,) = by_class["rviz/Pose"]
    assert goal["Shape"] == "Arrow" and 0.03 < goal["Shaft Length"] / size_m < 0.1, goal
    for path in by_class["rviz/Path"]:
        assert 0.003 < path["Line Width"] / size_m < 0.02, path


def test_fit_centres_and_scales_on_the_known_cells_only():
    grid = np.full((200, 300), -1, np.int8)
    grid[50:150, 100:140] = 0       # 40 x 100 known cells, 2 m x 5 m at 0.05 m
    occupancy = OccupancyMap(grid, 0.05, origin_x=-3.0, origin_y=1.0)
    extent = rviz_view.known_extent_m(occupancy)
    assert extent == pytest.approx((2.0, 4.0, 3.5, 8.5))
    fitted = rviz_view.fitted(config(), extent)
    view = fitted["Visualization Manager"]["Views"]["Current"]
    assert (view["X"], view["Y"]) == pytest.approx((3.0, 6.0), abs=1e-3)
    shown = rviz_view.shown_extent_m(fitted)
    # The tall area is fitted on its height, with the margin FILL leaves.
    assert (shown[3] - shown[2]) * rviz_view.FILL == pytest.approx(5.0, rel=1e-3)
    assert shown[0] < 2.0 and shown[1] > 4.0


def test_known_extent_follows_the_map_yaw():
    grid = np.zeros((10, 20), np.int8)     # 1 m x 0.5 m at 0.05 m
    turned = OccupancyMap(grid, 0.05, origin_x=1.0, origin_y=2.0, origin_yaw=math.pi / 2)
    assert rviz_view.known_extent_m(turned) == pytest.approx((0.5, 1.0, 2.0, 3.0))


def test_fit_rewrites_a_config_and_refuses_an_unknown_map(tmp_path):
    out = tmp_path / "fitted.rviz"
    done = rviz_view.main(["fit", "--map", str(WORKSPACE / "src" / "offload_planner_cpp" / "maps" / "turtlebot3_world"
                                              / "map.yaml"), "--out", str(out)])
    assert done == 0
    assert yaml.safe_load(out.read_text())["Visualization Manager"]["Views"]["Current"]["Scale"] > 100
    assert rviz_view.main(["fit", "--map", str(tmp_path / "missing.yaml"), "--out", str(out)]) == 2


@pytest.mark.skipif(shutil.which("Xvfb") is None, reason="Xvfb not installed (make demo HEADLESS=1 installs it)")
def test_headless_gives_the_command_a_screen_and_fails_when_no_rviz_window_shows(tmp_path):
    runs = tmp_path / "runs"
    # The command sees a working X display of the config's window size (RViz would draw there), but shows
    # no window: the screen stays one colour, so there is no frame to keep.
    probe = (f"import os, pathlib, time; from PIL import ImageGrab; pathlib.Path({str(runs / 'run1')!r}).mkdir(parents=True);"
             f" print('screen', ImageGrab.grab(xdisplay=os.environ['DISPLAY']).size, flush=True); time.sleep(1.5)")
    done = subprocess.run([sys.executable, "-m", "offload_demos.rviz_view", "headless", "--runs-dir",
                           str(runs), "--period-s", "0.5", "--", sys.executable, "-c", probe],
                          capture_output=True, text=True, timeout=60)
    assert "screen (1400, 900)" in done.stdout, done.stderr
    assert done.returncode == 1, done.stderr
    assert "RViz never showed a window" in done.stderr
    display = re.search(r"display (:\d+)", done.stdout).group(1)
    assert not Path(f"/tmp/.X{display[1:]}-lock").exists(), "Xvfb left running"
    assert not (runs / "run1" / "rviz.png").exists()
