"""Map loading into OccupancyGrid-convention arrays: int8, indexed [y, x], -1 unknown, 0..100 occupancy.

Two sources:
- MovingAI benchmark maps (`.map`) and scenario files (`.map.scen`). (0, 0) is the upper-left cell and
  y grows downwards; cells keep those coordinates here (grid[y, x] with y the text row), so scenario
  start/goal cells index the grid directly.
- ROS map_server maps (YAML + PGM/PNG), following map_server: the image's top row is the map's highest y,
  so rows are flipped to make grid[0] the row at the origin, as in OccupancyGrid.data.

Malformed files raise MapFormatError (a ValueError) naming the file and the problem.
"""
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple

import numpy as np

FREE = 0
OCCUPIED = 100
UNKNOWN = -1

_MOVINGAI_PASSABLE = frozenset(".GS")
_MOVINGAI_BLOCKED = frozenset("@OTW")


# A map_server YAML is a few lines; anything past this is not one.
MAX_YAML_BYTES = 1 << 20


class MapFormatError(ValueError):
    """A map, scenario or map_server YAML file that cannot be read as one."""


@dataclass(frozen=True)
class OccupancyMap:
    """A grid with the metadata of nav_msgs/MapMetaData."""

    grid: np.ndarray          # int8 [y, x], C-contiguous
    resolution: float         # metres per cell
    origin_x: float = 0.0     # metres: lower-left corner of cell (0, 0)
    origin_y: float = 0.0
    origin_yaw: float = 0.0   # radians
    name: str = ""

    @property
    def width(self) -> int:
        return int(self.grid.shape[1])

    @property
    def height(self) -> int:
        return int(self.grid.shape[0])


@dataclass(frozen=True)
class Scenario:
    """One MovingAI query."""

    bucket: int
    map_name: str
    start: Tuple[int, int]    # (x, y)
    goal: Tuple[int, int]
    optimal_length: float
    decimals: int             # digits printed after the point: tells the precision of optimal_length


def _text_lines(path: Path) -> List[str]:
    try:
        text = path.read_text(encoding="ascii")
    except (OSError, UnicodeDecodeError) as error:
        raise MapFormatError(f"{path}: cannot read as text: {error}") from error
    # Street maps use CRLF and some files lack a final newline; splitlines() handles both.
    return text.splitlines()


def load_movingai_map(path) -> OccupancyMap:
    """Read a MovingAI `.map` file (header `type`, `height H`, `width W`, `map`, then H rows)."""
    path = Path(path)
    lines = _text_lines(path)
    header = {}
    row = 0
    while row < len(lines) and lines[row].strip() != "map":
        parts = lines[row].split()
        if len(parts) == 2:
            header[parts[0]] = parts[1]
        elif parts:
            raise MapFormatError(f"{path}:{row + 1}: unexpected header line {lines[row]!r}")
        row += 1
    if row == len(lines):
        raise MapFormatError(f"{path}: no 'map' line ending the header")
    try:
        height, width = int(header["height"]), int(header["width"])
    except (KeyError, ValueError) as error:
        raise MapFormatError(f"{path}: header needs integer 'height' and 'width', got {header}") from error
    if height <= 0 or width <= 0:
        raise MapFormatError(f"{path}: map size {width} x {height} is empty")
    rows = lines[row + 1:]
    while rows and not rows[-1].strip():
        rows.pop()
    if len(rows) != height:
        raise MapFormatError(f"{path}: header says {height} rows, found {len(rows)}")
    for number, text in enumerate(rows):
        if len(text) != width:
            raise MapFormatError(f"{path}: map row {number} has {len(text)} cells, expected {width}")
    chars = np.frombuffer("".join(rows).encode("ascii"), dtype=np.uint8)
    grid = np.full(chars.shape, OCCUPIED, dtype=np.int8)
    passable = np.isin(chars, np.frombuffer("".join(sorted(_MOVINGAI_PASSABLE)).encode(), np.uint8))
    known = passable | np.isin(chars, np.frombuffer("".join(sorted(_MOVINGAI_BLOCKED)).encode(), np.uint8))
    if not known.all():
        index = int(np.flatnonzero(~known)[0])
        raise MapFormatError(f"{path}: unknown terrain {chr(chars[index])!r} at x={index % width}, "
                             f"y={index // width}")
    grid[passable] = FREE
    return OccupancyMap(grid=grid.reshape(height, width), resolution=1.0, name=path.stem)


def load_scenarios(path) -> List[Scenario]:
    """Read a MovingAI `.map.scen` file (`version 1`, then tab-separated queries)."""
    path = Path(path)
    lines = _text_lines(path)
    if not lines or not lines[0].startswith("version"):
        raise MapFormatError(f"{path}: first line must be 'version 1'")
    scenarios = []
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        fields = line.split("\t") if "\t" in line else line.split()
        if len(fields) != 9:
            raise MapFormatError(f"{path}:{number}: expected 9 fields, got {len(fields)}")
        try:
            bucket, sx, sy, gx, gy = (int(fields[i]) for i in (0, 4, 5, 6, 7))
            length = float(fields[8])
        except ValueError as error:
            raise MapFormatError(f"{path}:{number}: {error}") from error
        decimals = len(fields[8].split(".")[1]) if "." in fields[8] else 0
        scenarios.append(Scenario(bucket, Path(fields[1]).name, (sx, sy), (gx, gy), length, decimals))
    return scenarios


def length_tolerance(scenario: Scenario) -> float:
    """How far an exact length may differ from the printed optimum. Street, bg512, maze and room print 8
    decimals, but were computed with sqrt(2) = 1.414213562, 3.7e-10 short per diagonal step (measured:
    the errors fit n_diagonal * 3.73e-10 within 4e-9), so the allowance grows with the length. dao and
    random print about 6 significant digits."""
    if scenario.decimals >= 8:
        return 1e-6 + 5e-10 * scenario.optimal_length
    return 0.01


def load_map_server_yaml(path) -> OccupancyMap:
    """Read a map_server map: the YAML (image, resolution, origin, negate, occupied_thresh, free_thresh,
    mode) and its image, converted exactly as map_server does."""
    import yaml
    from PIL import Image

    path = Path(path)
    try:
        if path.stat().st_size > MAX_YAML_BYTES:
            raise MapFormatError(f"{path}: a map YAML of {path.stat().st_size} bytes is not a map_server YAML "
                                 f"(at most {MAX_YAML_BYTES})")
        meta = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, RecursionError, yaml.YAMLError) as error:
        # RecursionError: PyYAML composes nested collections recursively ("[" * 10000 is a short file).
        raise MapFormatError(f"{path}: cannot read map YAML: {type(error).__name__}: {error}") from error
    if not isinstance(meta, dict):
        raise MapFormatError(f"{path}: map YAML must be a mapping")
    try:
        image_path = path.parent / str(meta["image"])
        resolution = float(meta["resolution"])
        origin = [float(v) for v in meta["origin"]]
        negate = int(meta.get("negate", 0))
        occupied_thresh = float(meta.get("occupied_thresh", 0.65))
        free_thresh = float(meta.get("free_thresh", 0.196))
    except (KeyError, TypeError, ValueError) as error:
        raise MapFormatError(f"{path}: missing or malformed field: {error}") from error
    mode = str(meta.get("mode", "trinary"))
    if len(origin) != 3 or not all(math.isfinite(v) for v in origin):
        raise MapFormatError(f"{path}: origin must be [x, y, yaw], got {meta['origin']}")
    if not (resolution > 0 and math.isfinite(resolution)):
        raise MapFormatError(f"{path}: resolution must be positive, got {resolution}")
    if mode not in ("trinary", "scale", "raw"):
        raise MapFormatError(f"{path}: unknown mode {mode!r} (trinary, scale or raw)")
    try:
        with Image.open(image_path) as image:
            has_alpha = image.mode in ("LA", "RGBA", "PA")
            pixels = np.asarray(image.convert("LA" if has_alpha else "L"))
    except OSError as error:
        raise MapFormatError(f"{path}: cannot read image {image_path}: {error}") from error
    if pixels.ndim == 3:
        value, alpha = pixels[..., 0].astype(np.float64), pixels[..., 1]
    else:
        value, alpha = pixels.astype(np.float64), None
    if pixels.shape[0] == 0 or pixels.shape[1] == 0:
        raise MapFormatError(f"{path}: image {image_path} is empty")

    if mode == "raw":
        grid = value.astype(np.int16)
    else:
        p = value / 255.0 if negate else (255.0 - value) / 255.0
        grid = np.full(p.shape, UNKNOWN, dtype=np.int16)
        grid[p > occupied_thresh] = OCCUPIED
        grid[p < free_thresh] = FREE
        if mode == "scale":
            middle = (p >= free_thresh) & (p <= occupied_thresh)
            grid[middle] = np.rint(99.0 * (p[middle] - free_thresh) / (occupied_thresh - free_thresh))
            if alpha is not None:
                grid[alpha < 255] = UNKNOWN
    # Image row 0 is the top of the map; OccupancyGrid row 0 is at the origin (bottom).
    grid = np.ascontiguousarray(grid[::-1].astype(np.int8))
    return OccupancyMap(grid=grid, resolution=resolution, origin_x=origin[0], origin_y=origin[1],
                        origin_yaw=origin[2], name=path.parent.name or path.stem)


def load_map(path) -> OccupancyMap:
    """Load a MovingAI `.map` or a map_server `.yaml` by its extension."""
    path = Path(path)
    if path.suffix in (".yaml", ".yml"):
        return load_map_server_yaml(path)
    if path.suffix == ".map":
        return load_movingai_map(path)
    raise MapFormatError(f"{path}: expected a MovingAI .map or a map_server .yaml")
