"""Occupancy grids (CONTRACTS §1b): a Nav2 `map_server` map read from its YAML and image, or built from
an in-memory array (a ROS `nav_msgs/OccupancyGrid`), and the true geometry every judge measures.

A cell is *blocked* when its occupancy p ≥ `free_thresh`: occupied and unknown cells are solid squares,
`resolution` on a side. Cell (i, j) — column i, row j counted from the bottom as ROS counts them — covers
[i r, (i + 1) r] × [j r, (j + 1) r] in the grid frame, which sits at `origin` (x, y, yaw) in the world:
world = (x, y) + R(yaw) · grid. Beyond the map's extent nothing is known, so it is blocked too.
"""

from __future__ import annotations

import math
import stat
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]

# A cell's state: why it is blocked, for the errors that name it.
FREE, OCCUPIED, UNKNOWN = 0, 1, 2
STATE_NAMES = {FREE: "free", OCCUPIED: "occupied", UNKNOWN: "unknown"}
MAP_SAVER_UNKNOWN = 205  # the shade Nav2's map_saver writes for an unknown cell in trinary mode
MAX_CELLS = 1 << 24  # larger maps are refused before their image is decoded (docs/contracts.md)
MAX_YAML_BYTES = 1 << 20  # a map's YAML holds a handful of fields

MapMode = Literal["trinary", "scale", "raw"]


class MapError(ValueError):
    """A map that cannot be used; `str()` is one line naming the file, the field and the reason."""


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A grid of blocked and free square cells placed in the world.

    `state` is (rows, columns) of FREE / OCCUPIED / UNKNOWN with row 0 at the bottom (the origin's
    side), as a ROS OccupancyGrid stores it. The arrays are read-only: a grid never changes, so what
    is derived from it (the border cells, their KD-tree) is kept.
    """

    state: NDArray[np.uint8]
    resolution_m: float
    origin_x_m: float = 0.0
    origin_y_m: float = 0.0
    origin_yaw_rad: float = 0.0
    source: str = "<array>"  # the file it came from, for messages
    _rotation: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        state = np.ascontiguousarray(self.state, dtype=np.uint8)
        if state.ndim != 2 or state.shape[0] < 1 or state.shape[1] < 1:
            raise MapError(f"{self.source}: the grid must be a non-empty 2-D array, got shape {state.shape}")
        if not all(map(math.isfinite, (self.resolution_m, self.origin_x_m, self.origin_y_m, self.origin_yaw_rad))):
            raise MapError(f"{self.source}: resolution and origin must be finite")
        if not self.resolution_m > 0.0:
            raise MapError(f"{self.source}: resolution: must be positive, got {self.resolution_m}")
        state.flags.writeable = False
        object.__setattr__(self, "state", state)
        c, s = math.cos(self.origin_yaw_rad), math.sin(self.origin_yaw_rad)
        rotation = np.array([[c, -s], [s, c]])
        rotation.flags.writeable = False
        object.__setattr__(self, "_rotation", rotation)

    # ------------------------------------------------------------------ construction

    @classmethod
    def from_mask(cls, blocked: ArrayLike, *, resolution_m: float, origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  source: str = "<array>") -> OccupancyGrid:
        """A grid from a boolean array (row 0 at the bottom): True cells are occupied."""
        mask = np.asarray(blocked, dtype=bool)
        return cls(state=np.where(mask, OCCUPIED, FREE).astype(np.uint8), resolution_m=float(resolution_m),
                   origin_x_m=float(origin[0]), origin_y_m=float(origin[1]), origin_yaw_rad=float(origin[2]),
                   source=source)

    @classmethod
    def from_values(cls, values: ArrayLike, *, width: int, height: int, resolution_m: float,
                    origin: tuple[float, float, float] = (0.0, 0.0, 0.0), free_thresh: float = 0.25,
                    occupied_thresh: float = 0.65, source: str = "<OccupancyGrid>") -> OccupancyGrid:
        """A grid from `nav_msgs/OccupancyGrid` data: row-major from cell (0, 0), values 0…100 (occupancy in
        percent) or −1 (unknown). A value v is blocked when v / 100 ≥ `free_thresh`, as a map file's pixel is.
        """
        data = np.asarray(values).reshape(-1)
        if width < 1 or height < 1:
            raise MapError(f"{source}: width and height must be positive, got {width} × {height}")
        if data.size != width * height:
            raise MapError(f"{source}: data: {data.size} values for a {width} × {height} grid "
                           f"(needs {width * height})")
        _check_thresholds(free_thresh, occupied_thresh, source=source)
        v = data.astype(np.int16).reshape(height, width)
        unknown = (v < 0) | (v > 100)
        p = np.clip(v, 0, 100) / 100.0
        state = np.where(unknown | (p >= free_thresh), np.where(~unknown & (p > occupied_thresh), OCCUPIED, UNKNOWN),
                         FREE)
        return cls(state=state.astype(np.uint8), resolution_m=float(resolution_m), origin_x_m=float(origin[0]),
                   origin_y_m=float(origin[1]), origin_yaw_rad=float(origin[2]), source=source)

    # ------------------------------------------------------------------ frames

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, columns)."""
        return self.state.shape

    @cached_property
    def blocked(self) -> NDArray[np.bool_]:
        out = self.state != FREE
        out.flags.writeable = False
        return out

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the map in metres."""
        return self.shape[1] * self.resolution_m, self.shape[0] * self.resolution_m

    def to_grid(self, points: ArrayLike) -> FloatArray:
        """World points → grid-frame metres (the map's lower-left corner at 0, its rows along y)."""
        z = np.atleast_2d(np.asarray(points, dtype=float)).reshape(-1, 2)
        return (z - (self.origin_x_m, self.origin_y_m)) @ self._rotation  # Rᵀ (z − o), row by row

    def to_world(self, points: ArrayLike) -> FloatArray:
        """Grid-frame metres → world points."""
        g = np.atleast_2d(np.asarray(points, dtype=float)).reshape(-1, 2)
        return g @ self._rotation.T + (self.origin_x_m, self.origin_y_m)

    @property
    def rotation(self) -> FloatArray:
        """R(yaw): the grid frame's axes in the world, as columns."""
        return self._rotation

    def extent_corners(self) -> FloatArray:
        """The map's four corners in the world, counter-clockwise from the origin."""
        w, h = self.size_m
        return self.to_world([(0.0, 0.0), (w, 0.0), (w, h), (0.0, h)])

    def bounds(self) -> tuple[FloatArray, FloatArray]:
        """The axis-aligned box round the map's extent in the world: (min, max)."""
        corners = self.extent_corners()
        return corners.min(axis=0), corners.max(axis=0)

    def cells_of(self, points: ArrayLike) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
        """(column, row, inside the map) of the cell holding each world point."""
        g = self.to_grid(points) / self.resolution_m
        i, j = np.floor(g[:, 0]).astype(np.intp), np.floor(g[:, 1]).astype(np.intp)
        inside = (i >= 0) & (j >= 0) & (i < self.shape[1]) & (j < self.shape[0])
        return i, j, inside

    def state_at(self, points: ArrayLike) -> NDArray[np.uint8]:
        """FREE / OCCUPIED / UNKNOWN of the cell under each world point (UNKNOWN beyond the map)."""
        i, j, inside = self.cells_of(points)
        out = np.full(len(i), UNKNOWN, dtype=np.uint8)
        out[inside] = self.state[j[inside], i[inside]]
        return out

    # ------------------------------------------------------------------ border and distances

    def padded_blocked(self, rows: slice, cols: slice) -> NDArray[np.bool_]:
        """The blocked mask over rows × columns of the grid, which may run past it (beyond the map is blocked)."""
        r0, r1, c0, c1 = rows.start, rows.stop, cols.start, cols.stop
        out = np.ones((r1 - r0, c1 - c0), dtype=bool)
        a0, a1 = max(r0, 0), min(r1, self.shape[0])
        b0, b1 = max(c0, 0), min(c1, self.shape[1])
        if a0 < a1 and b0 < b1:
            out[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0] = self.blocked[a0:a1, b0:b1]
        return out

    def border_cells(self, rows: slice | None = None, cols: slice | None = None) -> NDArray[np.intp]:
        """(column, row) of every blocked cell that shares an edge or a corner with a free cell, within
        the given rows and columns (default: the map and the ring of cells just beyond it).

        A path from free space into blocked space crosses such a cell first (it enters the blocked region
        through a cell touching the free cell it leaves), so covering these cells keeps a robot that
        starts free out of every blocked cell. Cells beyond the map are blocked, so the ring round the
        map borders the free cells at its edge.
        """
        rows = rows or slice(-1, self.shape[0] + 1)
        cols = cols or slice(-1, self.shape[1] + 1)
        from scipy import ndimage  # here, not at the top: loading a scenario must not cost its import (~0.4 s)

        blocked = self.padded_blocked(slice(rows.start - 1, rows.stop + 1), slice(cols.start - 1, cols.stop + 1))
        touches_free = ndimage.maximum_filter(~blocked, size=3, mode="constant", cval=False)  # 8 neighbours
        j, i = np.nonzero((blocked & touches_free)[1:-1, 1:-1])
        return np.column_stack([i + cols.start, j + rows.start])

    @cached_property
    def _border_tree(self) -> tuple[cKDTree | None, FloatArray]:
        cells = self.border_cells()
        centres = (cells + 0.5) * self.resolution_m
        return (cKDTree(centres) if len(centres) else None), centres

    def clearance(self, points: ArrayLike) -> FloatArray:
        """Exact Euclidean distance from each world point to the nearest blocked square (0 in or beyond one).

        The nearest blocked square of a free point is a border cell (the segment to it runs through free
        cells up to the one it ends in), so the candidates are border cells, found by a KD-tree of their
        centres: a square of half-side h centred c is ‖max(|g − c| − h, 0)‖ away, at least ‖g − c‖ − h√2,
        so once the k-th nearest centre is that much further than the best square so far, no other square
        can be nearer; the few points where it is not get a ball query.
        """
        z = np.atleast_2d(np.asarray(points, dtype=float)).reshape(-1, 2)
        out = np.zeros(len(z))
        free = self.state_at(z) == FREE
        tree, centres = self._border_tree
        if tree is None or not np.any(free):
            out[free] = np.inf
            return out
        g = self.to_grid(z[free])
        half = 0.5 * self.resolution_m
        k = min(8, len(centres))
        near, index = tree.query(g, k=k)
        near, index = near.reshape(len(g), k), index.reshape(len(g), k)
        best = np.min(_square_distance(g[:, None, :], centres[index], half), axis=1)
        unsure = np.flatnonzero(near[:, -1] - half * math.sqrt(2.0) < best) if k < len(centres) else []
        for row in unsure:
            ball = tree.query_ball_point(g[row], r=best[row] + half * math.sqrt(2.0))
            best[row] = np.min(_square_distance(g[row], centres[ball], half))
        out[free] = best
        return out

    def rectangles(self, *, states: tuple[int, ...] = (OCCUPIED,)) -> list[FloatArray]:
        """The cells in `states` as few rectangles (world corners, counter-clockwise): the runs along each
        row, joined down the rows while the same run continues. For drawing, not for measuring."""
        mask = np.isin(self.state, states)
        padded = np.pad(mask, ((0, 0), (1, 1)))
        out: list[tuple[int, int, int, int]] = []  # column 0, row 0, column 1, row 1 (exclusive)
        open_runs: dict[tuple[int, int], int] = {}
        for j, row in enumerate(padded):
            edges = np.flatnonzero(np.diff(row.astype(np.int8)))
            runs = set(zip(edges[::2].tolist(), edges[1::2].tolist()))
            out += [(c0, j0, c1, j) for (c0, c1), j0 in open_runs.items() if (c0, c1) not in runs]
            open_runs = {run: open_runs.get(run, j) for run in runs}
        out += [(c0, j0, c1, self.shape[0]) for (c0, c1), j0 in open_runs.items()]
        r = self.resolution_m
        return [self.to_world(np.array([(c0, j0), (c1, j0), (c1, j1), (c0, j1)], dtype=float) * r)
                for c0, j0, c1, j1 in out]


def _square_distance(g: FloatArray, centres: FloatArray, half: float) -> FloatArray:
    """Distance from points g to axis-aligned squares of half-side `half` centred at `centres` (broadcast)."""
    d = np.maximum(np.abs(g - centres) - half, 0.0)
    return np.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)


def _check_thresholds(free_thresh: float, occupied_thresh: float, *, source: str) -> None:
    for name, value in (("free_thresh", free_thresh), ("occupied_thresh", occupied_thresh)):
        if not (isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 <= value <= 1.0):
            raise MapError(f"{source}: {name}: must be a number from 0 to 1, got {value!r}")
    if not free_thresh < occupied_thresh:
        raise MapError(f"{source}: free_thresh: must be below occupied_thresh {occupied_thresh}, got {free_thresh} "
                       "(thresholds out of order)")


# ---------------------------------------------------------------------------------------------------
# Nav2 map_server files
# ---------------------------------------------------------------------------------------------------


def _number(doc: dict, key: str, *, source: str, default: float | None = None) -> float:
    value = doc.get(key, default)
    if value is None:
        raise MapError(f"{source}: {key}: missing")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise MapError(f"{source}: {key}: must be a finite number, got {value!r}")
    return float(value)


def _irregular(path: Path, *, max_bytes: int | None) -> str | None:
    """Why `path` is not a regular file of at most `max_bytes` (a FIFO would block its reader, a device such
    as /dev/zero never end); None when it is one."""
    info = path.stat()
    if not stat.S_ISREG(info.st_mode):
        return "not a regular file (a FIFO, socket, device or directory)"
    if max_bytes is not None and info.st_size > max_bytes:
        return f"{info.st_size} bytes, more than the {max_bytes} a map's YAML may have"
    return None


def map_readers():
    """(yaml, PIL.Image, PIL.UnidentifiedImageError): the modules `load_map` reads a map with, imported
    when first asked for (a scenario without a map does not pay for them), Pillow's drivers for the common
    formats (PGM, PNG among them) loaded too. `cvxnav plan` asks before its clock starts, as it imports
    the planner: its `load` time is reading the files, not the interpreter importing (30–40 ms)."""
    import yaml
    from PIL import Image, UnidentifiedImageError

    Image.preinit()
    return yaml, Image, UnidentifiedImageError


def load_map(path: str | Path) -> OccupancyGrid:
    """Read a Nav2 `map_server` map: its YAML and the image it names (relative to the YAML).

    The pixel's shade is the mean of its colour channels over 255; its occupancy p is 1 − shade (shade
    with `negate: 1`), as map_server computes it. p > `occupied_thresh` is occupied; p < `free_thresh`
    free; anything else unknown — and so is a pixel that is not fully opaque, and in trinary mode a pixel
    of map_saver's unknown shade 205 whatever the thresholds: map_saver writes unknown cells so, and with
    Nav2's default `free_thresh: 0.25` they would otherwise load as free (205 is p = 0.196; ROS 1's
    default was 0.196, slam_toolbox issue #587). In `raw` mode a pixel v ≤ 100 is occupancy v / 100
    and a larger one unknown. Every problem is one line naming the field.
    """
    yaml, Image, UnidentifiedImageError = map_readers()
    path = Path(path)
    source = path.name
    try:
        reason = _irregular(path, max_bytes=MAX_YAML_BYTES)
        if reason is not None:
            raise MapError(f"{path}: cannot read the map file: {reason}")
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise MapError(f"{path}: no such map file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MapError(f"{path}: cannot read the map file: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        doc = yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))  # libyaml's, where PyYAML has it
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        raise MapError(f"{source}: invalid YAML{where}: {getattr(exc, 'problem', None) or exc}") from None
    if not isinstance(doc, dict):
        raise MapError(f"{source}: expected a YAML mapping of map_server fields, got {type(doc).__name__}")
    image_name = doc.get("image")
    if not isinstance(image_name, str) or not image_name:
        raise MapError(f"{source}: image: missing (the PGM or PNG file the map is drawn in)")
    resolution = _number(doc, "resolution", source=source)
    if resolution <= 0.0:
        raise MapError(f"{source}: resolution: must be positive, got {resolution}")
    origin = doc.get("origin")
    if not (isinstance(origin, (list, tuple)) and len(origin) == 3):
        raise MapError(f"{source}: origin: must be [x, y, yaw], got {origin!r}")
    ox, oy, yaw = (_number({"origin": v}, "origin", source=source) for v in origin)
    negate = doc.get("negate", 0)
    if negate not in (0, 1) or isinstance(negate, float):
        raise MapError(f"{source}: negate: must be 0 or 1, got {negate!r}")
    free_thresh = _number(doc, "free_thresh", source=source, default=0.25)
    occupied_thresh = _number(doc, "occupied_thresh", source=source, default=0.65)
    _check_thresholds(free_thresh, occupied_thresh, source=source)
    mode = doc.get("mode", "trinary")
    if mode not in ("trinary", "scale", "raw"):
        raise MapError(f"{source}: mode: must be trinary, scale or raw, got {mode!r}")

    image_path = (path.parent / image_name)
    where = f"{source}: image: {image_name}"
    try:
        reason = _irregular(image_path, max_bytes=None)  # its size is bounded by its header, below
        if reason is not None:
            raise MapError(f"{where}: {reason}")
        with Image.open(image_path) as image:
            width, height = image.size
            if width < 1 or height < 1:
                raise MapError(f"{where}: the image has no pixels ({width} × {height})")
            if width * height > MAX_CELLS:
                raise MapError(f"{where}: {width} × {height} pixels is more than the {MAX_CELLS} cells a map may have")
            image.load()
            state = _state_of_pixels(image, where=where, mode=mode, negate=bool(negate), free_thresh=free_thresh,
                                     occupied_thresh=occupied_thresh)
    except FileNotFoundError:
        raise MapError(f"{where}: no such file (looked in {image_path.parent})") from None
    except UnidentifiedImageError:
        raise MapError(f"{where}: not an image Pillow can read (PGM or PNG expected)") from None
    except OSError as exc:
        reason = str(exc)
        if "truncated" in reason:
            reason = f"truncated: the file holds fewer pixels than its header's {width} × {height} ({reason})"
        raise MapError(f"{where}: {reason}") from None
    return OccupancyGrid(state=state[::-1], resolution_m=resolution, origin_x_m=ox, origin_y_m=oy,
                         origin_yaw_rad=yaw, source=source)


def _state_of_pixels(image, *, where: str, mode: MapMode, negate: bool, free_thresh: float,
                     occupied_thresh: float) -> NDArray[np.uint8]:
    """Each pixel's FREE / OCCUPIED / UNKNOWN (image rows, top first), by a lookup table on its shade.

    The shade is the mean of the colour channels, so an 8-bit grey image has 256 shades and a colour
    one 3 · 255 + 1 channel sums: the state of every possible value is worked out once, and the image
    is one table lookup (a building-sized map is millions of pixels).
    """
    kind = image.mode
    if kind == "P":
        image = image.convert("RGBA" if "transparency" in image.info else "RGB")
        kind = image.mode
    if kind == "1":
        image, kind = image.convert("L"), "L"
    if kind in ("L", "LA"):
        a = np.asarray(image)
        value, channels, top = (a, 1, 255) if kind == "L" else (a[..., 0], 1, 255)
        opaque = None if kind == "L" else a[..., 1] == 255
    elif kind in ("RGB", "RGBA"):
        a = np.asarray(image)
        value = a[..., 0].astype(np.uint16) + a[..., 1] + a[..., 2]
        channels, top = 3, 765
        opaque = None if kind == "RGB" else a[..., 3] == 255
    elif kind.startswith("I;16") or kind == "I":
        a = np.asarray(image).astype(np.int64)
        value, channels, top = np.clip(a, 0, 65535), 257, 65535  # shade = v / 257 on 0…255
        opaque = None
    else:
        raise MapError(f"{where}: unsupported pixel format {kind!r} (8- or 16-bit grey, RGB or RGBA expected)")
    table = _occupancy_state(np.arange(top + 1) / channels, mode=mode, negate=negate, free_thresh=free_thresh,
                             occupied_thresh=occupied_thresh)
    state = table[value]
    if opaque is not None:
        state[~opaque] = UNKNOWN
    return state


def _occupancy_state(shade: FloatArray, *, mode: MapMode, negate: bool, free_thresh: float,
                     occupied_thresh: float) -> NDArray[np.uint8]:
    """The state of each shade (0…255, the mean of a pixel's colour channels), as map_server reads it."""
    if mode == "raw":
        value = np.rint(shade)
        unknown = value > 100.0
        p = np.minimum(value, 100.0) / 100.0
    else:
        p = shade / 255.0 if negate else (255.0 - shade) / 255.0
        unknown = np.zeros(shade.shape, dtype=bool)
        if mode == "trinary" and not negate:
            unknown = shade == MAP_SAVER_UNKNOWN
    occupied = ~unknown & (p > occupied_thresh)
    blocked = unknown | (p >= free_thresh)
    return np.where(occupied, OCCUPIED, np.where(blocked, UNKNOWN, FREE)).astype(np.uint8)
