"""The customer's figures: a labelled site map, a 3D view of the surface and two cross-sections.

`ground.plots` draws the engineer's figures (every point, coverage, filled cells); these answer a
customer's questions instead: where is each pile, how high, what shape. Same conventions as
`ground.plots`: explicit Agg figures (no pyplot state), the storage frame W in metres, grids indexed
[ix, iy] and transposed once when drawn.

Cost is bounded whatever the grid: the 3D view draws at most MAX_3D_CELLS_PER_SIDE quads a side
(strided, each quad the mean of its block would hide peaks, so the block's maximum is kept), and each
cross-section shows at most MAX_SECTION_POINTS points (evenly strided, not random: the figure is
reproducible).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps, patheffects
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from matplotlib.ticker import MaxNLocator
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from ground.plots import (
    DPI,
    HEIGHT_CMAP,
    _cell_mask,
    _check_grid,
    _decorate,
    _finite_xy,
    _height_mesh,
    _no_data,
    _storage_lw,
    mask_boundary_segments,
    save_png,
)

SITE_MAP, SURFACE_3D, SECTIONS = "site_map", "surface_3d", "sections"
"""The figures' names: image keys for the report writers and their PNG files' stems."""
MAP_FIGSIZE_IN = (8.0, 6.0)
VIEW_FIGSIZE_IN = (8.0, 5.5)
SECTIONS_FIGSIZE_IN = (8.0, 6.5)
_OUTLINE_EDGE = [patheffects.withStroke(linewidth=2.4, foreground="0.1")]
"""The piles' white outline on the map is drawn over a dark edge, so it reads on light and dark heights alike."""
TARGET_CONTOURS = 8
"""About this many contour lines over the height range, at a 1-2-5 step (0.5 m, 1 m, 2 m ...)."""
MAX_3D_CELLS_PER_SIDE = 80
MAX_SECTION_POINTS = 4000
MIN_SECTION_POINTS = 100
"""A section's band of points widens from one cell (doubling, up to MAX_BAND_FRACTION of the building's
shorter side) until it holds this many: a sparse survey still shows its points, a dense one a thin band."""
MAX_BAND_FRACTION = 0.05
TARGET_RELIEF_FRACTION = 0.25
"""The 3D view and the sections exaggerate heights (by a 1-2-5 factor, never below 1) until the peak is
about this fraction of the building's longer side: a 3 m pile on a 60 m floor is otherwise a smear."""
_HALO = [patheffects.withStroke(linewidth=3, foreground="white")]


def nice_step(span: float, target: int) -> float:
    """The 1-2-5 step (…, 0.5, 1, 2, 5, 10, …) giving about `target` intervals over `span` (> 0)."""
    if not (math.isfinite(span) and span > 0):
        return 1.0
    raw = span / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    return next(m * mag for m in (1.0, 2.0, 5.0, 10.0) if m * mag >= raw * 0.999)


def contour_levels(heights: np.ndarray, target: int = TARGET_CONTOURS) -> np.ndarray:
    """Contour heights at a 1-2-5 step, from the first step above the floor (or the lowest height) to the
    highest: a line at the floor itself would trace its noise."""
    h = np.asarray(heights, float)
    h = h[np.isfinite(h)]
    if h.size == 0 or float(h.max()) <= float(h.min()):
        return np.empty(0)
    step = nice_step(float(h.max() - max(float(h.min()), 0.0)), target)
    first = math.floor(max(float(h.min()), 0.0) / step) * step + step  # none at the floor: its noise would draw
    return np.arange(first, float(h.max()), step)


def vertical_exaggeration(peak_m: float, storage_lw_m: tuple[float, float]) -> float:
    """The 1-2-5 factor (>= 1) that makes the peak about TARGET_RELIEF_FRACTION of the longer side."""
    if not (math.isfinite(peak_m) and peak_m > 0):
        return 1.0
    want = TARGET_RELIEF_FRACTION * max(storage_lw_m) / peak_m
    if want <= 1.0:
        return 1.0
    mag = 10.0 ** math.floor(math.log10(want))
    return max(m * mag for m in (1.0, 2.0, 5.0) if m * mag <= want * 1.0001)


def north_in_frame(heading_deg: float) -> tuple[float, float]:
    """True north as a unit vector in W: its x axis points `heading_deg` clockwise from north and its y
    axis 90 deg to the x axis' left (firmware_py.core.site), so north = (cos h, sin h)."""
    h = math.radians(heading_deg)
    return math.cos(h), math.sin(h)


def _cell_centres(edges: np.ndarray) -> np.ndarray:
    return 0.5 * (edges[:-1] + edges[1:])


def _pile_records(piles: Mapping[str, Any] | None) -> list[Mapping[str, Any]]:
    recs = piles.get("piles") if isinstance(piles, Mapping) else None
    return [p for p in recs or [] if isinstance(p, Mapping)]


def _north_arrow(ax: Axes, heading_deg: float) -> None:
    """A compass in the axes' top-left corner, in an equal-aspect inset so the arrow's angle is true."""
    nx, ny = north_in_frame(heading_deg)
    c = ax.inset_axes((0.005, 0.80, 0.11, 0.19), zorder=12)
    c.set_xlim(-1.15, 1.15)
    c.set_ylim(-1.15, 1.15)
    c.set_aspect("equal")
    c.axis("off")
    c.add_patch(Circle((0, 0), 1.1, facecolor="white", edgecolor="0.4", alpha=0.85, linewidth=0.8))
    c.annotate("", xy=(0.62 * nx, 0.62 * ny), xytext=(-0.62 * nx, -0.62 * ny),
               arrowprops={"arrowstyle": "-|>", "color": "black", "linewidth": 1.5, "mutation_scale": 14})
    c.text(0.95 * nx, 0.95 * ny, "N", ha="center", va="center", fontsize=10, fontweight="bold")


def _label_xy(ax: Axes, x: float, y: float, length_m: float, compass: bool) -> tuple[float, float, str, str]:
    """Where a pile's label goes: at (x, y), unless that is under the scale bar (lower left) or the compass (upper
    left), which are drawn over the map; then just above the bar or right of the compass. With its alignment."""
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    fx, fy = (x - x0) / (x1 - x0), (y - y0) / (y1 - y0)
    bar_fx = (nice_step(length_m, 5) + 0.06 * length_m) / (x1 - x0)  # the bar, its padding and frame
    if fx < bar_fx and fy < 0.13:
        return x, y0 + 0.14 * (y1 - y0), "center", "bottom"
    if compass and fx < 0.13 and fy > 0.78:
        return x0 + 0.14 * (x1 - x0), y, "left", "center"
    return x, y, "center", "center"


def _scale_bar(ax: Axes, length_m: float) -> None:
    bar = nice_step(length_m, 5)
    ax.add_artist(AnchoredSizeBar(ax.transData, bar, f"{bar:g} m", "lower left", pad=0.4, borderpad=0.6,
                                  sep=3, frameon=True, size_vertical=0.004 * length_m, zorder=12))


# ----------------------------------------------------------------------------------------------- map


def site_map_figure(x_edges: np.ndarray, y_edges: np.ndarray, heights: np.ndarray,
                    storage_lw_m: tuple[float, float], piles: Mapping[str, Any] | None = None,
                    heading_deg: float | None = None, path_w: np.ndarray | None = None,
                    volume_unit: str = "m³", m3_per_unit: float = 1.0, title: str = "Site map",
                    filled: np.ndarray | None = None, pile_labels: np.ndarray | None = None) -> Figure:
    """Height map with contour lines, each pile's name and volume at its centroid, the building's outline,
    a scale bar, metres on the axes, a north arrow when the heading is known, the flight path and the outline of
    the cells the empty-cell policy filled (`filled`: never seen; legend under the map, clear of the ground)."""
    storage = _storage_lw(storage_lw_m)
    xe, ye = np.asarray(x_edges, float), np.asarray(y_edges, float)
    h = np.asarray(heights, float)
    fig = Figure(figsize=MAP_FIGSIZE_IN, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    _decorate(ax, storage)
    finite = np.isfinite(h)
    if h.size == 0 or not finite.any():
        _no_data(ax)
    else:
        _check_grid(xe, ye, h, "heights")
        _height_mesh(fig, ax, xe, ye, h, finite)
        levels = contour_levels(h)
        if levels.size:
            cs = ax.contour(_cell_centres(xe), _cell_centres(ye), np.ma.masked_invalid(h).T, levels=levels,
                            colors="black", linewidths=0.6, alpha=0.75, zorder=3)
            ax.clabel(cs, levels[:: max(1, len(levels) // 4)], fmt=lambda v: f"{v:g} m", fontsize=7, inline=True)
            title += f"\ncontours every {levels[1] - levels[0] if levels.size > 1 else levels[0]:g} m above the floor"
    compass = heading_deg is not None and math.isfinite(heading_deg)  # drawn last, over the map
    for p in _pile_records(piles):
        cxy = p.get("centroid_xy_m")
        v = p.get("volume_m3")
        if not (isinstance(cxy, Sequence) and len(cxy) == 2):
            continue
        shown = v / m3_per_unit if isinstance(v, int | float) else None
        text = str(p.get("label", "?")) + ("" if shown is None else
                                           f"\n{shown:,.{0 if abs(shown) >= 100 else 1}f} {volume_unit}")
        lx, ly, ha, va = _label_xy(ax, float(cxy[0]), float(cxy[1]), storage[0], compass)
        ax.text(lx, ly, text, ha=ha, va=va, fontsize=9, fontweight="bold", path_effects=_HALO, zorder=13)
    path = _finite_xy(path_w, 2)
    if path.shape[0] > 0:
        ax.plot(path[:, 0], path[:, 1], color="0.15", linewidth=0.5, alpha=0.6, zorder=4, label="flight path")
    f = _cell_mask(filled, h) & np.isfinite(h)
    if f.any():  # outlined, not hatched: the map's colours and contours stay readable under it
        ax.add_collection(LineCollection(mask_boundary_segments(xe, ye, f), colors="tab:red", linewidths=1.0,
                                         linestyles=(0, (3, 2)), zorder=5, label="filled: never seen"))
    outlined = False
    if pile_labels is not None:  # each pile's cells as the table sums them, toe included
        labels = np.asarray(pile_labels)
        if labels.shape != h.shape:
            raise ValueError(f"pile_labels shape {labels.shape} differs from heights shape {h.shape}")
        segs = [mask_boundary_segments(xe, ye, labels == k) for k in range(1, int(labels.max(initial=0)) + 1)]
        segs = [sg for sg in segs if len(sg)]
        if segs:
            ax.add_collection(LineCollection(np.concatenate(segs), colors="white", linewidths=1.0, zorder=6,
                                             path_effects=_OUTLINE_EDGE,
                                             label="pile outline (the cells its volume sums)"))
            outlined = True
    # The legend goes under the map in one row (the constrained layout makes room): inside, it hid the ground it names.
    if path.shape[0] > 0 or f.any() or outlined:
        handles, names = ax.get_legend_handles_labels()
        leg = fig.legend(handles, names, loc="outside lower center", ncols=len(handles), fontsize="small",
                         frameon=False)
        for handle, name in zip(leg.legend_handles, names, strict=True):
            if name.startswith("pile outline"):  # white as on the map, with its dark edge, or it is lost on the page
                handle.set_path_effects(_OUTLINE_EDGE)
    _scale_bar(ax, storage[0])
    if compass:
        _north_arrow(ax, heading_deg)
        title += f"; building's x axis {heading_deg:g}° from north"
    ax.set_title(title)
    return fig


# ------------------------------------------------------------------------------------------- 3D view


def _block_max(h: np.ndarray, max_side: int) -> tuple[np.ndarray, int, int]:
    """Coarsen h[ix, iy] by whole blocks to at most max_side a side, keeping each block's highest value."""
    nx, ny = h.shape
    sx, sy = max(1, math.ceil(nx / max_side)), max(1, math.ceil(ny / max_side))
    px, py = (-nx) % sx, (-ny) % sy
    padded = np.pad(h, ((0, px), (0, py)), constant_values=np.nan)
    blocks = padded.reshape(padded.shape[0] // sx, sx, padded.shape[1] // sy, sy)
    with np.errstate(all="ignore"):
        finite = np.isfinite(blocks).any(axis=(1, 3))
        out = np.where(finite, np.nanmax(np.where(np.isfinite(blocks), blocks, -np.inf), axis=(1, 3)), np.nan)
    return out, sx, sy


def surface_3d_figure(x_edges: np.ndarray, y_edges: np.ndarray, heights: np.ndarray,
                      storage_lw_m: tuple[float, float], title: str = "3D view of the surface") -> Figure:
    """The height grid as a shaded 3D surface seen from the south-west corner of the frame (30° up), heights
    exaggerated by `vertical_exaggeration` (said in the title); cells without a surface are left out."""
    storage = _storage_lw(storage_lw_m)
    xe, ye = np.asarray(x_edges, float), np.asarray(y_edges, float)
    h = np.asarray(heights, float)
    fig = Figure(figsize=VIEW_FIGSIZE_IN, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    finite = np.isfinite(h)
    if h.ndim != 2 or h.size == 0 or not finite.any():
        ax.text2D(0.5, 0.5, "no data", transform=ax.transAxes, ha="center", va="center", fontsize=16, color="0.35")
        ax.set_title(title)
        return fig
    _check_grid(xe, ye, h, "heights")
    coarse, sx, sy = _block_max(h, MAX_3D_CELLS_PER_SIDE)
    xc = _cell_centres(xe)[::sx][: coarse.shape[0]]
    yc = _cell_centres(ye)[::sy][: coarse.shape[1]]
    peak = float(np.nanmax(coarse))
    ve = vertical_exaggeration(peak, storage)
    lo = min(0.0, float(np.nanmin(coarse)))
    norm = Normalize(vmin=lo, vmax=peak if peak > lo else lo + 1.0)
    X, Y = np.meshgrid(xc, yc, indexing="ij")
    colors = colormaps[HEIGHT_CMAP](norm(np.nan_to_num(coarse, nan=lo)))
    ax.plot_surface(X, Y, np.ma.masked_invalid(coarse), facecolors=colors, rstride=1, cstride=1, linewidth=0,
                    antialiased=False, shade=True)
    L, W = storage
    ax.plot([0, L, L, 0, 0], [0, 0, W, W, 0], [0, 0, 0, 0, 0], color="0.3", linewidth=0.8)
    ax.set_xlim(0, L)
    ax.set_ylim(0, W)
    ax.set_zlim(lo, max(peak, lo + 1e-6))
    ax.set_box_aspect((L, W, max(peak - lo, 1e-3) * ve))
    ax.set_zticks(height_ticks(lo, peak, (peak - lo) * ve / max(L, W)))
    ax.view_init(elev=30, azim=-60)
    ax.xaxis.labelpad = 8  # clear of the tick labels under it
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    ax.set_title(f"{title}\nvertical exaggeration ×{ve:g}" + (
        f"; drawn at {sx * (xe[1] - xe[0]):.2g} m cells (highest kept)" if max(sx, sy) > 1 else ""))
    return fig


def height_ticks(lo_m: float, peak_m: float, drawn_fraction: float) -> list[float]:
    """The 3D view's height ticks: as many as the height axis, drawn at drawn_fraction of the longer side, has room
    for at the horizontal axes' spacing (about X_TICKS_PER_SIDE on a side), at least the floor and one above it, so
    the labels of a low relief do not print over each other; the floor alone for a flat surface (an empty building)."""
    if not peak_m > lo_m + FLAT_RELIEF_M:
        return [round(lo_m, 2)]
    n = max(1, min(X_TICKS_PER_SIDE, int(X_TICKS_PER_SIDE * drawn_fraction)))
    ticks = [float(t) for t in MaxNLocator(nbins=n, steps=[1, 2, 2.5, 5, 10]).tick_values(lo_m, peak_m)
             if lo_m - 1e-9 <= t <= peak_m + 1e-9]
    if len(ticks) < 2:
        ticks = sorted({round(lo_m, 1), float(np.floor(peak_m * 10.0) / 10.0)})
    return ticks


FLAT_RELIEF_M = 0.01
"""A relief under this (a centimetre: the rangefinder's quantum) is drawn as flat: one height label."""
X_TICKS_PER_SIDE = 6
"""About how many labelled ticks the 3D view's longer horizontal axis carries (matplotlib's default for its size)."""


# ------------------------------------------------------------------------------------- cross-sections


def section_centre(piles: Mapping[str, Any] | None, heights: np.ndarray, x_edges: np.ndarray,
                   y_edges: np.ndarray) -> tuple[float, float, str]:
    """Where the sections cross: the largest pile's peak (by volume), else the highest cell; and its name."""
    recs = [p for p in _pile_records(piles) if isinstance(p.get("volume_m3"), int | float)
            and isinstance(p.get("peak_xy_m"), Sequence) and len(p["peak_xy_m"]) == 2]
    if recs:
        big = max(recs, key=lambda p: p["volume_m3"])
        return float(big["peak_xy_m"][0]), float(big["peak_xy_m"][1]), f"pile {big.get('label', '?')}'s peak"
    h = np.asarray(heights, float)
    if h.size == 0 or not np.isfinite(h).any():
        return float(np.mean(x_edges[[0, -1]])), float(np.mean(y_edges[[0, -1]])), "the building's centre"
    ix, iy = np.unravel_index(int(np.nanargmax(h)), h.shape)
    return float(_cell_centres(x_edges)[ix]), float(_cell_centres(y_edges)[iy]), "the highest cell"


def section_band_m(points_w: np.ndarray, x0: float, y0: float, cell_m: float, shorter_side_m: float) -> float:
    """Half-width of the sections' band of points: one cell, doubled until both lines hold MIN_SECTION_POINTS
    points or the band reaches MAX_BAND_FRACTION of the shorter side."""
    band, limit = cell_m, max(cell_m, MAX_BAND_FRACTION * shorter_side_m)
    while band < limit:
        n = min(int((np.abs(points_w[:, 1] - y0) <= band).sum()), int((np.abs(points_w[:, 0] - x0) <= band).sum()))
        if n >= MIN_SECTION_POINTS:
            break
        band = min(2 * band, limit)
    return band


def _profile(ax: Axes, along: np.ndarray, surface: np.ndarray, base: np.ndarray, pts_along: np.ndarray,
             pts_z: np.ndarray, ve: float, axis: str, where: str, filled: np.ndarray) -> None:
    ax.plot(along, np.where(filled, np.nan, surface), color="tab:blue", linewidth=1.4, label="surface", zorder=3)
    if filled.any():  # the fill's stretches, joined to the seen ones at their ends: dashed, as not measured
        ends = filled | np.convolve(filled.astype(float), np.ones(3), mode="same").astype(bool)
        ax.plot(along, np.where(ends, surface, np.nan), color="tab:blue", linewidth=1.2, linestyle=(0, (4, 2)),
                label="surface, filled (never seen)", zorder=3)
    ax.plot(along, base, color="tab:brown", linewidth=1.2, linestyle="--", label="base", zorder=2)
    ax.fill_between(along, base, surface, where=np.isfinite(surface) & (surface > base), color="tab:blue",
                    alpha=0.15, linewidth=0, zorder=1)
    if pts_along.size:
        ax.scatter(pts_along, pts_z, s=5, color="tab:red", linewidths=0, alpha=0.6, label="LiDAR points near the line",
                   zorder=4, rasterized=True)
    ax.set_aspect(ve, adjustable="datalim")
    ax.set_xlabel(f"{axis} [m]")
    ax.set_ylabel("z [m]")
    ax.set_title(where, fontsize="medium")
    ax.grid(True, linewidth=0.4, alpha=0.5)
    ax.legend(loc="best", fontsize="x-small", framealpha=0.85)  # where it hides least of the profile


def sections_figure(x_edges: np.ndarray, y_edges: np.ndarray, heights: np.ndarray,
                    storage_lw_m: tuple[float, float], points_w: np.ndarray | None = None,
                    base_heights: np.ndarray | None = None, piles: Mapping[str, Any] | None = None,
                    band_m: float | None = None, title: str = "Cross-sections",
                    filled: np.ndarray | None = None) -> Figure:
    """Two profiles through the largest pile's peak, along x and along y: the fitted surface (dashed where the
    empty-cell policy filled cells no surface reached: `filled`), the base (z = 0 unless given per cell) and the
    LiDAR points within `band_m` of the line (default: section_band_m), heights exaggerated as in the 3D view."""
    storage = _storage_lw(storage_lw_m)
    xe, ye = np.asarray(x_edges, float), np.asarray(y_edges, float)
    h = np.asarray(heights, float)
    fig = Figure(figsize=SECTIONS_FIGSIZE_IN, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax_x, ax_y = fig.subplots(2, 1)
    if h.ndim != 2 or h.size == 0 or not np.isfinite(h).any():
        for ax in (ax_x, ax_y):
            _no_data(ax)
        fig.suptitle(title)
        return fig
    _check_grid(xe, ye, h, "heights")
    b = np.zeros_like(h) if base_heights is None else np.asarray(base_heights, float)
    if b.shape != h.shape:
        raise ValueError(f"base_heights shape {b.shape} differs from heights shape {h.shape}")
    x0, y0, what = section_centre(piles, h, xe, ye)
    ix = int(np.clip(np.searchsorted(xe, x0) - 1, 0, h.shape[0] - 1))
    iy = int(np.clip(np.searchsorted(ye, y0) - 1, 0, h.shape[1] - 1))
    pts = _finite_xy(points_w, 3)
    band = section_band_m(pts, x0, y0, float(min(xe[1] - xe[0], ye[1] - ye[0])), min(storage)) \
        if band_m is None else float(band_m)
    f = _cell_mask(filled, h)
    ve = vertical_exaggeration(float(np.nanmax(h)), storage)
    for ax, axis, along, surf, base, fill, sel, coord, fixed in (
            (ax_x, "x", _cell_centres(xe), h[:, iy], b[:, iy], f[:, iy], np.abs(pts[:, 1] - y0) <= band, 0,
             f"y = {y0:.1f} m"),
            (ax_y, "y", _cell_centres(ye), h[ix, :], b[ix, :], f[ix, :], np.abs(pts[:, 0] - x0) <= band, 1,
             f"x = {x0:.1f} m")):
        near = pts[sel]
        near = near[:: max(1, math.ceil(len(near) / MAX_SECTION_POINTS))]
        _profile(ax, along, surf, base, near[:, coord], near[:, 2], ve, axis,
                 f"along {axis} at {fixed} (through {what}); points within {band:.2g} m", fill)
    fig.suptitle(f"{title}: vertical exaggeration ×{ve:g}")
    return fig


# ----------------------------------------------------------------------------------------- PNG writers


def plot_site_map(out_png: str | Path, *args: Any, **kwargs: Any) -> Path:
    return save_png(site_map_figure(*args, **kwargs), out_png)


def plot_surface_3d(out_png: str | Path, *args: Any, **kwargs: Any) -> Path:
    return save_png(surface_3d_figure(*args, **kwargs), out_png)


def plot_sections(out_png: str | Path, *args: Any, **kwargs: Any) -> Path:
    return save_png(sections_figure(*args, **kwargs), out_png)
