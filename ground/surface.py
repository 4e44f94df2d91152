"""Surface over the floor and the grid volume: eqs. (7)-(9).

The surface is a scattered-data cubic (Clough-Tocher on the Delaunay triangulation of its nodes), the
analogue of MATLAB's `fit(..., 'cubicinterp')` the paper used, limited: in each triangle it may not leave
the range of its three nodes' heights. By default (``local-linear``, below) the nodes are heights estimated
from the points, one per occupied cell; ``cubic-limited`` takes the points themselves as nodes. With exact
points the limit almost never bites; with noisy ones (a 1° servo angle error moves a far point 0.3-0.5 m)
the cubic's gradients, estimated from points that contradict each other, carry it metres past its data
across the long triangles between sparse tracks (docs/design-notes.md). ``cubic`` is the paper's
unlimited fit through the points, ``linear`` the piecewise-planar one.

``local-linear`` estimates instead of interpolating (`ground.smoothing`): every point gets its vertical
sigma from the sensor model in the log header (range, beam angle, position, quantum), points further from
their neighbours' plane than their noise allows are left out (wall returns that escaped the structure
mask: the measured source of about half of Appendix A's volume bias on pile 1), each occupied cell gets a
weighted local plane over the widest window Lepski's rule accepts, evaluated at the cell's data centroid,
and the cubic-limited surface is drawn through those nodes. `fit_heights_with_se` also gives each cell's
standard error from the points' noise. It is the default: docs/surface_estimators.md compares the fits on the
paper's piles and on the evaluation set (tools.estimator_compare, tools.estimator_evalset), and
docs/design-notes.md says why. The surface exists
only inside the convex hull of the points; what happens to cells outside it is the empty-cell
policy:

- ``nearest``: extend the surface to the walls with the nearest reconstructed cell's
  height, the usual survey practice: the walls bound the pile, and a pile that leans on them
  would otherwise lose a strip of volume along every wall whose width depends on where the last
  sample happened to land (docs/cell_sensitivity.md shows the grid sensitivity this removes).
- ``leave`` (the paper's method): no surface there, no volume counted.
- ``bounded``: the nearest reconstructed height too, but held between the floor and the flight's
  free-space ceiling (`ground.unseen`: beams that passed over a cell bound its height).
- ``wall-contact``: the empty cells take the surface fitted through the points and the wall
  contacts (`ground.wall_contact`: where a sweep's lowest wall hit sits above material, the material's height at
  the wall), nodes at the walls' feet, so it reaches the walls where the sweeps saw them; what that
  leaves empty as ``CONTACT_REST`` (`ground.wall_contact`), all of it held under the free-space ceiling
  (as ``bounded``: what a beam passed over, carried at the steepest slope the ground may have to the cells
  around). ``carry-down`` is the same, but in the unseen cells a beam passed over (shadows) where the seen
  surface falls towards them, that rest is carried on down at its slope, to the floor at most, instead of copied
  level (`ground.carry_down`). ``wall-strip`` (default) is ``carry-down`` with the strip along each wall that no
  point reached taken as unseen where the wall contacts either side contradict the fit there (the hull's bridge:
  `ground.wall_strip`).
  The fitted cells keep the points' own fit,
  and R_a and the interval's unseen term are the points' own: the contacts are bounded estimates, not
  measured pile points.

Either way R_a (eq. 9) is computed from the fitted surface before any filling, and the report
states the uncovered area, so extrapolation is never hidden.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage
from scipy.interpolate import CloughTocher2DInterpolator, LinearNDInterpolator
from scipy.spatial import ConvexHull, QhullError

from firmware_py.core.surface_file import MAX_GRID_CELLS, MIN_GRID_CELL_M, SEEN_RADIUS_M
from ground.blas_threads import one_blas_thread
from ground.gp_slopes import node_slopes
from ground.smoothing import DEFAULT_SMOOTHING, CubicLimit, NodeSlopes, SmoothingOptions, smoothed_nodes
from ground.triangulation import delaunay

SURFACE_FITS = ("cubic-limited", "cubic", "linear", "local-linear")
LIMITED_FITS = ("local-linear", "cubic-limited")
"""The fits whose cubic is held within each triangle's node heights (`CubicLimit` says how)."""
CLIP_TOLERANCE_M = 0.5
"""How far a fitted height may leave the building (below its floor, above its roof) before it is no surface
(`clip_to_building`)."""
DEFAULT_SURFACE_FIT = "local-linear"
"""docs/surface_estimators.md: on 414 runs of the evaluation set the interpolants read 2-9 % low under the
rangefinder's own datasheet noise (range noise moves a point along its beam, which couples its height error to
its position); the local regression does not (docs/design-notes.md, "The default surface is estimated")."""
EMPTY_CELL_POLICIES = ("nearest", "leave", "bounded", "wall-contact", "carry-down", "wall-strip")
CONTACT_POLICIES = ("wall-contact", "carry-down", "wall-strip")
"""The policies that take the unseen cells from the surface through the points and the wall contacts first."""
CARRY_DOWN_POLICIES = ("carry-down", "wall-strip")
"""The policies that carry the rest down the seen slope in the shadows (`ground.carry_down`). `wall-strip` also
takes the strip along each wall that no point reached as unseen where the wall contacts contradict the fit there
(`ground.wall_strip`)."""
STRIP_POLICIES = ("wall-strip",)
DEFAULT_EMPTY_CELLS = "wall-strip"
"""On the 945 runs of the evaluation set's bay, wall, corner, irregular and steep piles better than `carry-down`
(|Ve| by more than 0.05 pp) on 113, worse on 36; the held-out bay piles' interval coverage 85.7 -> 90.5 %
(docs/design-notes.md, "`wall-strip` made the default"). `carry-down` before it: better than `wall-contact` on 133
of the 1,449 pile runs, worse on 23 ("The unseen fill carried down the seen slope in the shadows")."""
DEFAULT_CELL_M = 0.25
"""Grid cell side; docs/cell_sensitivity.md measures the volume change against 0.05 m cells."""
MEASURED_MAX_CELL_M = 0.5
"""The coarsest cell at which that change stayed within 0.2 % on every row of the default fill. The interval,
calibrated at the default cell, leaves the grid's own error out; coarser, the report warns."""
MAX_CELLS = MAX_GRID_CELLS
"""Largest grid (a few hundred MB per array): 60 x 40 m in 0.01 m cells fits, a 10 km building in 0.25 m does not."""


@dataclass(frozen=True)
class Grid:
    """A regular grid of square-ish cells tiling the floor [0, L] x [0, W]."""

    length_m: float
    width_m: float
    cell_m: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cell_m) and MIN_GRID_CELL_M <= self.cell_m <= min(self.length_m, self.width_m)):
            raise ValueError(f"cell size must be between {MIN_GRID_CELL_M:g} m and the building's width, "
                             f"got {self.cell_m}")
        nx, ny = self.shape
        if nx * ny > MAX_CELLS:  # a big building (as a log header may claim) with fine cells: refuse, not MemoryError
            raise ValueError(f"a {self.length_m:g} x {self.width_m:g} m floor in {self.cell_m:g} m cells is "
                             f"{nx * ny:,} cells, more than {MAX_CELLS:,}: use a larger cell size")

    @property
    def shape(self) -> tuple[int, int]:
        return max(1, round(self.length_m / self.cell_m)), max(1, round(self.width_m / self.cell_m))

    @property
    def x_edges(self) -> np.ndarray:
        return np.linspace(0.0, self.length_m, self.shape[0] + 1)

    @property
    def y_edges(self) -> np.ndarray:
        return np.linspace(0.0, self.width_m, self.shape[1] + 1)

    @property
    def cell_xy_m(self) -> tuple[float, float]:
        """The cells' sides along x and y (the floor's length and width over the cell counts)."""
        nx, ny = self.shape
        return self.length_m / nx, self.width_m / ny

    @property
    def cell_area_m2(self) -> float:
        """G_xy of eq. (7): the cells tile the floor exactly."""
        nx, ny = self.shape
        return self.length_m * self.width_m / (nx * ny)

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        xe, ye = self.x_edges, self.y_edges
        return np.meshgrid(0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1]), indexing="ij")

    def counts(self, points_xy: np.ndarray) -> np.ndarray:
        """Points per cell, (nx, ny)."""
        return self.cell_sums(self.flat_cells(points_xy)).astype(np.int64)

    def cell_sums(self, cells: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Per cell, (nx, ny): the count of the points `flat_cells` put there, or the sum of their weights; points
        off the floor (-1) add nothing."""
        on = cells >= 0
        nx, ny = self.shape
        return np.bincount(cells[on], None if weights is None else weights[on], minlength=nx * ny).reshape(nx, ny)

    def flat_cells(self, points_xy: np.ndarray) -> np.ndarray:
        """Each point's cell as a flat index into (nx, ny), -1 off the floor (or not finite): the cells
        `np.histogram2d` over the grid's edges puts them in (the last edge in the last cell), found once for
        several sums over the same points (`np.bincount`, which adds in the same order)."""
        nx, ny = self.shape
        x, y = points_xy[:, 0], points_xy[:, 1]
        xe, ye = self.x_edges, self.y_edges
        ix = np.searchsorted(xe, x, side="right") - (x == xe[-1])
        iy = np.searchsorted(ye, y, side="right") - (y == ye[-1])
        inside = (ix >= 1) & (ix <= nx) & (iy >= 1) & (iy <= ny)
        return np.where(inside, (ix - 1) * ny + (iy - 1), -1)


def fit_heights(points_w: np.ndarray, grid: Grid, method: str = DEFAULT_SURFACE_FIT,
                sigma_m: np.ndarray | None = None, smoothing: SmoothingOptions = DEFAULT_SMOOTHING,
                wanted: np.ndarray | None = None) -> np.ndarray:
    """The surface through (or, ``local-linear``, estimated from) the points (module docstring:
    SURFACE_FITS), sampled at the cell centres; NaN outside the hull. sigma_m: each point's vertical
    1-sigma error (`ground.smoothing.vertical_sigma_m`), used by ``local-linear`` only. wanted (a cell
    mask, or None for all): the cells the caller will use; the surface is then drawn through only the nodes
    that shape it there (`shaping_points`), the same surface in those cells for a fraction of the cost: with
    scipy's slopes only (ValueError for the GP's, whose covariance is fitted over every node)."""
    return fit_surface(points_w, grid, method, sigma_m, smoothing, wanted).heights_m


class SurfaceFit(NamedTuple):
    """A fitted surface at the cell centres (`fit_surface`)."""

    heights_m: np.ndarray
    se_m: np.ndarray  # each cell's standard error from the points' noise (NaN: not estimated)
    scipy_slopes_m: np.ndarray | None  # the same nodes' cubic with scipy's slopes, where the GP's replaced them
    # (`NodeSlopes.GP`, `NodeSlopes.GP_BRIDGES`); None: heights_m took scipy's slopes itself


def fit_heights_with_se(points_w: np.ndarray, grid: Grid, method: str = DEFAULT_SURFACE_FIT,
                        sigma_m: np.ndarray | None = None,
                        smoothing: SmoothingOptions = DEFAULT_SMOOTHING,
                        wanted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`fit_surface`'s heights and standard errors."""
    fit = fit_surface(points_w, grid, method, sigma_m, smoothing, wanted)
    return fit.heights_m, fit.se_m


def fit_surface(points_w: np.ndarray, grid: Grid, method: str = DEFAULT_SURFACE_FIT,
                sigma_m: np.ndarray | None = None,
                smoothing: SmoothingOptions = DEFAULT_SMOOTHING,
                wanted: np.ndarray | None = None) -> SurfaceFit:
    """`fit_heights` and each cell's standard error of the fitted height from the points' noise alone
    (the estimator's own variance: not the error of bridging unseen ground), NaN where not estimated:
    outside the hull, and everywhere for the interpolating fits or without sigma_m (an interpolant has
    no variance of its own to state). Inside the hull, between the nodes, the nodes' standard errors are
    interpolated linearly: the nodes' errors are correlated (overlapping windows), so this is the bound
    for fully correlated errors rather than the smaller independent sum. With the GP's slopes, also the cubic through
    the same nodes with scipy's slopes (`SurfaceFit.scipy_slopes_m`): the unseen term takes the slope where sight
    stopped from it (`ground.uncertainty.unseen_reach_m`)."""
    if method not in SURFACE_FITS:
        raise ValueError(f"surface fit must be one of {', '.join(SURFACE_FITS)}, got {method!r}")
    if wanted is not None and method == "local-linear" and sigma_m is not None \
            and smoothing.slopes is not NodeSlopes.CURVATURE:
        raise ValueError(f"a fit in some cells only (wanted) takes scipy's slopes: the {smoothing.slopes} slopes' "
                         "process is fitted over every node, so a subset of them would give another surface")
    nan = np.full(grid.shape, np.nan)
    if len(points_w) < 3:
        return SurfaceFit(nan, nan.copy(), None)
    if method != "local-linear":
        near = slice(None) if wanted is None else shaping_points(points_w[:, :2], wanted, grid)
        return _interpolate(points_w[near], grid, method, limit=smoothing.limit)
    nx, ny = grid.shape
    cell_xy = (grid.length_m / nx, grid.width_m / ny)
    exact = sigma_m is None  # exact points: the cell's centroid, no smoothing and no variance
    if exact:
        sigma, smoothing = np.ones(len(points_w)), SmoothingOptions(max_window_m=0, reject_outliers=False,
                                                                      limit=smoothing.limit)
    else:
        sigma = np.asarray(sigma_m, dtype=float)
        if sigma.shape != (len(points_w),) or not np.all(np.isfinite(sigma) & (sigma > 0)):
            raise ValueError("sigma_m must hold one finite sigma > 0 per point")
    corners = hull_corners(points_w)
    nodes = smoothed_nodes(points_w, sigma, grid.shape, cell_xy, smoothing, at_xy=corners)
    has = np.isfinite(nodes.at_z)  # a corner whose cell has no node (its points were all outliers) adds nothing
    xyz = np.concatenate([nodes.xyz, np.column_stack([corners[has], nodes.at_z[has]])])
    node_se = None if exact else np.concatenate([nodes.se_m, nodes.at_se[has]])
    if wanted is not None:  # the nodes that shape the surface in the wanted cells
        near = shaping_points(xyz[:, :2], wanted, grid)
        xyz, node_se = xyz[near], None if node_se is None else node_se[near]
    fit = _interpolate(xyz, grid, "cubic-limited", node_se, smoothing.slopes, smoothing.max_window_m, smoothing.limit)
    fit.se_m[~np.isfinite(fit.heights_m)] = np.nan  # exact: se all NaN
    return fit


def hull_corners(points_w: np.ndarray) -> np.ndarray:
    """The corners (k, 2) of the points' convex hull, none for collinear or coincident points. The estimated
    surface takes a node at each (its cell's chosen plane there), so that it covers the points' hull as an
    interpolant through the points does, instead of stopping at the nodes' (cell centroids') hull up to half a
    cell inside it, which would leave a rim of seen ground to the empty-cell fill and out of R_a."""
    xy = np.ascontiguousarray(points_w[:, :2], dtype=float)
    try:
        return xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        return np.empty((0, 2))


def _interpolate(points_w: np.ndarray, grid: Grid, method: str, also_linear: np.ndarray | None = None,
                 slopes: NodeSlopes = NodeSlopes.CURVATURE,
                 reach_m: float | None = None, limit: CubicLimit = CubicLimit.CLIP) -> SurfaceFit:
    """The interpolating fits (cubic-limited, cubic, linear) at the cell centres, and also_linear (one value
    per point, or None) interpolated linearly on the same triangulation as `SurfaceFit.se_m` (NaN without it).
    cubic-limited: where the cubic leaves its triangle's corners' range, held at it or linear there (`CubicLimit`).
    With `NodeSlopes.GP` and also_linear the nodes' standard errors, the cubic takes its slopes at the nodes from
    `ground.gp_slopes` (scipy's where that cannot fit them); with `NodeSlopes.GP_BRIDGES` from the process at the
    nodes of the triangles longer than reach_m (`ground.gp_slopes.bridge_nodes`) only. The cubic with scipy's
    slopes is then evaluated too: its triangulation and slopes are made already, so it costs one evaluation."""
    heights = np.full(grid.shape, np.nan)
    extra = np.full(grid.shape, np.nan)
    if len(points_w) < 3:
        return SurfaceFit(heights, extra, None)
    xy = np.ascontiguousarray(points_w[:, :2], dtype=float)
    # One BLAS thread: the triangulation makes tens of thousands of 2x2 LAPACK solves, which a
    # threaded OpenBLAS turns into thread hand-offs; with two processes on two cores they crawl.
    with one_blas_thread():
        try:
            tri = delaunay(xy)
        except (QhullError, ValueError):  # all points collinear or coincident: no surface
            return SurfaceFit(heights, extra, None)
        z = np.asarray(points_w[:, 2], dtype=float)
        cx, cy = grid.centres()
        if also_linear is not None:
            extra = LinearNDInterpolator(tri, np.asarray(also_linear, dtype=float))(cx, cy)
        if method == "linear":
            return SurfaceFit(LinearNDInterpolator(tri, z)(cx, cy), extra, None)
        cubic = CloughTocher2DInterpolator(tri, z)
        scipy_grad = None
        if slopes in (NodeSlopes.GP, NodeSlopes.GP_BRIDGES) and also_linear is not None:
            g = node_slopes(tri, z, also_linear, reach_m if slopes is NodeSlopes.GP_BRIDGES else None)
            if g is not None:  # scipy's interpolator evaluates with the slopes it holds
                scipy_grad, cubic.grad = cubic.grad, g[:, None, :]
        heights = cubic(cx, cy)
        plain = None
        if scipy_grad is not None:
            cubic.grad = scipy_grad
            plain = cubic(cx, cy)
        if method == "cubic":
            return SurfaceFit(heights, extra, plain)
        simplex = tri.find_simplex(np.column_stack([cx.ravel(), cy.ravel()])).reshape(cx.shape)
        inside = simplex >= 0
        zv = z[tri.simplices[simplex[inside]]]  # (n, 3) heights of each cell's triangle
        lo, hi = zv.min(axis=1), zv.max(axis=1)
        planar = None if limit is CubicLimit.CLIP else LinearNDInterpolator(tri, z)(cx, cy)[inside]
        heights[inside] = _limited(heights[inside], lo, hi, planar)
        if plain is not None:
            plain[inside] = _limited(plain[inside], lo, hi, planar)
        return SurfaceFit(heights, extra, plain)


def _limited(cubic: np.ndarray, lo: np.ndarray, hi: np.ndarray, planar: np.ndarray | None) -> np.ndarray:
    """Cells' cubic heights held within [lo, hi], their triangle's corners' range: clipped to it (planar None), or
    the plane through the corners (planar) in each cell where the cubic leaves it by more than rounding (a
    micrometre: a flat's cubic is its plane). Per cell, not per triangle: a triangle where the cubic leaves its
    range at one cell keeps the cubic in the others (the whole triangle planar read domes between tracks lower:
    docs/design-notes.md), at the price of a step where the cubic reaches the range."""
    if planar is None:
        return np.clip(cubic, lo, hi)
    return np.where((cubic < lo - 1e-6) | (cubic > hi + 1e-6), planar, cubic)


def clip_to_building(heights: np.ndarray, height_m: float,
                     tolerance_m: float = CLIP_TOLERANCE_M) -> tuple[np.ndarray, int]:
    """Cells whose fit left the building by more than tolerance_m become empty (NaN), and their count.

    A cubic through points that contradict each other (two heights at nearly the same spot)
    overshoots without bound: such a cell has no surface, and the empty-cell policy (and R_a) treat
    it as uncovered. Smaller dips below the floor are kept as they are: with noisy points the fit
    wanders a few cm either side of the floor, and clamping only the low side would add volume.
    """
    h = np.array(heights, dtype=float)
    off = np.isfinite(h) & ((h < -tolerance_m) | (h > height_m + tolerance_m))
    h[off] = np.nan
    return h, int(off.sum())


def fill_empty(heights: np.ndarray, policy: str, ceiling_m: np.ndarray | None = None,
               contact_fit_m: np.ndarray | None = None, cell_xy_m: tuple[float, float] | None = None,
               shadow: np.ndarray | None = None) -> np.ndarray:
    """Apply the empty-cell policy to a height grid (see module docstring); ``bounded`` holds the fill
    under ceiling_m (`ground.unseen.free_space_ceiling_m`; None: only the floor bounds it). ``wall-contact``
    takes the empty cells from contact_fit_m, the fit through the points and the wall contacts (None: no
    contacts), fills what is still empty by CONTACT_REST, and holds all of it under ceiling_m (None, or a NaN
    cell: not bounded). ``carry-down`` does the same with the rest carried down the seen slope in the `shadow`
    cells (those a beam passed over: `ground.unseen.free_space_ceilings_m`; None: none known, the rest is copied
    level as ``wall-contact`` does), which needs the grid's cell sides, cell_xy_m (`Grid.cell_xy_m`)."""
    if policy not in EMPTY_CELL_POLICIES:
        raise ValueError(f"empty-cell policy must be one of {', '.join(EMPTY_CELL_POLICIES)}, got {policy!r}")
    if policy in CARRY_DOWN_POLICIES and cell_xy_m is None:
        raise ValueError(f"the {policy} empty-cell policy needs the grid's cell sides (cell_xy_m)")
    empty = ~np.isfinite(heights)
    if policy == "leave" or not empty.any() or empty.all():
        return heights
    if policy in CONTACT_POLICIES:
        from ground.carry_down import carry_down
        from ground.wall_contact import CONTACT_REST
        extended = heights if contact_fit_m is None else np.where(empty, contact_fit_m, heights)
        filled = (carry_down(extended, *cell_xy_m, where=np.zeros(heights.shape, bool) if shadow is None else shadow)
                  if policy in CARRY_DOWN_POLICIES else fill_empty(extended, CONTACT_REST, ceiling_m))
        if ceiling_m is None:
            return filled
        from ground.unseen import upper_bound_m
        return np.where(empty, np.minimum(filled, upper_bound_m(ceiling_m, filled.shape)), filled)
    if policy == "bounded":
        from ground.unseen import bounded_fill
        return bounded_fill(heights, ceiling_m)
    _, (ix, iy) = ndimage.distance_transform_edt(empty, return_indices=True)
    return heights[ix, iy]


REACH_GAPS = 4.0
"""`shaping_points`' reach in widest gaps (see there)."""


def shaping_points(points_xy: np.ndarray, wanted: np.ndarray, grid: Grid) -> np.ndarray:
    """Which points shape a Delaunay-based fit (cubic, cubic-limited, linear) in the wanted cells: those within
    REACH_GAPS widest gaps of a wanted cell. A fit needed only in a few cells (the wall-contact fit, in the
    unseen ones) is then a triangulation of these points rather than of the whole cloud, and equal to the whole
    cloud's fit there (tested).

    Why four gaps: with g the widest distance from any cell to a cell holding points (plus a cell's diagonal),
    no circle empty of points is wider than about g, so the triangle holding a wanted cell's centre has its
    corners within 2g of it; a Clough-Tocher corner's gradient is estimated from its neighbours, within another
    2g. Where the points are sparse (a wide unseen corner) g is large and the reach takes the whole cloud."""
    wanted = np.asarray(wanted, dtype=bool)
    if not wanted.any() or len(points_xy) == 0:
        return np.zeros(len(points_xy), dtype=bool)
    holds = grid.counts(points_xy) > 0
    if not holds.any():
        return np.ones(len(points_xy), dtype=bool)
    nx, ny = grid.shape
    cell_xy = (grid.length_m / nx, grid.width_m / ny)
    gap_m = float(ndimage.distance_transform_edt(~holds, sampling=cell_xy).max()) + math.hypot(*cell_xy)
    to_wanted_m = ndimage.distance_transform_edt(~wanted, sampling=cell_xy)
    ix = np.clip(np.floor(points_xy[:, 0] / cell_xy[0]).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.floor(points_xy[:, 1] / cell_xy[1]).astype(np.int64), 0, ny - 1)
    return to_wanted_m[ix, iy] <= REACH_GAPS * gap_m


def grid_volume(heights: np.ndarray, grid: Grid) -> float:
    """Eq. (7): V = sum H_z G_xy over cells that have a surface."""
    return float(np.nansum(heights) * grid.cell_area_m2)


def volume_error_pct(volume_m3: float, true_volume_m3: float | None) -> float | None:
    """Eq. (8): |V - V_true| / V_true x 100, or None when the truth is unknown."""
    if true_volume_m3 is None or not math.isfinite(true_volume_m3) or true_volume_m3 <= 0:
        return None
    return abs(volume_m3 - true_volume_m3) / true_volume_m3 * 100.0


def bridged_cells(counts: np.ndarray, fitted: np.ndarray, cell_xy_m: tuple[float, float],
                  radius_m: float = SEEN_RADIUS_M) -> np.ndarray:
    """The fitted cells with no point within radius_m (from the cell to the nearest cell holding one): where the
    points' hull bridges ground no point saw (a trough behind a pile's shoulder, the floor between fans too far apart).
    They are inside R_a (eq. 9), but their heights are as much a guess as the fill's; the gap re-flight targets them
    (`sitl.missions.gaps`), and the report gives their area beside R_a."""
    fitted = np.asarray(fitted, dtype=bool)
    hit = np.asarray(counts) > 0
    if not hit.any():
        return fitted.copy()
    return fitted & (ndimage.distance_transform_edt(~hit, sampling=cell_xy_m) > radius_m)


def reconstructed_ratio_pct(heights: np.ndarray) -> float:
    """Eq. (9): R_a = projected area of the generated surface / total area, in percent."""
    return float(np.isfinite(heights).mean() * 100.0)
