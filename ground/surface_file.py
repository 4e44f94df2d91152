"""A survey's final height grid on disk (`surface.npz` in a report directory), so that a later survey can
use it as its base (`--base REPORT_DIR`) and `pilescan-ground compare` can difference two surveys.

The file holds the heights the volume was computed from (after the empty-cell policy; NaN where no
surface), the grid's geometry, the building it was measured in (dimensions and, when the log had one,
the site: where the corner stands and the heading of the x axis) and what is needed to carry the survey's
own uncertainty into a difference: its volume's 90 % half-widths below and above (from its interval
terms, before the interval is clipped at 0) and the points' scatter about the surface (a cell's height
noise, for `compare`'s level of detection). Numbers live in arrays; the rest in one JSON string (no
pickles: `np.load(allow_pickle=False)`). The name, format, version and the bounded raw read are the
shared contract in `firmware_py.core.surface_file` (the coverage planner reads the file too); since version 2
it also holds the mask of the cells fitted to the points (the rest are the empty-cell policy's fill: what the
survey could not see, `plan --fill-gaps`), and a version 1 file still reads (mask unknown). This module
checks every field it uses (each number by the shared `meta_number`): a damaged or foreign file is one clear
error, never a traceback or a silently wrong base.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.cli import UserError
from firmware_py.core.surface_file import (
    FORMAT,
    FORMAT_VERSION,
    MIN_BUILDING_M,
    MIN_GRID_CELL_M,
    meta_number,
    read_surface_file,
)
from ground.site_check import HEADING_TOLERANCE_DEG, SITE_TOLERANCE_M
from ground.surface import CLIP_TOLERANCE_M, Grid

FIRST_VERSION = 1
"""The version without the fitted mask: what a surface whose fitted cells are unknown is written as."""


@dataclass(frozen=True)
class SavedSurface:
    """One survey's final surface with what a later survey needs to use it (module docstring)."""

    heights_m: np.ndarray  # (nx, ny) heights above z = 0 at the cell centres, NaN: no surface
    length_m: float
    width_m: float
    height_m: float  # the building's roof height (part of "the same building")
    cell_m: float
    volume_m3: float
    below_m3: float  # the volume's 90 % half-width below (unclipped), 0 when not estimated
    above_m3: float
    scatter_sigma_m: float  # the points' robust scatter about the surface (a cell's height noise)
    site: dict | None = None  # the log header's site record (`firmware_py.core.site.Site.to_dict`)
    source: str = ""
    software_version: str = ""
    fitted: np.ndarray | None = None  # (nx, ny) bool: heights fitted to points, not filled; None: unknown (version 1)

    @property
    def grid(self) -> Grid:
        return Grid(self.length_m, self.width_m, self.cell_m)

    def meta(self) -> dict:
        return {"format": FORMAT, "format_version": FIRST_VERSION if self.fitted is None else FORMAT_VERSION,
                "length_m": self.length_m,
                "width_m": self.width_m, "height_m": self.height_m, "cell_m": self.cell_m,
                "volume_m3": self.volume_m3, "below_m3": self.below_m3, "above_m3": self.above_m3,
                "scatter_sigma_m": self.scatter_sigma_m, "site": self.site, "source": self.source,
                "software_version": self.software_version}


def save_surface(s: SavedSurface, path: str | Path) -> Path:
    path = Path(path)
    arrays = {"heights_m": np.asarray(s.heights_m, dtype=np.float64), "meta": np.array(json.dumps(s.meta()))}
    if s.fitted is not None:
        arrays["fitted"] = np.asarray(s.fitted, dtype=bool)
    with path.open("wb") as f:
        np.savez_compressed(f, **arrays)
    return path


def load_surface(path: str | Path) -> SavedSurface:
    """Read and check a surface file; UserError (one line) on anything unusable."""
    path = Path(path)
    try:
        raw = read_surface_file(path)
        length, width, height = (meta_number(raw.meta, k, path, minimum=MIN_BUILDING_M)
                                 for k in ("length_m", "width_m", "height_m"))
        cell = meta_number(raw.meta, "cell_m", path, minimum=MIN_GRID_CELL_M)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    heights, meta = raw.heights_m, raw.meta
    try:
        grid = Grid(length, width, cell)
    except ValueError as exc:
        raise UserError(f"{path}: surface file grid is unusable: {exc}") from None
    if heights.dtype != np.float64 or heights.shape != grid.shape:
        raise UserError(f"{path}: surface file heights are {heights.dtype} {heights.shape}, not float64 "
                        f"{grid.shape} as its {length:g} x {width:g} m grid of {cell:g} m cells needs")
    if np.isinf(heights).any():
        raise UserError(f"{path}: surface file heights hold infinite values")
    # a report writes only heights inside its building (`ground.surface.clip_to_building`): others are damage, and a
    # later survey measured against them would carry it (a cell of 1e300 m made a change of -6e301 m^3)
    lo, hi = -CLIP_TOLERANCE_M, height + CLIP_TOLERANCE_M
    with np.errstate(invalid="ignore"):
        out = np.isfinite(heights) & ((heights < lo) | (heights > hi))
    if out.any():
        bad = float(heights[out][np.argmax(np.abs(heights[out]))])
        raise UserError(f"{path}: surface file has {int(out.sum())} heights outside its {height:g} m building "
                        f"({bad:g} m; a report writes {lo:g} to {hi:g} m): the file is damaged")
    site = meta.get("site")
    if site is not None and not isinstance(site, dict):
        raise UserError(f"{path}: surface file site must be an object or null")
    most = length * width * hi  # the building's whole volume bounds the volume and its interval
    try:
        volume = meta_number(meta, "volume_m3", path, minimum=-length * width * CLIP_TOLERANCE_M, maximum=most)
        below, above = (meta_number(meta, k, path, maximum=most) for k in ("below_m3", "above_m3"))
        scatter = meta_number(meta, "scatter_sigma_m", path, maximum=height)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    return SavedSurface(heights, length, width, height, cell, volume, below, above, scatter, site,
                        str(meta.get("source", ""))[:500], str(meta.get("software_version", ""))[:100], raw.fitted)


def building_mismatch(a: SavedSurface, b: SavedSurface) -> str | None:
    """Why two surfaces are not of the same building (dimensions or site differ), or None."""
    da, db = (a.length_m, a.width_m, a.height_m), (b.length_m, b.width_m, b.height_m)
    if max(abs(x - y) for x, y in zip(da, db, strict=True)) > SITE_TOLERANCE_M:
        return (f"the buildings differ: {' x '.join(f'{v:g}' for v in da)} m against "
                f"{' x '.join(f'{v:g}' for v in db)} m")
    if a.site is not None and b.site is not None:
        try:
            lat = math.radians(float(a.site["lat_deg"]))
            north = math.radians(float(a.site["lat_deg"]) - float(b.site["lat_deg"])) * 6_371_000.0
            east = math.radians(float(a.site["lon_deg"]) - float(b.site["lon_deg"])) * 6_371_000.0 * math.cos(lat)
            off = math.hypot(north, east, float(a.site["alt_m"]) - float(b.site["alt_m"]))
            turn = (float(a.site["heading_deg"]) - float(b.site["heading_deg"]) + 180.0) % 360.0 - 180.0
        except (KeyError, TypeError, ValueError):
            return None  # a malformed site was already reported by the report that wrote it
        if off > SITE_TOLERANCE_M:
            return f"the buildings' corners are {off:.2f} m apart (their sites differ)"
        if abs(turn) > HEADING_TOLERANCE_DEG:
            return f"the buildings' x axes are {abs(turn):g} deg apart (their sites differ)"
    return None


def resampled(s: SavedSurface, grid: Grid) -> np.ndarray:
    """s's heights at grid's cell centres: bilinear between s's cell centres (held at the nearest centre
    beyond the outer ones); NaN where a neighbour needed has no surface. Same geometry: the heights as they are."""
    if s.grid.shape == grid.shape and math.isclose(s.cell_m, grid.cell_m) \
            and math.isclose(s.length_m, grid.length_m) and math.isclose(s.width_m, grid.width_m):
        return s.heights_m
    from scipy import ndimage
    nx, ny = s.heights_m.shape
    cx, cy = grid.centres()
    fx = np.clip(cx / s.length_m * nx - 0.5, 0.0, nx - 1.0)
    fy = np.clip(cy / s.width_m * ny - 0.5, 0.0, ny - 1.0)
    h = ndimage.map_coordinates(np.nan_to_num(s.heights_m, nan=0.0), [fx, fy], order=1, mode="nearest")
    ok = ndimage.map_coordinates(np.isfinite(s.heights_m).astype(float), [fx, fy], order=1, mode="nearest")
    return np.where(ok > 0.999, h, np.nan)
