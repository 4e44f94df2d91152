"""Contour lines of the surface: computed with contourpy (matplotlib's own contour generator), written as
GeoJSON LineStrings (QGIS, ArcGIS, geojson.io, any GIS), and drawn on a matplotlib axes (the height map).

Levels: heights above the floor at a "nice" interval (1, 2, 2.5 or 5 x a power of ten metres), the finest
giving at most MAX_LINES levels between the floor and the highest cell, so a 12 m pile gets 1 m contours and a
0.4 m heap 2.5 cm ones: 7 to 15 levels whenever the surface rises (consecutive nice steps differ by at most
2x, so the step before the one chosen gave more than 15). The
floor itself (0 m) is no level: there the contour would trace the floor's noise. Lines run through the cell
centres, where the surface is defined; undefined (NaN) cells break them.

``contours.geojson`` is in the storage frame W (x, y metres, and the height as the third coordinate); GeoJSON
(RFC 7946) says coordinates are WGS-84 longitude/latitude, so a GIS would put this file near (0, 0): it is for
CAD-like use and the report's own map, and the file says so in a ``pilescan_frame`` member. With a site in
the log header ``contours_wgs84.geojson`` holds the same lines in longitude/latitude (degrees, 8 decimals:
about 1 mm), the altitude above mean sea level as the third coordinate, as RFC 7946 wants.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ground.exports.formats import ExportFormat, need
from ground.exports.georef import Georef
from ground.surface import Grid

MAX_LINES = 15
NICE_MANTISSAS = (1.0, 2.0, 2.5, 5.0)


@dataclass(frozen=True)
class Contour:
    """The lines of one level: each a (K, 2) array of W x, y in metres."""

    level_m: float
    lines: tuple[np.ndarray, ...]


def nice_interval_m(lo_m: float, hi_m: float, max_lines: int = MAX_LINES) -> float | None:
    """The finest nice step giving at most max_lines levels strictly between max(lo, 0) and hi (module
    docstring); None when the surface does not rise above the floor."""
    lo = max(lo_m, 0.0)
    if not (math.isfinite(lo) and math.isfinite(hi_m)) or hi_m <= lo:
        return None
    k = math.floor(math.log10((hi_m - lo) / max_lines)) - 1
    while True:
        for m in NICE_MANTISSAS:
            step = m * 10.0**k
            if len(levels_between(lo, hi_m, step)) <= max_lines:
                return step
        k += 1


def levels_between(lo_m: float, hi_m: float, step_m: float) -> np.ndarray:
    """Multiples of step strictly between lo and hi."""
    first = math.floor(lo_m / step_m) + 1
    last = math.ceil(hi_m / step_m) - 1
    return np.arange(first, last + 1) * step_m if last >= first else np.empty(0)


def contour_levels(heights: np.ndarray) -> np.ndarray:
    """The levels for a height grid (module docstring); empty when it does not rise above the floor."""
    h = np.asarray(heights, dtype=float)
    finite = h[np.isfinite(h)]
    if finite.size == 0:
        return np.empty(0)
    lo, hi = max(float(finite.min()), 0.0), float(finite.max())
    step = nice_interval_m(lo, hi)
    return np.empty(0) if step is None else levels_between(lo, hi, step)


def contour_lines(heights: np.ndarray, grid: Grid, levels: np.ndarray | None = None) -> list[Contour]:
    """The contour lines of heights[ix, iy] at levels (default `contour_levels`), through the cell centres."""
    contourpy = need("contourpy", ExportFormat.CONTOURS)
    h = np.asarray(heights, dtype=float)
    if h.shape != grid.shape:
        raise ValueError(f"heights shape {h.shape} differs from the grid's {grid.shape}")
    levels = contour_levels(h) if levels is None else np.asarray(levels, dtype=float)
    if len(levels) == 0 or min(h.shape) < 2 or np.isfinite(h).sum() < 4:
        return []
    xe, ye = grid.x_edges, grid.y_edges
    gen = contourpy.contour_generator(0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1]),
                                      np.ma.masked_invalid(h.T), line_type=contourpy.LineType.Separate)
    out = []
    for level, lines in zip(levels, gen.multi_lines(levels), strict=True):
        kept = tuple(np.asarray(line, dtype=float) for line in lines if len(line) >= 2)
        if kept:
            out.append(Contour(float(level), kept))
    return out


def split_at_antimeridian(lon: np.ndarray, lat: np.ndarray, alt: np.ndarray) -> list[list[tuple[float, float, float]]]:
    """A line's (lon, lat, alt) points cut where they cross longitude +-180, each piece ending on it (RFC 7946
    3.1.9): drawn whole, a contour of a building on the antimeridian ran once round the globe."""
    parts = [[(float(lon[0]), float(lat[0]), float(alt[0]))]]
    for i in range(1, len(lon)):
        a, b = float(lon[i - 1]), float(lon[i])
        if abs(b - a) > 180.0:
            edge = 180.0 if a > 0 else -180.0
            b_unwrapped = b + 360.0 if a > 0 else b - 360.0
            f = (edge - a) / (b_unwrapped - a)
            at_lat = float(lat[i - 1] + f * (lat[i] - lat[i - 1]))
            parts[-1].append((edge, at_lat, float(alt[i])))
            parts.append([(-edge, at_lat, float(alt[i]))])
        parts[-1].append((b, float(lat[i]), float(alt[i])))
    return parts


def contours_geojson(contours: list[Contour], georef: Georef | None = None) -> dict:
    """A GeoJSON FeatureCollection, one LineString per line (module docstring: W, or WGS-84 with georef; a line
    across the 180th meridian is a MultiLineString cut there)."""
    features = []
    for c in contours:
        for line in c.lines:
            props: dict = {"height_m": round(c.level_m, 6)}
            if georef is None:
                coords = [[round(float(x), 3), round(float(y), 3), round(c.level_m, 6)] for x, y in line]
            else:
                pts = np.column_stack([line, np.full(len(line), c.level_m)])
                lon, lat, alt = georef.w_to_lonlat_alt(pts)
                parts = [[[round(float(a), 8), round(float(b), 8), round(float(z), 3)] for a, b, z in part]
                         for part in split_at_antimeridian(lon, lat, alt)]
                props["elevation_m"] = round(float(alt[0]), 3)
                if len(parts) > 1:
                    features.append({"type": "Feature", "properties": props,
                                     "geometry": {"type": "MultiLineString", "coordinates": parts}})
                    continue
                coords = parts[0]
            features.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": coords},
                             "properties": props})
    doc: dict = {"type": "FeatureCollection", "features": features}
    levels = [c.level_m for c in contours]
    doc["pilescan_interval_m"] = round(levels[1] - levels[0], 6) if len(levels) > 1 else None
    if georef is None:
        doc["pilescan_frame"] = ("storage frame W, metres: x along the building's length, y along its width, "
                                 "third coordinate the height above the floor; not WGS-84")
    return doc


def write_contours(heights: np.ndarray, grid: Grid, out_dir: Path, names: tuple[str, str],
                   georef: Georef | None = None) -> list[Path]:
    """Write the W GeoJSON (names[0]) and, with georef, the WGS-84 one (names[1]); returns the paths."""
    contours = contour_lines(heights, grid)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = [out_dir / names[0]]
    written[0].write_text(json.dumps(contours_geojson(contours)) + "\n")
    if georef is not None:
        written.append(out_dir / names[1])
        written[1].write_text(json.dumps(contours_geojson(contours, georef)) + "\n")
    return written


def draw_contours(ax, contours: list[Contour], *, color: str = "black", linewidth: float = 0.6,
                  labels: bool = True, zorder: float = 5) -> None:
    """Draw the lines on a matplotlib axes in W metres, each level labelled once with its height, at the point
    of its lines farthest from the labels already placed."""
    from matplotlib.collections import LineCollection

    if not contours:
        return
    ax.add_collection(LineCollection([line for c in contours for line in c.lines], colors=color,
                                     linewidths=linewidth, zorder=zorder))
    if not labels:
        return
    step = contours[1].level_m - contours[0].level_m if len(contours) > 1 else contours[0].level_m
    decimals = max(0, -math.floor(math.log10(step) + 1e-9)) + (1 if round(step / 10.0**math.floor(
        math.log10(step) + 1e-9), 6) == 2.5 else 0)
    placed: list[np.ndarray] = []
    for c in contours:  # each label where it is farthest from those already placed (greedy): no pile-ups
        cand = np.vstack(c.lines)
        if placed:
            gap = np.min(np.linalg.norm(cand[:, None, :] - np.array(placed)[None, :, :], axis=2), axis=1)
            x, y = cand[int(np.argmax(gap))]
        else:
            longest = max(c.lines, key=len)
            x, y = longest[len(longest) // 2]
        placed.append(np.array([x, y]))
        ax.text(x, y, f"{c.level_m:.{decimals}f}", fontsize="x-small", color=color, ha="center", va="center",
                zorder=zorder + 0.1, bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7})
