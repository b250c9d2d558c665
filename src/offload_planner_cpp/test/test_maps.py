"""Map loaders: map_server YAML + PGM as map_server converts them, MovingAI text quirks, clear errors."""
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from offload_planner_cpp.maps import MapFormatError, load_map, load_map_server_yaml, load_movingai_map, \
    load_scenarios

from planner_testdata import ros_map_yamls

ROS_YAMLS = ros_map_yamls()


def write_map_server(tmp_path, pixels, **fields):
    Image.fromarray(np.asarray(pixels, dtype=np.uint8)).save(tmp_path / "m.pgm")
    meta = {"image": "m.pgm", "resolution": 0.05, "origin": "[1.5, -2.0, 0.0]", "negate": 0,
            "occupied_thresh": 0.65, "free_thresh": 0.196, **fields}
    (tmp_path / "m.yaml").write_text("".join(f"{k}: {v}\n" for k, v in meta.items()))
    return tmp_path / "m.yaml"


@pytest.mark.parametrize("yaml_file", ROS_YAMLS, ids=lambda p: p.parent.name)
def test_ros_maps_load_like_map_server(yaml_file):
    occupancy = load_map_server_yaml(yaml_file)
    import yaml
    meta = yaml.safe_load(yaml_file.read_text())
    with Image.open(yaml_file.parent / meta["image"]) as image:
        pixels = np.asarray(image.convert("L"))
    grid = occupancy.grid
    assert grid.dtype == np.int8 and grid.flags.c_contiguous
    assert grid.shape == pixels.shape
    assert set(np.unique(grid)) <= {-1, 0, 100}
    assert occupancy.resolution == pytest.approx(meta["resolution"])
    assert (occupancy.origin_x, occupancy.origin_y) == pytest.approx(tuple(meta["origin"][:2]))
    # Image row 0 is the top: it becomes the last OccupancyGrid row.
    p = (255.0 - pixels) / 255.0
    expected = np.where(p > meta["occupied_thresh"], 100, np.where(p < meta["free_thresh"], 0, -1))
    np.testing.assert_array_equal(grid, expected[::-1])
    assert (grid == 0).sum() > 1000 and (grid == 100).sum() > 100


def test_willow_walls_are_unknown_grey(shared_maps):
    grid = load_map(next((shared_maps / "ros" / "willow_garage_2010").glob("*.yaml"))).grid
    assert (grid == -1).sum() > 10 * (grid == 100).sum()


def test_thresholds_negate_modes_and_flip(tmp_path):
    # Top row: black (occupied), mid grey (unknown); bottom row: white (free), light grey (free).
    pixels = [[0, 128], [254, 220]]
    grid = load_map_server_yaml(write_map_server(tmp_path, pixels)).grid
    np.testing.assert_array_equal(grid, [[0, 0], [100, -1]])
    grid = load_map_server_yaml(write_map_server(tmp_path, pixels, negate=1)).grid
    np.testing.assert_array_equal(grid, [[100, 100], [0, -1]])
    grid = load_map_server_yaml(write_map_server(tmp_path, pixels, mode="scale")).grid
    assert grid[1, 0] == 100 and grid[0, 0] == 0 and 0 < grid[1, 1] < 100
    grid = load_map_server_yaml(write_map_server(tmp_path, pixels, mode="raw")).grid
    np.testing.assert_array_equal(grid, np.array([[254, 220], [0, 128]], dtype=np.uint8).astype(np.int8))


@pytest.mark.parametrize("fields, needle", [
    ({"resolution": 0}, "resolution"),
    ({"origin": "[1, 2]"}, "origin"),
    ({"mode": "fancy"}, "mode"),
    ({"image": "missing.pgm"}, "cannot read image"),
])
def test_map_server_errors_name_the_problem(tmp_path, fields, needle):
    with pytest.raises(MapFormatError, match=needle):
        load_map_server_yaml(write_map_server(tmp_path, [[0, 255]], **fields))


def test_map_server_rejects_garbage_yaml(tmp_path):
    (tmp_path / "g.yaml").write_text("just a string")
    with pytest.raises(MapFormatError, match="mapping"):
        load_map_server_yaml(tmp_path / "g.yaml")
    (tmp_path / "h.yaml").write_text("image: [unclosed")
    with pytest.raises(MapFormatError, match="cannot read"):
        load_map_server_yaml(tmp_path / "h.yaml")


@pytest.mark.parametrize("content", [b"\xfcimage: map.pgm\n", b"[" * 20000, b"a: " + b"{b: " * 20000],
                         ids=["not utf-8", "deep list", "deep mapping"])
def test_map_server_yaml_that_is_not_text_or_too_deep_is_a_map_format_error(tmp_path, content):
    # Found by the fuzzer (offload_demos.fuzz map_yaml): a UnicodeDecodeError escaped the loader.
    path = tmp_path / "map.yaml"
    path.write_bytes(content)
    with pytest.raises(MapFormatError, match="cannot read map YAML"):
        load_map_server_yaml(path)


def test_map_server_yaml_too_large_is_refused_unread(tmp_path):
    path = tmp_path / "map.yaml"
    with open(path, "wb") as out:
        out.truncate(64 << 20)   # sparse: 64 MiB of nothing
    with pytest.raises(MapFormatError, match="not a map_server YAML"):
        load_map_server_yaml(path)


def test_bundled_maps_load(bundled_maps):
    playpen = load_map(bundled_maps / "husky_playpen" / "playpen_map.yaml")
    assert playpen.grid.shape == (1984, 1984) and playpen.resolution == pytest.approx(0.05)
    assert (playpen.origin_x, playpen.origin_y) == (-50.0, -50.0)


def test_movingai_crlf_missing_newline_and_terrain(tmp_path):
    path = tmp_path / "t.map"
    path.write_bytes(b"type octile\r\nheight 2\r\nwidth 3\r\nmap\r\n.GS\r\n@TW")
    grid = load_movingai_map(path).grid
    np.testing.assert_array_equal(grid, [[0, 0, 0], [100, 100, 100]])


@pytest.mark.parametrize("text, needle", [
    (b"type octile\nheight 2\nwidth 3\nmap\n.GS\n@T\n", "row 1 has 2 cells"),
    (b"type octile\nheight 2\nwidth 3\nmap\n.GS\n@TX\n", "unknown terrain 'X'"),
    (b"type octile\nheight 3\nwidth 3\nmap\n.GS\n@TW\n", "3 rows, found 2"),
    (b"type octile\nwidth 3\nmap\n...\n", "height"),
    (b"type octile\nheight 1\nwidth 3\n", "no 'map' line"),
    (b"type octile\nheight 1\nwidth 3\n...\n", "unexpected header line"),
    (b"\xff\xfe binary", "cannot read as text"),
])
def test_movingai_errors_name_the_problem(tmp_path, text, needle):
    path = tmp_path / "t.map"
    path.write_bytes(text)
    with pytest.raises(MapFormatError, match=needle):
        load_movingai_map(path)


def test_scenarios_blank_lines_and_errors(tmp_path):
    path = tmp_path / "s.scen"
    path.write_text("version 1\n3\tmaps/x/t.map\t3\t2\t0\t0\t2\t1\t2.41421356\n\n")
    (scenario,) = load_scenarios(path)
    assert scenario.bucket == 3 and scenario.map_name == "t.map"
    assert scenario.start == (0, 0) and scenario.goal == (2, 1) and scenario.decimals == 8
    path.write_text("version 1\n3\tt.map\t3\t2\t0\n")
    with pytest.raises(MapFormatError, match="expected 9 fields"):
        load_scenarios(path)
    path.write_text("0\tt.map\n")
    with pytest.raises(MapFormatError, match="version"):
        load_scenarios(path)


def test_load_map_dispatches_by_extension(tmp_path):
    with pytest.raises(MapFormatError, match="expected a MovingAI"):
        load_map(tmp_path / "x.png")
