"""An earlier survey's surface for the coverage planner (`plan --coverage PCT --surface REPORT_DIR`).

The coverage model casts beams at the empty floor, so it cannot see the floor a pile's flank hides (pile 2:
material against every wall shadows the wall's foot from legs a few metres inside). With an earlier survey's
height grid the beams stop at the first surface they meet instead. The file is the report's `surface.npz`
(written by `ground.surface_file`); the simulator must not import the ground station, so it reads the file
through the shared contract (`firmware_py.core.surface_file`: bounded, format and version checked) and checks
the fields it uses here (each number by the shared `meta_number`, as the ground does): a damaged, foreign or
other building's file is one line, never a traceback. The report's heights are after its empty-cell policy: the
cells it could not see hold a fill, not a measurement (pile 2: the fill carries the flanks' heights over the
floor strip at the walls' foot they hide). So the cells the report did not fit count as floor, as do NaN cells:
nothing measured stands there, and a floor is what a later flight must still see. Which cells were fitted the
file says since its version 2 (`fitted`); for a version 1 file they are the cells inside the convex hull of the
report's own points (`cloud.ply`, the pile points the surface was fitted to: the report's R_a, eq. 9).
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from firmware_py.core.safe_read import InputError, read_bounded
from firmware_py.core.storage import Storage
from firmware_py.core.surface_file import (
    MAX_GRID_CELLS,
    MIN_BUILDING_M,
    MIN_GRID_CELL_M,
    SURFACE_FILE,
    meta_number,
    read_surface_file,
)

CLOUD_FILE = "cloud.ply"
MAX_CLOUD_BYTES = 1_000_000_000
"""Largest cloud read: a day's survey at 500 Hz is about 40 M points of 16 bytes (ground.report's PLY)."""
BUILDING_TOLERANCE_M = 0.01
"""The survey must be of the planned building: its dimensions agree to 1 cm (the ground station's own tolerance,
`ground.site_check.SITE_TOLERANCE_M`; the SITL reads the surface file without the ground station)."""


@dataclass(frozen=True)
class HeightField:
    """Surface heights above the floor on a regular grid over [0, L] x [0, W] (cell centres)."""

    heights_m: np.ndarray = field(hash=False, compare=False)  # (nx, ny), finite, >= 0
    length_m: float
    width_m: float
    source: str = ""
    measured: np.ndarray | None = field(default=None, hash=False, compare=False)
    """(nx, ny) bool: the cells the survey fitted to its points (the rest it could not see); None: unknown."""
    site: dict | None = field(default=None, hash=False, compare=False)  # the surface file's site record, if any

    @property
    def max_height_m(self) -> float:
        return float(self.heights_m.max()) if self.heights_m.size else 0.0

    def height_at(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """The height of the cell holding each point (points outside are clamped to the border cells)."""
        nx, ny = self.heights_m.shape
        ix = np.clip((x_m * (nx / self.length_m)).astype(int), 0, nx - 1)
        iy = np.clip((y_m * (ny / self.width_m)).astype(int), 0, ny - 1)
        return self.heights_m[ix, iy]


def load_height_field(report_dir: str | Path, storage: Storage) -> HeightField:
    """The surface of the report in report_dir (or a surface.npz named directly), checked against the building
    being planned; ValueError (one line) when it is unusable."""
    path = Path(report_dir)
    if path.is_dir():
        path = path / SURFACE_FILE
    raw = read_surface_file(path)
    heights, meta = raw.heights_m, raw.meta
    length, width, height = (meta_number(meta, k, path, minimum=MIN_BUILDING_M)
                             for k in ("length_m", "width_m", "height_m"))
    cell = meta_number(meta, "cell_m", path, minimum=MIN_GRID_CELL_M)  # 1e-320 m cells overflowed the grid's shape
    if max(abs(length - storage.length_m), abs(width - storage.width_m), abs(height - storage.height_m)) \
            > BUILDING_TOLERANCE_M:
        raise ValueError(f"{path} is a survey of a {length:g} x {width:g} x {height:g} m building, not the "
                         f"{storage} one being planned")
    shape = (max(1, round(length / cell)), max(1, round(width / cell)))
    if heights.dtype != np.float64 or heights.shape != shape or shape[0] * shape[1] > MAX_GRID_CELLS:
        raise ValueError(f"{path}: surface heights are {heights.dtype} {heights.shape}, not float64 {shape} as its "
                         f"{length:g} x {width:g} m grid of {cell:g} m cells needs")
    if np.isinf(heights).any():
        raise ValueError(f"{path}: surface heights hold infinite values")
    h = np.clip(np.nan_to_num(heights, nan=0.0), 0.0, height)  # no surface: floor; nothing above the roof
    cloud = path.parent / CLOUD_FILE
    measured = raw.fitted & np.isfinite(heights) if raw.fitted is not None else \
        measured_cells(cloud, length, width, h.shape) if cloud.exists() else None
    if measured is not None:
        h = np.where(measured, h, 0.0)
    site = meta.get("site")
    return HeightField(h, length, width, str(path), measured, site if isinstance(site, dict) else None)


def cloud_points_xy(cloud_path: Path) -> np.ndarray:
    """(N, 2) the horizontal positions of the report's pile points (its `cloud.ply`), the non-finite left out;
    ValueError (one line) for an unusable cloud."""
    import trimesh
    try:
        data = read_bounded(cloud_path, MAX_CLOUD_BYTES, "point cloud")
        pts = np.asarray(trimesh.load(io.BytesIO(data), file_type="ply").vertices, dtype=float)[:, :2]
    except InputError as exc:
        raise ValueError(str(exc)) from None
    except Exception as exc:  # trimesh raises many types for a damaged PLY
        raise ValueError(f"{cloud_path} is not a readable point cloud ({type(exc).__name__}: {exc})"[:300]) from None
    pts = pts.reshape(-1, 2)
    return pts[np.isfinite(pts).all(axis=1)]


def measured_cells(cloud_path: Path, length_m: float, width_m: float, shape: tuple[int, int]) -> np.ndarray:
    """(nx, ny) True where a cell centre lies inside the convex hull of the report's pile points (where its
    surface was fitted, not filled); ValueError (one line) for an unusable cloud."""
    from scipy.spatial import ConvexHull, QhullError
    pts = cloud_points_xy(cloud_path)
    nx, ny = shape
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) * length_m / nx, (np.arange(ny) + 0.5) * width_m / ny, indexing="ij")
    try:
        eq = ConvexHull(pts).equations
    except (QhullError, ValueError):  # fewer than three points, or all on a line: nothing was measured
        return np.zeros(shape, dtype=bool)
    return np.all(eq[:, 0, None, None] * gx + eq[:, 1, None, None] * gy + eq[:, 2, None, None] <= 1e-9, axis=0)


def first_hits_w(o_w: np.ndarray, d_w: np.ndarray, field_: HeightField, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each downward beam (origin o, unit direction d, both (N, 3) in W) first meets the surface, by
    marching in steps of step_m from where the beam comes below the highest surface; (hits (N, 3), range (N,)),
    NaN for a beam that leaves the building's floor before meeting anything (it met a wall)."""
    n = len(o_w)
    hits = np.full((n, 3), np.nan)
    rng = np.full(n, np.nan)
    if n == 0:
        return hits, rng
    down = -d_w[:, 2]
    r0 = np.maximum(0.0, (o_w[:, 2] - field_.max_height_m) / down)
    r_floor = o_w[:, 2] / down
    # A beam whose path from r0 to the floor stays inside the building over cells of height 0 meets the floor: no
    # march needed. Its cells lie within the box of its two ends' cells, counted empty from a prefix sum. Over a
    # survey most beams are such (the material covers a part of the floor), and the march was the planner's time.
    clear = _floor_reached(o_w + r0[:, None] * d_w, o_w + r_floor[:, None] * d_w, field_)
    hits[clear] = o_w[clear] + r_floor[clear, None] * d_w[clear]
    rng[clear] = r_floor[clear]
    todo = np.flatnonzero(~clear)
    k = 0
    while len(todo):
        r = np.minimum(r0[todo] + k * step_m, r_floor[todo])
        p = o_w[todo] + r[:, None] * d_w[todo]
        outside = (p[:, 0] < 0) | (p[:, 0] > field_.length_m) | (p[:, 1] < 0) | (p[:, 1] > field_.width_m)
        met = ~outside & (p[:, 2] <= field_.height_at(p[:, 0], p[:, 1]) + 1e-9)
        hits[todo[met]] = p[met]
        rng[todo[met]] = r[met]
        done = met | outside | (r >= r_floor[todo])
        todo = todo[~done]
        k += 1
    return hits, rng


def _floor_reached(p0_w: np.ndarray, p1_w: np.ndarray, field_: HeightField) -> np.ndarray:
    """(N,) True where the segment p0 -> p1 (its ends inside the building) crosses no cell of non-zero height: every
    cell a straight segment crosses lies in the box spanned by its ends' cells."""
    nx, ny = field_.heights_m.shape
    inside = np.ones(len(p0_w), dtype=bool)
    for p in (p0_w, p1_w):
        inside &= (p[:, 0] >= 0) & (p[:, 0] <= field_.length_m) & (p[:, 1] >= 0) & (p[:, 1] <= field_.width_m)
    raised = np.zeros((nx + 1, ny + 1), dtype=np.int64)
    raised[1:, 1:] = np.cumsum(np.cumsum(field_.heights_m > 0, axis=0), axis=1)

    def cell(v: np.ndarray, n: int, size_m: float) -> np.ndarray:  # as HeightField.height_at clamps
        return np.clip((v * (n / size_m)).astype(int), 0, n - 1)

    ix0, ix1 = cell(p0_w[:, 0], nx, field_.length_m), cell(p1_w[:, 0], nx, field_.length_m)
    iy0, iy1 = cell(p0_w[:, 1], ny, field_.width_m), cell(p1_w[:, 1], ny, field_.width_m)
    xa, xb = np.minimum(ix0, ix1), np.maximum(ix0, ix1) + 1
    ya, yb = np.minimum(iy0, iy1), np.maximum(iy0, iy1) + 1
    count = raised[xb, yb] - raised[xa, yb] - raised[xb, ya] + raised[xa, ya]
    return inside & (count == 0)
