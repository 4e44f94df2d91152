"""Report figures: point-cloud top view, fitted height map and coverage map.

Figures are built on `matplotlib.figure.Figure` with an explicit Agg canvas instead of pyplot: no
global state, so it is thread-safe and needs no display, and it is faster. Each `plot_*` writes one
PNG and returns its path; each has a `*_figure` twin that returns the Figure so tests (and callers
that want another format) can inspect exactly what was drawn.

Coordinates are the storage frame W: x along the length L, y along the width W, z up, metres.
Grids are indexed [ix, iy] (x first), matching `np.histogram2d`; matplotlib wants [row=y, col=x],
so every grid is transposed exactly once, in `_grid_mesh`.

Blind spots are the point of these plots, so nothing is interpolated or smoothed: empty cells and
pixels stay white.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.collections import LineCollection
from matplotlib.colors import ListedColormap, LogNorm, Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Rectangle
from matplotlib.ticker import FuncFormatter, LogFormatter

from firmware_py.core.surface_file import SEEN_RADIUS_M
from ground.exports.contours import Contour, draw_contours

DPI = 110
FIGSIZE_IN = (8.0, 5.5)
HEIGHT_CMAP = "viridis"
COVERAGE_CMAP = "plasma"
HEIGHT_LABEL = "height above floor [m]"

SCATTER_MAX_POINTS = 200_000
"""Above this the top view bins points to screen pixels (highest point wins) instead of drawing
markers: every point still counts, but drawing 1M markers takes seconds for no visible gain."""

_MARGIN_FRAC = 0.04
_MAX_OVERHANG_FRAC = 0.5
"""Data outside the building widens the view by at most this fraction of L or W, so that a single
wild return does not shrink the storage to a dot."""

BRIDGED_GREY = "0.78"
"""The coverage figure's bridged cells (`ground.surface.bridged_cells`): a grey the points' colour map never takes."""
_LEGEND_BELOW = {"loc": "upper right", "bbox_to_anchor": (1.0, -0.07), "fontsize": "small", "frameon": False}
"""Legends of the engineer's grids go under the axes, right of the x label: inside they would hide data."""
_LEGEND_INSIDE = {"loc": "upper right", "fontsize": "small", "framealpha": 0.85}
"""The flight path's legend sits inside the axes, over the wall margin, where a reader looks for it."""

# --------------------------------------------------------------------------------------------- helpers


def _new_figure() -> tuple[Figure, Axes]:
    fig = Figure(figsize=FIGSIZE_IN, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    return fig, ax


def save_png(fig: Figure, out_png: str | Path) -> Path:
    """Write `fig` as PNG at the module DPI (no tight bbox: pixel positions stay predictable)."""
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=DPI, format="png")
    return out


def _storage_lw(storage_lw_m: tuple[float, float]) -> tuple[float, float]:
    try:
        length, width = (float(v) for v in storage_lw_m)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"storage_lw_m must be (length, width) in metres, got {storage_lw_m!r}") from exc
    if not (np.isfinite(length) and np.isfinite(width) and length > 0 and width > 0):
        raise ValueError(f"storage dimensions must be finite and positive, got {storage_lw_m!r}")
    return length, width


def _decorate(ax: Axes, storage_lw_m: tuple[float, float], extra_xy: list[np.ndarray] | None = None) -> None:
    """Storage outline, axis labels, equal aspect and limits covering the building (+ nearby data)."""
    length, width = storage_lw_m
    ax.add_patch(
        Rectangle((0.0, 0.0), length, width, fill=False, edgecolor="0.25", linewidth=1.2, zorder=5)
    )
    x_lo, x_hi, y_lo, y_hi = 0.0, length, 0.0, width
    for xy in extra_xy or []:
        if xy.size == 0:
            continue
        x_lo = min(x_lo, max(float(xy[:, 0].min()), -_MAX_OVERHANG_FRAC * length))
        x_hi = max(x_hi, min(float(xy[:, 0].max()), (1 + _MAX_OVERHANG_FRAC) * length))
        y_lo = min(y_lo, max(float(xy[:, 1].min()), -_MAX_OVERHANG_FRAC * width))
        y_hi = max(y_hi, min(float(xy[:, 1].max()), (1 + _MAX_OVERHANG_FRAC) * width))
    mx = _MARGIN_FRAC * (x_hi - x_lo)
    my = _MARGIN_FRAC * (y_hi - y_lo)
    ax.set_xlim(x_lo - mx, x_hi + mx)
    ax.set_ylim(y_lo - my, y_hi + my)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def _colorbar(fig: Figure, ax: Axes, mappable, label: str):
    """Colourbar in an inset hugging the axes, so it is exactly as tall as the equal-aspect plot."""
    return fig.colorbar(mappable, cax=ax.inset_axes((1.025, 0.0, 0.025, 1.0)), label=label)


def _no_data(ax: Axes, what: str = "no data") -> None:
    ax.text(
        0.5, 0.5, what, transform=ax.transAxes, ha="center", va="center",
        fontsize=16, color="0.35", zorder=10,
    )


def _cell_mask(mask: np.ndarray | None, heights: np.ndarray, name: str = "filled") -> np.ndarray:
    """mask as booleans per cell of heights (none set when None); ValueError naming it when its shape differs."""
    m = np.zeros(heights.shape, bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != heights.shape:
        raise ValueError(f"{name} shape {m.shape} differs from heights shape {heights.shape}")
    return m


def _check_grid(x_edges: np.ndarray, y_edges: np.ndarray, grid: np.ndarray, name: str) -> None:
    if grid.ndim != 2:
        raise ValueError(f"{name} must be 2-D (nx, ny), got shape {grid.shape}")
    nx, ny = grid.shape
    if x_edges.shape != (nx + 1,) or y_edges.shape != (ny + 1,):
        raise ValueError(
            f"{name} shape {grid.shape} needs x_edges ({nx + 1},) and y_edges ({ny + 1},), "
            f"got {x_edges.shape} and {y_edges.shape}"
        )


def _grid_mesh(ax: Axes, x_edges: np.ndarray, y_edges: np.ndarray, grid_xy: np.ndarray, **kwargs):
    """pcolormesh of a grid indexed [ix, iy]: the single place where the transpose happens."""
    return ax.pcolormesh(x_edges, y_edges, grid_xy.T, shading="flat", rasterized=True, **kwargs)


def _height_mesh(fig: Figure, ax: Axes, x_edges: np.ndarray, y_edges: np.ndarray, h: np.ndarray,
                 finite: np.ndarray):
    """The surface heights h[ix, iy] coloured over their own range (NaN white) with the height colour bar:
    one look for every height map of a report."""
    lo, hi = float(h[finite].min()), float(h[finite].max())
    norm = Normalize(vmin=lo, vmax=hi) if hi > lo else Normalize(vmin=lo - 0.5, vmax=hi + 0.5)
    cmap = colormaps[HEIGHT_CMAP].with_extremes(bad="white")
    mesh = _grid_mesh(ax, x_edges, y_edges, np.ma.masked_invalid(h), cmap=cmap, norm=norm, zorder=2)
    _colorbar(fig, ax, mesh, HEIGHT_LABEL)
    return mesh


def _grid_corners(x_edges: np.ndarray, y_edges: np.ndarray) -> np.ndarray:
    """(K, 2) extreme corners of a grid, so a grid larger than the building stays in view."""
    if x_edges.size == 0 or y_edges.size == 0:
        return np.empty((0, 2))
    xs = x_edges[np.isfinite(x_edges)]
    ys = y_edges[np.isfinite(y_edges)]
    if xs.size == 0 or ys.size == 0:
        return np.empty((0, 2))
    return np.array([[xs.min(), ys.min()], [xs.max(), ys.max()]])


def _finite_xy(arr: np.ndarray | None, min_cols: int) -> np.ndarray:
    if arr is None:
        return np.empty((0, min_cols))
    a = np.asarray(arr, dtype=float)
    if a.size == 0:
        return np.empty((0, min_cols))
    if a.ndim != 2 or a.shape[1] < min_cols:
        raise ValueError(f"expected an (N, >={min_cols}) array, got shape {a.shape}")
    return a[np.all(np.isfinite(a[:, :min_cols]), axis=1)]


# ------------------------------------------------------------------------------------ cloud top view


def cloud_top_figure(
    points_w: np.ndarray,
    path_w: np.ndarray | None,
    storage_lw_m: tuple[float, float],
    title: str = "Point cloud, top view",
) -> Figure:
    """Top view of the cloud coloured by z, with flight path and storage outline (paper Fig. 12).

    Points are drawn lowest first so the top surface is what shows, as seen from above. Up to
    SCATTER_MAX_POINTS they are 1-pt markers; above, each screen pixel takes its highest point
    (no subsampling either way), and the title says so.
    """
    storage = _storage_lw(storage_lw_m)
    pts = _finite_xy(points_w, 3)
    path = _finite_xy(path_w, 2)
    if pts.shape[0] > SCATTER_MAX_POINTS:
        title = f"{title}\n({pts.shape[0]:,} points binned to screen pixels, highest shown)"
    fig, ax = _new_figure()
    _decorate(ax, storage, [pts[:, :2], path[:, :2]])
    # Title, path and legend before the points: they take room, and the pixel raster needs final sizes.
    ax.set_title(title)
    if path.shape[0] > 0:
        ax.plot(path[:, 0], path[:, 1], color="black", linewidth=0.9, zorder=6, label="flight path")
        ax.legend(**_LEGEND_INSIDE)

    if pts.shape[0] == 0:
        _no_data(ax)
    else:
        z = pts[:, 2]
        norm = Normalize(vmin=float(z.min()), vmax=float(z.max()))
        if norm.vmin == norm.vmax:
            norm = Normalize(vmin=norm.vmin - 0.5, vmax=norm.vmax + 0.5)
        if pts.shape[0] <= SCATTER_MAX_POINTS:
            order = np.argsort(z, kind="stable")
            mappable = ax.scatter(
                pts[order, 0], pts[order, 1], c=z[order], s=1, linewidths=0,
                cmap=HEIGHT_CMAP, norm=norm, rasterized=True, zorder=2,
            )
            _colorbar(fig, ax, mappable, HEIGHT_LABEL)
        else:
            # Colourbar first: it takes room from the axes, and the raster must match the final size.
            _colorbar(fig, ax, ScalarMappable(norm=norm, cmap=HEIGHT_CMAP), HEIGHT_LABEL)
            _pixel_max_image(fig, ax, pts, norm)
    return fig


def _pixel_max_image(fig: Figure, ax: Axes, pts: np.ndarray, norm: Normalize) -> None:
    """Draw the cloud as an image with one cell per screen pixel holding its highest z (NaN -> white)."""
    fig.get_layout_engine().execute(fig)  # the same deterministic layout savefig will produce
    ax.apply_aspect()
    bbox = ax.get_window_extent()
    npx = max(int(np.ceil(bbox.width)), 1)
    npy = max(int(np.ceil(bbox.height)), 1)
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    ix = np.floor((pts[:, 0] - x0) / (x1 - x0) * npx).astype(np.int64)
    iy = np.floor((pts[:, 1] - y0) / (y1 - y0) * npy).astype(np.int64)
    inside = (ix >= 0) & (ix < npx) & (iy >= 0) & (iy < npy)
    flat = np.full(npx * npy, -np.inf)
    np.maximum.at(flat, iy[inside] * npx + ix[inside], pts[inside, 2])
    img = flat.reshape(npy, npx)
    img[~np.isfinite(img)] = np.nan
    ax.imshow(
        np.ma.masked_invalid(img), origin="lower", extent=(x0, x1, y0, y1), cmap=HEIGHT_CMAP,
        norm=norm, interpolation="nearest", zorder=2,
    )
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", adjustable="box")


def plot_cloud_top(
    points_w: np.ndarray,
    path_w: np.ndarray | None,
    storage_lw_m: tuple[float, float],
    out_png: str | Path,
    title: str = "Point cloud, top view",
) -> Path:
    """Write the top-view cloud plot (see `cloud_top_figure`) and return the PNG path."""
    return save_png(cloud_top_figure(points_w, path_w, storage_lw_m, title), out_png)


# ----------------------------------------------------------------------------------------- height map


def height_map_figure(
    x_edges: np.ndarray,
    y_edges: np.ndarray,
    heights: np.ndarray,
    storage_lw_m: tuple[float, float],
    title: str = "Fitted height map",
    filled: np.ndarray | None = None,
    contours: list[Contour] | None = None,
) -> Figure:
    """Top view of the surface heights[ix, iy] (paper Fig. 10b from above); NaN cells white. Cells the
    fitted surface never reached and the empty-cell policy filled (filled[ix, iy]) are hatched and
    outlined, so the invented part is never mistaken for a measured one. Contour lines
    (`ground.exports.contours`), when given, are drawn and labelled with their heights."""
    storage = _storage_lw(storage_lw_m)
    xe = np.asarray(x_edges, dtype=float)
    ye = np.asarray(y_edges, dtype=float)
    h = np.asarray(heights, dtype=float)
    fig, ax = _new_figure()
    _decorate(ax, storage, [_grid_corners(xe, ye)])
    finite = np.isfinite(h)
    if h.size == 0 or not finite.any():
        _no_data(ax)
    else:
        _check_grid(xe, ye, h, "heights")
        _height_mesh(fig, ax, xe, ye, h, finite)
        f = _cell_mask(filled, h) & finite
        measured = finite & ~f
        if f.any():
            hatch = np.ma.masked_where(~f, np.ones(h.shape))
            ax.pcolor(xe, ye, hatch.T, hatch="///", facecolor="none", edgecolor="0.25", linewidth=0.0, zorder=3)
            ax.add_collection(LineCollection(mask_boundary_segments(xe, ye, f), colors="black", linewidths=0.9,
                                             zorder=4))
            ax.legend(handles=[Patch(facecolor="white", edgecolor="0.25", hatch="///",
                                     label="filled (never seen; empty-cell policy)")], **_LEGEND_BELOW)
        if contours:
            draw_contours(ax, contours)
        step = contours[1].level_m - contours[0].level_m if contours and len(contours) > 1 else None
        title = (f"{title}\n(surface fitted on {100 * measured.mean():.1f} % of {h.size:,} cells"
                 + (f", filled on {100 * f.mean():.1f} %" if f.any() else "")
                 + (f"; contours every {step:g} m)" if step else ")"))
    ax.set_title(title)
    return fig


def plot_height_map(
    x_edges: np.ndarray,
    y_edges: np.ndarray,
    heights: np.ndarray,
    storage_lw_m: tuple[float, float],
    out_png: str | Path,
    title: str = "Fitted height map",
    filled: np.ndarray | None = None,
    contours: list[Contour] | None = None,
) -> Path:
    """Write the height-map plot (see `height_map_figure`) and return the PNG path."""
    return save_png(height_map_figure(x_edges, y_edges, heights, storage_lw_m, title, filled, contours), out_png)


# ------------------------------------------------------------------------------------------- coverage


def mask_boundary_segments(x_edges: np.ndarray, y_edges: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Cell-edge segments (K, 2, 2) separating True from False cells of mask[ix, iy].

    Drawn along the cell edges rather than with `contour` on cell centres, so the line is exactly
    where the fitted surface stops (contour would cut half a cell inside), outer border included.
    """
    m = np.asarray(mask, dtype=bool)
    xe = np.asarray(x_edges, dtype=float)
    ye = np.asarray(y_edges, dtype=float)
    if m.size == 0:
        return np.empty((0, 2, 2))
    p = np.pad(m, 1, constant_values=False)
    # Vertical edges at x_edges[i], between cells (i-1, j) and (i, j): shape (nx+1, ny).
    vi, vj = np.nonzero(p[1:, 1:-1] != p[:-1, 1:-1])
    vert = np.stack(
        [np.stack([xe[vi], ye[vj]], axis=-1), np.stack([xe[vi], ye[vj + 1]], axis=-1)], axis=1
    )
    # Horizontal edges at y_edges[j], between cells (i, j-1) and (i, j): shape (nx, ny+1).
    hi, hj = np.nonzero(p[1:-1, 1:] != p[1:-1, :-1])
    horiz = np.stack(
        [np.stack([xe[hi], ye[hj]], axis=-1), np.stack([xe[hi + 1], ye[hj]], axis=-1)], axis=1
    )
    return np.concatenate([vert, horiz], axis=0)


def coverage_figure(
    x_edges: np.ndarray,
    y_edges: np.ndarray,
    counts: np.ndarray,
    surface_mask: np.ndarray,
    storage_lw_m: tuple[float, float],
    title: str = "Coverage",
    bridged: np.ndarray | None = None,
) -> Figure:
    """Points per cell on a log scale (zero -> white) with the fitted-surface boundary outlined, and the fitted
    cells with no point within the seen radius (bridged: `ground.surface.bridged_cells`) in grey.

    The title carries the fraction of cells hit by at least one point: the honest companion of the
    paper's area coverage ratio R_a, which counts where a surface was fitted, not where data was.
    """
    storage = _storage_lw(storage_lw_m)
    xe = np.asarray(x_edges, dtype=float)
    ye = np.asarray(y_edges, dtype=float)
    c = np.asarray(counts)
    m = np.asarray(surface_mask, dtype=bool)
    fig, ax = _new_figure()
    _decorate(ax, storage, [_grid_corners(xe, ye)])

    if c.size == 0:
        _no_data(ax)
        ax.set_title(title)
        return fig

    _check_grid(xe, ye, c, "counts")
    if m.shape != c.shape:
        raise ValueError(f"surface_mask shape {m.shape} differs from counts shape {c.shape}")
    c = np.where(np.isfinite(c.astype(float)), c, 0).astype(float)
    hit = c > 0
    n_hit = int(hit.sum())
    if n_hit == 0:
        _no_data(ax)
    else:
        vmax = max(float(c.max()), 2.0)  # LogNorm needs vmax > vmin
        cmap = colormaps[COVERAGE_CMAP].with_extremes(bad=(0.0, 0.0, 0.0, 0.0))  # no points: what lies under
        mesh = _grid_mesh(
            ax, xe, ye, np.ma.masked_less_equal(c, 0), cmap=cmap, norm=LogNorm(vmin=1.0, vmax=vmax), zorder=2
        )
        counts_bar = _colorbar(fig, ax, mesh, "points per cell")
        # Counts as counts: "2, 3, 4, 6" rather than the log axis's "2 x 10^0"; the in-between ticks are named only
        # where the bar spans about a decade or less (LogFormatter's thresholds), so a wide range is not crowded.
        counts_bar.ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
        counts_bar.ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False))

    handles = []
    segs = mask_boundary_segments(xe, ye, m)
    if segs.shape[0] > 0:
        ax.add_collection(LineCollection(segs, colors="black", linewidths=1.1, zorder=4))
        handles.append(Line2D([], [], color="black", linewidth=1.1, label="fitted surface boundary"))
    if bridged is not None:
        if np.shape(bridged) != c.shape:
            raise ValueError(f"bridged shape {np.shape(bridged)} differs from counts shape {c.shape}")
        b = np.asarray(bridged, dtype=bool)
        if b.any():  # grey under the points' colours: the cells between fans too far apart, a trough no beam reached
            _grid_mesh(ax, xe, ye, np.ma.masked_where(~b, np.ones(b.shape)), cmap=ListedColormap([BRIDGED_GREY]),
                       vmin=0.0, vmax=1.0, zorder=1)
            handles.append(Patch(facecolor=BRIDGED_GREY, label=f"bridged: no point within {SEEN_RADIUS_M:g} m"))
    if handles:
        ax.legend(handles=handles, **_LEGEND_BELOW)
    ax.set_title(
        f"{title}\n{n_hit:,} of {c.size:,} cells have points ({100 * n_hit / c.size:.1f} %), "
        f"surface on {100 * m.mean():.1f} %"
    )
    return fig


def plot_coverage(
    x_edges: np.ndarray,
    y_edges: np.ndarray,
    counts: np.ndarray,
    surface_mask: np.ndarray,
    storage_lw_m: tuple[float, float],
    out_png: str | Path,
    title: str = "Coverage",
    bridged: np.ndarray | None = None,
) -> Path:
    """Write the coverage plot (see `coverage_figure`) and return the PNG path."""
    return save_png(coverage_figure(x_edges, y_edges, counts, surface_mask, storage_lw_m, title, bridged), out_png)
