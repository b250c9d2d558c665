"""RViz for the demo: a view fitted to a map's known area, and RViz without a screen.

    python -m offload_demos.rviz_view fit --map MAP [--config launch/config/offload.rviz] [--out FILE]
        sets the view (centre, scale) so the known cells of MAP fill RViz's map area, and sizes the goal
        arrow and the path lines to that area (a 0.08 m line is invisible on a 100 m map). In place by
        default: run it when the demo's default map changes (test_rviz_view.py tells).
    python -m offload_demos.rviz_view headless --runs-dir runs -- COMMAND...
        runs COMMAND (`make demo RVIZ=1 HEADLESS=1` passes the demo) with DISPLAY on a private Xvfb and
        screenshots the screen every --period-s while RViz shows a window, into rviz.png of the newest run
        directory under --runs-dir made after the start: the file holds the last frame RViz showed.
        Exits with COMMAND's status, or 1 when COMMAND succeeded but RViz never showed a window.
"""
import argparse
import math
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml
from PIL import ImageGrab

from offload_planner_cpp.maps import MapFormatError, load_map

WORKSPACE = Path(__file__).resolve().parents[4]
DEFAULT_CONFIG = WORKSPACE / "launch" / "config" / "offload.rviz"
# RViz's map area inside its window: the window minus the Displays panel on the left, the tool bar and
# the status bar (measured on a headless screenshot of the 1400 x 900 window).
PANEL_WIDTH_PX, BARS_HEIGHT_PX = 380, 95
FILL = 0.92          # share of the map area the known area spans along its tighter side
# Marker sizes as shares of the known area's larger side: about 1 m of goal arrow and 0.12 m of path line
# on the 20 m building of the default map.
ARROW_SHAFT, ARROW_HEAD, LINE_WIDTH = 0.05, 0.025, 0.006


def known_extent_m(occupancy):
    """(x_min, x_max, y_min, y_max) in the map frame of the cells that are not unknown (-1)."""
    ys, xs = np.nonzero(occupancy.grid != -1)
    if xs.size == 0:
        raise ValueError(f"{occupancy.name or 'the map'} has no known cell")
    resolution, yaw = occupancy.resolution, occupancy.origin_yaw
    corners = np.array([[xs.min(), ys.min()], [xs.max() + 1, ys.min()], [xs.min(), ys.max() + 1],
                        [xs.max() + 1, ys.max() + 1]], dtype=float) * resolution
    rotated_x = occupancy.origin_x + corners[:, 0] * math.cos(yaw) - corners[:, 1] * math.sin(yaw)
    rotated_y = occupancy.origin_y + corners[:, 0] * math.sin(yaw) + corners[:, 1] * math.cos(yaw)
    return float(rotated_x.min()), float(rotated_x.max()), float(rotated_y.min()), float(rotated_y.max())


def displays(config):
    """Every display of an RViz config, inside groups too."""
    def walk(items):
        for item in items or []:
            yield item
            yield from walk(item.get("Displays"))
    return list(walk(config["Visualization Manager"]["Displays"]))


def map_area_px(config):
    window = config["Window Geometry"]
    return window["Width"] - PANEL_WIDTH_PX, window["Height"] - BARS_HEIGHT_PX


def fitted(config, extent_m):
    """The config with its top-down view centred on `extent_m` and scaled to show it whole."""
    x_min, x_max, y_min, y_max = extent_m
    width_m, height_m = x_max - x_min, y_max - y_min
    width_px, height_px = map_area_px(config)
    view = config["Visualization Manager"]["Views"]["Current"]
    if view["Class"] != "rviz/TopDownOrtho":
        raise ValueError(f"the current view is {view['Class']}, not rviz/TopDownOrtho")
    view["X"], view["Y"] = round((x_min + x_max) / 2, 3), round((y_min + y_max) / 2, 3)
    view["Scale"] = round(FILL * min(width_px / width_m, height_px / height_m), 3)   # pixels per metre
    size_m = max(width_m, height_m)
    for display in displays(config):
        if display["Class"] == "rviz/Pose":
            display["Shaft Length"] = round(ARROW_SHAFT * size_m, 3)
            display["Shaft Radius"] = round(ARROW_SHAFT * size_m / 6, 3)
            display["Head Length"] = round(ARROW_HEAD * size_m, 3)
            display["Head Radius"] = round(ARROW_HEAD * size_m / 2, 3)
        elif display["Class"] == "rviz/Path":
            display["Line Width"] = round(LINE_WIDTH * size_m, 3)
    return config


def shown_extent_m(config):
    """(x_min, x_max, y_min, y_max) the config's view shows in its map area."""
    view = config["Visualization Manager"]["Views"]["Current"]
    width_px, height_px = map_area_px(config)
    half_w, half_h = width_px / view["Scale"] / 2, height_px / view["Scale"] / 2
    return view["X"] - half_w, view["X"] + half_w, view["Y"] - half_h, view["Y"] + half_h


def fit(args) -> int:
    try:
        extent = known_extent_m(load_map(args.map))
    except (MapFormatError, OSError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    config = fitted(yaml.safe_load(Path(args.config).read_text()), extent)
    out = Path(args.out or args.config)
    out.write_text(yaml.safe_dump(config, sort_keys=False, default_flow_style=False))
    view = config["Visualization Manager"]["Views"]["Current"]
    print(f"{out}: view centred on ({view['X']}, {view['Y']}) m at {view['Scale']} px/m, known area "
          f"{extent[1] - extent[0]:.1f} x {extent[3] - extent[2]:.1f} m")
    return 0


# --- headless -----------------------------------------------------------------------------------------
def start_xvfb(width_px: int, height_px: int, log):
    """A private Xvfb on a display number it picks itself (-displayfd): (process, ":N", pipe). In a session of
    its own, so a Ctrl-C meant for the demo does not take the screen away before the last screenshot. The
    caller closes `pipe` after stopping Xvfb: Xvfb may write the number again and dies when it cannot."""
    read_fd, write_fd = os.pipe()
    xvfb = subprocess.Popen(["Xvfb", "-displayfd", str(write_fd), "-screen", "0", f"{width_px}x{height_px}x24",
                             "-nolisten", "tcp", "-br", "-noreset"], pass_fds=(write_fd,), stdout=log, stderr=log,
                            start_new_session=True)
    os.close(write_fd)
    ready, _, _ = select.select([read_fd], [], [], 20.0)
    number = os.read(read_fd, 32).decode().split()[:1] if ready else []
    display = f":{number[0]}" if number else ""
    deadline = time.monotonic() + 20.0
    while display and xvfb.poll() is None and time.monotonic() < deadline:
        try:
            ImageGrab.grab(xdisplay=display)
            return xvfb, display, read_fd
        except OSError:
            time.sleep(0.2)
    if xvfb.poll() is None:
        xvfb.kill()
    xvfb.wait()
    os.close(read_fd)
    raise RuntimeError("Xvfb did not start or does not answer (is the Debian package xvfb installed?)")


def rviz_frame(display: str):
    """The screen, or None while it is one colour (Xvfb's black root: no RViz window up)."""
    try:
        image = ImageGrab.grab(xdisplay=display)
    except OSError:
        return None
    low, high = zip(*image.getextrema())
    return image if low != high else None


def newest_run_dir(runs_dir: Path, started: float):
    candidates = [p for p in runs_dir.glob("*") if p.is_dir() and p.stat().st_mtime >= started - 1.0]
    return max(candidates, key=lambda p: p.stat().st_mtime) if candidates else None


def headless(args) -> int:
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        print("error: give the command to run after --", file=sys.stderr)
        return 2
    config = yaml.safe_load(DEFAULT_CONFIG.read_text())
    runs_dir = Path(args.runs_dir).resolve()
    started = time.time()
    with open(os.devnull, "wb") as log:
        try:
            xvfb, display, pipe = start_xvfb(config["Window Geometry"]["Width"], config["Window Geometry"]["Height"],
                                             log)
        except (OSError, RuntimeError) as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
        print(f"rviz_view: RViz on Xvfb display {display}; screenshots every {args.period_s:g} s", flush=True)
        shots, written = 0, None
        child = subprocess.Popen(command, env=dict(os.environ, DISPLAY=display))
        # Ctrl-C reaches the demo through the terminal's process group; wait for it to finish cleanly.
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            while True:
                try:
                    status = child.wait(timeout=args.period_s)
                    break
                except subprocess.TimeoutExpired:
                    pass
                frame = rviz_frame(display)
                run_dir = newest_run_dir(runs_dir, started) if frame is not None else None
                if run_dir is not None:
                    partial = run_dir / "rviz.png.partial"
                    frame.save(partial, format="PNG")
                    os.replace(partial, run_dir / "rviz.png")
                    shots, written = shots + 1, run_dir / "rviz.png"
        finally:
            signal.signal(signal.SIGINT, previous)
            if child.poll() is None:
                child.terminate()
                child.wait()
            xvfb.terminate()
            xvfb.wait()
            os.close(pipe)
    if written is None:
        print("error: RViz never showed a window on Xvfb: no rviz.png (was the demo run with --rviz?)",
              file=sys.stderr)
        return status or 1
    print(f"rviz_view: {written} (last of {shots} screenshots)")
    return status


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    fit_parser = sub.add_parser("fit", help="fit the view and marker sizes to a map's known area")
    fit_parser.add_argument("--map", required=True, help="map_server YAML or MovingAI .map")
    fit_parser.add_argument("--config", default=str(DEFAULT_CONFIG))
    fit_parser.add_argument("--out", help="write here instead of rewriting --config")
    run_parser = sub.add_parser("headless", help="run a command with RViz on Xvfb and keep its last frame")
    run_parser.add_argument("--runs-dir", default="runs")
    run_parser.add_argument("--period-s", type=float, default=2.0)
    run_parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)
    return fit(args) if args.what == "fit" else headless(args)


if __name__ == "__main__":
    sys.exit(main())
