"""Estimating the surface from noisy points: per-point vertical error and binned local regression.

A surface through every point is the right estimator only for exact points. With noise (Appendix A:
2.5 cm of range, 1 deg of servo angle, 0.11 m of position) a point is off the surface by tens of cm,
and an interpolant reproduces every such error. This module estimates the height instead:

1. Every point's vertical 1-sigma error from the sensor model in the log header
   (`vertical_sigma_m`): range noise along the beam (sigma_r |d_z|), angle noise across it
   (r sigma_angle sqrt(1 - d_z^2): the beam turns about a horizontal axis), position noise, and the
   range quantum (resolution / sqrt 12, so a "noise-free" sensor still has a finite, honest error).
2. The points are binned in the grid's cells with weights 1/sigma^2 (`binned_moments`). A point further
   from the plane of its neighbours (the 3 x 3 cells around its own, its own cell left out) than its
   noise allows is left out (`outliers`): on Appendix A surveys these are mostly wall returns that
   escaped the structure mask (the mask's tolerance has no angle term), metres above the floor near the
   walls, each of which an interpolant spreads over a whole triangle.
3. For each occupied cell a weighted plane is fitted to the points of square windows of growing
   half-width (0, 1, 2, 4, ... cells) and evaluated at the cell's own data centroid (`window_sums`, `planes`):
   the cell alone (its weighted mean: exact on a plane) and ever smoother, lower-variance estimates, each
   with its standard error from the weights (the prediction variance of weighted least squares with
   known variances).
4. Per cell the window is chosen by Lepski's rule (`lepski_select`): the widest window whose estimate
   agrees with every narrower one within `z_crit` of the narrower one's standard error. Where the
   points are dense and noisy, wide windows agree within their noise and are taken; where the surface
   bends faster than the noise hides, or the points are exact (sigma tiny), the narrow window wins and
   the data are honoured. No bandwidth is set by hand: the noise, the point spacing and the cell
   size decide (`SmoothingOptions.max_window_m` only bounds the search).

The smoothed heights at the cells' data centroids are then the nodes of the ordinary surface
(`ground.surface`), so sparse swaths are bridged exactly as before. What the windows cannot do: a local
plane flattens a curved surface by 1/2 tr(H Sigma_w) (H the surface's Hessian, Sigma_w the window's
spread), which per cell is within the noise (that is Lepski's test) but has one sign over a whole convex
pile, so for the *volume* the windows trade variance, which averages out over thousands of cells anyway,
for a bias that does not (docs/design-notes.md has the measurements). `SmoothingOptions.quadratic` refits each
chosen window as a local quadratic, which holds the bend (`quadratic_nodes`); it is one of the report's noise
corrections, not yet the default (`ground.report.ReportOptions.noise_corrections`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from ground.pointcloud import Cloud, SensorErrorModel, structure_n_sigma

DEFAULT_Z_CRIT = 2.0
"""Lepski's critical value: a wider window is refused when its estimate differs from a narrower one by more
than this many of the narrower one's standard errors. 2 is the two-sided 95 % normal quantile (1.96),
rounded: a wider window is refused only when the difference would be unlikely (5 %) from noise alone."""
DEFAULT_MAX_WINDOW_M = 2.0
"""Largest window half-width. It bounds the cost (the windows double: 0, 1, 2, 4, 8 cells of 0.25 m) and the
distance one point's influence can reach; Lepski's rule picks within it. A fan line of the paper's
mission is 1-2 m wide at the lowest P_traj, so wider windows would mostly mix in other tracks' data."""


class NodeSlopes(StrEnum):
    """Where the cubic between the nodes takes its slopes at them: scipy's least-curvature estimate through the
    node heights taken as exact (``curvature``), or through the heights a Gaussian process fitted to the nodes and
    their standard errors predicts (``gp``: `ground.gp_slopes`), or the process's heights only at the nodes of the
    triangles that span further than the windows reach (`SmoothingOptions.max_window_m`) and their neighbours
    (``gp-bridges``: `ground.gp_slopes.bridge_nodes`): within the windows' reach the nodes' noise is averaged
    already and the cubic cannot carry a slope far."""

    CURVATURE = "curvature"
    GP = "gp"
    GP_BRIDGES = "gp-bridges"


class CubicLimit(StrEnum):
    """What the limited cubic does where it leaves the range of its triangle's three node heights: holds itself at
    that range (``clip``), or takes the plane through the three nodes there (``linear``). Across a long triangle (a
    bridge between sparse tracks, or from the points to a wall contact) a cubic whose slopes were estimated from
    noisy or far-off nodes can run metres past its corners; clipped, the triangle becomes a flat at its lowest (or
    highest) corner's height, one corner's value carried over metres of ground; the plane stays between the
    corners and keeps the lean from one to the other. Where the cubic's excursion is the pile's own curvature (a
    dome between two tracks, exact points) the clip is the closer of the two."""

    CLIP = "clip"
    LINEAR = "linear"


DEFAULT_CUBIC_LIMIT = CubicLimit.CLIP
"""The clip: the plane is closer under pointing noise on the paper's two piles but not on the evaluation set (worse
without noise, and from P_traj 20 % under Appendix A's noise, the corner piles most): docs/design-notes.md, "Where the
limited cubic overshoots: the plane, not a flat"."""


DEFAULT_NODE_SLOPES = NodeSlopes.GP_BRIDGES
"""The process's heights at the bridges: against scipy's slopes everywhere, the paper's piles under Appendix A's noise
within 0.2 pp of their noise-free volume on 10 of 12 rows instead of 7, the evaluation set's mean |Ve| 3.74 -> 3.24 %
(datasheet noise) and 3.17 -> 2.67 % (Appendix A), the same without noise, for about 0.2 s of a report; the GP at
every node gains little more for twice that (docs/design-notes.md, "GP slopes at the bridges only")."""


@dataclass(frozen=True)
class SmoothingOptions:
    """How the local regression chooses its windows (defaults: module constants, their reasons there), and where
    the cubic drawn through its nodes takes its slopes."""

    z_crit: float = DEFAULT_Z_CRIT
    max_window_m: float = DEFAULT_MAX_WINDOW_M
    reject_outliers: bool = True
    outlier_n_sigma: float | None = None  # None: structure_n_sigma of the cloud's size
    noise_from_data: bool = True  # the windows' standard errors scaled down to the scatter the data show
    slopes: NodeSlopes = DEFAULT_NODE_SLOPES
    quadratic: bool = False  # each chosen window refitted as a local quadratic (`quadratic_nodes`)
    limit: CubicLimit = DEFAULT_CUBIC_LIMIT  # where the cubic through the nodes leaves its triangle's range

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "slopes", NodeSlopes(self.slopes))
        except ValueError:
            raise ValueError(f"node slopes must be one of {', '.join(NodeSlopes)}, got {self.slopes!r}") from None
        try:
            object.__setattr__(self, "limit", CubicLimit(self.limit))
        except ValueError:
            raise ValueError(f"cubic limit must be one of {', '.join(CubicLimit)}, got {self.limit!r}") from None
        if not (math.isfinite(self.z_crit) and self.z_crit > 0):
            raise ValueError(f"smoothing z_crit must be > 0, got {self.z_crit!r}")
        if not (math.isfinite(self.max_window_m) and self.max_window_m >= 0):
            raise ValueError(f"smoothing max window must be >= 0 m, got {self.max_window_m!r}")
        k = self.outlier_n_sigma
        if k is not None and not (math.isfinite(k) and k > 0):
            raise ValueError(f"smoothing outlier_n_sigma must be > 0, got {k!r}")


DEFAULT_SMOOTHING = SmoothingOptions()


def vertical_sigma_m(range_sigma_m: np.ndarray | float, resolution_m: float, position_sigma_m: float,
                     angle_sigma: float, range_m: np.ndarray, dirs_w: np.ndarray) -> np.ndarray:
    """Each point's vertical 1-sigma error (module docstring, step 1): range noise along the beam, angle
    noise across it, position noise, and the range quantum."""
    dz = np.clip(np.abs(np.asarray(dirs_w, dtype=float)[:, 2]), 0.0, 1.0)
    r = np.asarray(range_m, dtype=float)
    var = ((np.asarray(range_sigma_m, dtype=float) * dz) ** 2 + (r * angle_sigma) ** 2 * (1.0 - dz**2)
           + position_sigma_m**2 + resolution_m**2 / 12.0)
    return np.sqrt(var)


RANGE_NEIGHBOURS = 4
"""The samples either side of each point in time whose median range its sigma is taken from (`typical_range_m`):
eight are a few milliseconds of sweep, over which the range changes little but at a step, which a median keeps (a
25-sample window measured the same: docs/design-notes.md)."""


def typical_range_m(range_m: np.ndarray, neighbours: int = RANGE_NEIGHBOURS) -> np.ndarray:
    """Each sample's range as its neighbours in time give it: the median of the `neighbours` samples either side,
    the sample itself left out, so that none of its own noise is in it. A median keeps a step (a beam going from
    the pile to the floor) where it is."""
    r = np.asarray(range_m, dtype=float)
    if len(r) < 2 or neighbours < 1:
        return r
    # By hand: scipy's median_filter on a 1-D array keeps the centre of a footprint that leaves it out (1.17).
    padded, n, k = np.pad(r, neighbours, mode="edge"), len(r), 2 * neighbours
    others = np.stack([padded[j:j + n] for j in range(k + 1) if j != neighbours], axis=1)
    mid = np.partition(others, [k // 2 - 1, k // 2], axis=1)
    return 0.5 * (mid[:, k // 2 - 1] + mid[:, k // 2])


def cloud_vertical_sigma_m(cloud: Cloud, err: SensorErrorModel, where: np.ndarray,
                           range_from_neighbours: bool = False) -> np.ndarray:
    """`vertical_sigma_m` of the cloud's points `where` (a mask or indices), from the sensor model in the log header:
    the one spelling of it for the surface fit's pile points, a fitted floor's and the floor check's candidates.
    The sigma grows with the range; by default each point's own. A sigma from the point's own measured range weighs a
    reading that came back long (its point placed low) less than one that came back short, and lifts every weighted
    mean by about 2 sigma^2 / r; range_from_neighbours takes the range its neighbours in time give it
    (`typical_range_m`; the cloud is in sample order) and has none of that (docs/design-notes.md, "Each point's weight
    carries its own noise"). It is one of the noise corrections (`ground.report.ReportOptions.noise_corrections`),
    not yet the default: removed alone it moves documented rows the wrong way."""
    rng = (typical_range_m(cloud.range_m) if range_from_neighbours else cloud.range_m)[where]
    dirs = cloud.dirs_w[where]
    return vertical_sigma_m(err.range_sigma(rng), err.resolution_m, err.position_sigma_m, err.angle_sigma_rad, rng,
                            dirs)


def window_halfwidths(cell_m: float, max_window_m: float) -> list[int]:
    """0, 1, 2, 4, ... cells, up to max_window_m."""
    out, j = [0], 1
    while j * cell_m <= max_window_m + 1e-9:
        out.append(j)
        j *= 2
    return out


def cell_index(points_w: np.ndarray, shape: tuple[int, int], cell_m_xy: tuple[float, float]) -> np.ndarray:
    """Each point's flat cell index (points on or past the far walls go to the last cell)."""
    nx, ny = shape
    ix = np.clip(np.floor(points_w[:, 0] / cell_m_xy[0]).astype(np.int64), 0, nx - 1)
    iy = np.clip(np.floor(points_w[:, 1] / cell_m_xy[1]).astype(np.int64), 0, ny - 1)
    return ix * ny + iy


def binned_moments(points_w: np.ndarray, sigma_m: np.ndarray, flat: np.ndarray, shape: tuple[int, int],
                   origin_xy: tuple[float, float]) -> dict[str, np.ndarray]:
    """Weighted sums per cell (weights 1/sigma^2) of the points in cells `flat`, coordinates relative to
    origin_xy (the grid's middle, so the sums stay well conditioned)."""
    nx, ny = shape
    w = 1.0 / np.square(sigma_m)
    x = points_w[:, 0] - origin_xy[0]
    y = points_w[:, 1] - origin_xy[1]
    z = points_w[:, 2]
    terms = {"n": np.ones_like(w), "w": w, "wx": w * x, "wy": w * y, "wz": w * z, "wxx": w * x * x,
             "wxy": w * x * y, "wyy": w * y * y, "wxz": w * x * z, "wyz": w * y * z, "wzz": w * z * z}
    return {k: np.bincount(flat, weights=v, minlength=nx * ny).reshape(nx, ny) for k, v in terms.items()}


def outliers(points_w: np.ndarray, sigma_m: np.ndarray, flat: np.ndarray, m: dict[str, np.ndarray],
             origin_xy: tuple[float, float], n_sigma: float, ring_halfwidths: list[int]) -> np.ndarray:
    """True for points further than n_sigma standard errors from the plane fitted to their neighbours: the
    cells of the smallest window (half-widths ring_halfwidths, 3 x 3 cells first) holding at least 4 points
    besides the point's own cell, which is left out (so a lone point cannot vouch for itself). The standard
    error is the point's sigma and the plane's, in quadrature, both scaled up by the plane's own misfit (its
    reduced chi-square, when above 1): where the neighbours themselves do not lie on a plane within their
    sigmas (a crest, a toe, or noise larger than the header states) nothing is called an outlier on the
    strength of that plane. Points with fewer than 4 neighbours in the widest window are kept: nothing
    contradicts them."""
    out = np.zeros(len(points_w), dtype=bool)
    todo = np.ones(len(points_w), dtype=bool)
    for j in ring_halfwidths:
        ring = {k: box_sum(v, j) - v for k, v in m.items()}
        has = todo & (ring["n"].ravel()[flat] >= 3.5)  # counts are sums of ones: >= 4
        if has.any():
            pl = planes({k: v.ravel()[flat[has]] for k, v in ring.items()})
            est, se = pl.at(points_w[has, 0] - origin_xy[0], points_w[has, 1] - origin_xy[1])
            scale = np.maximum(1.0, pl.chi2_red)
            out[has] = np.abs(points_w[has, 2] - est) > n_sigma * np.sqrt((sigma_m[has] ** 2 + se**2) * scale)
            todo &= ~has
        if not todo.any():
            break
    return out


def integral_image(a: np.ndarray, j_max: int) -> np.ndarray:
    """a's integral image, padded for `box_sum`'s windows up to half-width j_max."""
    return np.pad(a, ((j_max + 1, j_max), (j_max + 1, j_max))).cumsum(axis=0).cumsum(axis=1)


def box_sum(a: np.ndarray, j: int, integral: np.ndarray | None = None, j_max: int | None = None) -> np.ndarray:
    """Sum over the (2j+1)^2 window around each cell (zero outside the grid), by an integral image: a's own, or
    integral (`integral_image(a, j_max)`, j <= j_max) made once for every half-width a caller asks. The same sums to
    the bit either way: the wider padding only adds leading zeros to each running sum, and the four corners are
    combined in the same order. Why: a survey asks each of eleven moments for five windows, and making each
    window's integral image again cost a fifth of the windows' sums (docs/design-notes.md, "The windows' sums from one
    integral image")."""
    if j == 0:
        return a
    if integral is None:
        integral, j_max = integral_image(a, j), j
    o, k = j_max - j, 2 * j + 1
    n, m = a.shape
    c = integral
    return c[o + k:o + k + n, o + k:o + k + m] - c[o:o + n, o + k:o + k + m] - c[o + k:o + k + n, o:o + m] \
        + c[o:o + n, o:o + m]


@dataclass(frozen=True)
class Planes:
    """Weighted planes, one per masked cell: the window's centroid, its mean height, the slope in the
    eigen-frame of the window's spread (no slope along a direction the points do not span)."""

    xm: np.ndarray
    ym: np.ndarray
    zm: np.ndarray
    inv_w: np.ndarray
    ex: np.ndarray
    ey: np.ndarray
    inv1: np.ndarray
    inv2: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    chi2_red: np.ndarray  # weighted residual sum of squares / (points - 3); inf with 3 points or fewer

    def at(self, x: np.ndarray, y: np.ndarray, idx: np.ndarray | slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Height and standard error (known weights: 1/W + d' S^+ d, d the offset from the centroid) of the
        planes idx at (x, y)."""
        dx, dy = x - self.xm[idx], y - self.ym[idx]
        ex, ey = self.ex[idx], self.ey[idx]
        d1, d2 = ex * dx + ey * dy, -ey * dx + ex * dy
        inv1, inv2 = self.inv1[idx], self.inv2[idx]
        est = self.zm[idx] + inv1 * self.p1[idx] * d1 + inv2 * self.p2[idx] * d2
        return est, np.sqrt(self.inv_w[idx] + inv1 * d1 * d1 + inv2 * d2 * d2)


def planes(s: dict[str, np.ndarray]) -> Planes:
    """The weighted least-squares plane of each set of window sums (all arrays of the same shape, w > 0)."""
    w = s["w"]
    xm, ym, zm = s["wx"] / w, s["wy"] / w, s["wz"] / w
    sxx = s["wxx"] - w * xm * xm
    sxy = s["wxy"] - w * xm * ym
    syy = s["wyy"] - w * ym * ym
    sxz = s["wxz"] - w * xm * zm
    syz = s["wyz"] - w * ym * zm
    # Pseudo-inverse of the 2x2 scatter matrix through its eigen-decomposition.
    tr = sxx + syy
    disc = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy**2, 0.0))
    lam1, lam2 = 0.5 * tr + disc, np.maximum(0.5 * tr - disc, 0.0)
    has_xy = np.abs(sxy) > 0
    ex = np.where(has_xy, sxy, np.where(sxx >= syy, 1.0, 0.0))
    ey = np.where(has_xy, lam1 - sxx, np.where(sxx >= syy, 0.0, 1.0))
    norm = np.hypot(ex, ey)
    norm[norm == 0] = 1.0
    ex, ey = ex / norm, ey / norm
    eps = 1e-9 * np.maximum(lam1, 1e-300)  # relative: below it a direction has no spread (collinear points)
    inv1 = np.where(lam1 > eps, 1.0 / np.maximum(lam1, 1e-300), 0.0)
    inv2 = np.where(lam2 > eps, 1.0 / np.maximum(lam2, 1e-300), 0.0)
    p1, p2 = ex * sxz + ey * syz, -ey * sxz + ex * syz
    rss = np.maximum(s["wzz"] - w * zm * zm - inv1 * p1 * p1 - inv2 * p2 * p2, 0.0)
    dof = s["n"] - 3.0
    with np.errstate(divide="ignore", invalid="ignore"):
        chi2_red = np.where(dof > 0.5, rss / np.maximum(dof, 1.0), np.inf)
    return Planes(xm, ym, zm, 1.0 / w, ex, ey, inv1, inv2, p1, p2, chi2_red)


def window_sums(m: dict[str, np.ndarray], j: int, integrals: dict[str, np.ndarray] | None = None,
                j_max: int | None = None) -> dict[str, np.ndarray]:
    """Every moment summed over the (2j+1)^2 window around each cell: `planes` of them is each cell's
    local-linear plane at that window. integrals: each moment's `integral_image` up to j_max, when the caller
    asks for several windows (`box_sum`)."""
    if integrals is None:
        return {k: box_sum(v, j) for k, v in m.items()}
    return {k: box_sum(v, j, integrals[k], j_max) for k, v in m.items()}


MIN_DOF_FOR_SCALE = 5
"""A 3 x 3 window's plane counts towards the data's noise scale with at least this many degrees of freedom."""


def data_noise_scale(m: dict[str, np.ndarray], window: dict[str, np.ndarray] | None = None) -> float:
    """The factor (<= 1) by which the points scatter less than their header sigmas say: the square root of
    the median reduced chi-square of the 3 x 3-cell planes, capped at 1. The header states what the sensor
    may do; where the data show less (a simulated sensor without noise, a calm surface at short range), the
    windows' standard errors shrink with it, so Lepski's test refuses a window whose flattening the data
    would show, instead of accepting it against noise that is not there. Never above 1: a plane's misfit
    also holds the surface's own bend, so the chi-square over-states the noise, and where it is above 1 the
    header's sigma is kept (the outlier test scales by the local misfit itself). window: `window_sums(m, 1)`,
    when the caller has them already."""
    window = window_sums(m, 1) if window is None else window
    ok = (m["n"] > 0) & (window["n"] >= 3 + MIN_DOF_FOR_SCALE)
    if not ok.any():
        return 1.0
    chi2 = planes({k: v[ok] for k, v in window.items()}).chi2_red
    return float(min(1.0, math.sqrt(float(np.median(chi2)))))


def lepski_select(est: np.ndarray, se: np.ndarray, z_crit: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column (a cell), the estimate of the widest window (rows: narrow to wide) that agrees with every
    narrower window within z_crit of the narrower one's standard error; its standard error and the level."""
    n_levels, n = est.shape
    level = np.zeros(n, dtype=np.int64)
    alive = np.ones(n, dtype=bool)
    for k in range(1, n_levels):
        ok = alive & np.isfinite(est[k])
        for m in range(k):
            ok &= np.abs(est[k] - est[m]) <= z_crit * se[m]
        level[ok] = k
        alive = ok
    cols = np.arange(n)
    return est[level, cols], se[level, cols], level


QUAD_MIN_POINTS = 10
"""A chosen window is refitted as a quadratic (`quadratic_refit`) only with at least this many points: six unknowns
and a few degrees of freedom to spare."""
QUAD_MIN_COND = 1e-6
"""... and only when its normal equations are this well conditioned (smallest over largest eigenvalue, after scaling
to unit diagonal): points along one line, a fan line seen by one sweep, do not fix a curvature across it."""
_POWERS4 = [(a, b) for a in range(5) for b in range(5) if a + b <= 4]
_POWERS2 = [(a, b) for a in range(3) for b in range(3) if a + b <= 2]
_PHI = [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]  # 1, dx, dy, dx^2, dx dy, dy^2


_FROM_PLANE = {("m", 0, 0): "w", ("m", 1, 0): "wx", ("m", 0, 1): "wy", ("m", 2, 0): "wxx", ("m", 1, 1): "wxy",
               ("m", 0, 2): "wyy", ("z", 0, 0): "wz", ("z", 1, 0): "wxz", ("z", 0, 1): "wyz", "n": "n"}
"""The quadratic's sums that `binned_moments` already holds for the planes, by their names there."""


def quadratic_moments(points_w: np.ndarray, sigma_m: np.ndarray, flat: np.ndarray, plane: dict[str, np.ndarray],
                      origin_xy: tuple[float, float]) -> dict:
    """Per cell, the weighted sums a local quadratic needs: w x^a y^b (a + b <= 4), w z x^a y^b (a + b <= 2) and the
    point count; those up to the second order are the planes' (`binned_moments` of the same points, `plane`), the
    rest are binned here."""
    nx, ny = plane["w"].shape
    w = 1.0 / np.square(sigma_m)
    x, y, z = points_w[:, 0] - origin_xy[0], points_w[:, 1] - origin_xy[1], points_w[:, 2]

    def binned(v: np.ndarray) -> np.ndarray:
        return np.bincount(flat, weights=v, minlength=nx * ny).reshape(nx, ny)
    xp = [np.ones_like(x), x, x * x, x**3, x**4]
    yp = [np.ones_like(y), y, y * y, y**3, y**4]
    out = {key: plane[name] for key, name in _FROM_PLANE.items()}
    out.update({("m", a, b): binned(w * xp[a] * yp[b]) for a, b in _POWERS4 if ("m", a, b) not in out})
    out.update({("z", a, b): binned(w * z * xp[a] * yp[b]) for a, b in _POWERS2 if ("z", a, b) not in out})
    return out


def quadratic_refit(q: dict, cells: np.ndarray, j: int, at_xy: np.ndarray,
                    scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The weighted local quadratic of the (2j+1)^2 window around each of `cells` (flat indices), evaluated at at_xy
    (k, 2, relative to the moments' origin): (height, standard error, usable) per cell, unusable (NaN) where too few
    points or ill-conditioned. scale: the data's noise scale (`data_noise_scale`), applied to the standard error as
    to the planes'."""
    sums = {k: box_sum(v, j).ravel()[cells] for k, v in q.items()}
    ux, uy = at_xy[:, 0], at_xy[:, 1]
    pow_x = [np.ones_like(ux), -ux, ux * ux, -(ux**3), ux**4]
    pow_y = [np.ones_like(uy), -uy, uy * uy, -(uy**3), uy**4]
    binom = [[1], [1, 1], [1, 2, 1], [1, 3, 3, 1], [1, 4, 6, 4, 1]]

    def local(a: int, b: int, kind: str) -> np.ndarray:  # sum w (x - ux)^a (y - uy)^b [z]
        return sum(binom[a][i] * binom[b][k] * pow_x[a - i] * pow_y[b - k] * sums[(kind, i, k)]
                   for i in range(a + 1) for k in range(b + 1))
    n = len(cells)
    mat, rhs = np.empty((n, 6, 6)), np.empty((n, 6))
    for r, (a1, b1) in enumerate(_PHI):
        rhs[:, r] = local(a1, b1, "z")
        for c, (a2, b2) in enumerate(_PHI):
            mat[:, r, c] = local(a1 + a2, b1 + b2, "m") if c >= r else mat[:, c, r]
    usable = sums["n"] >= QUAD_MIN_POINTS - 0.5
    diag = np.sqrt(np.abs(np.einsum("nii->ni", mat)))
    diag[diag == 0] = 1.0
    scaled = mat / diag[:, :, None] / diag[:, None, :]
    ev = np.linalg.eigvalsh(np.where(usable[:, None, None], scaled, np.eye(6)))
    usable &= ev[:, 0] > QUAD_MIN_COND * ev[:, -1]
    height, se = np.full(n, np.nan), np.full(n, np.nan)
    if usable.any():
        inv = np.linalg.inv(scaled[usable]) / diag[usable][:, :, None] / diag[usable][:, None, :]
        height[usable] = np.einsum("nj,nj->n", inv[:, 0, :], rhs[usable])
        se[usable] = scale * np.sqrt(np.maximum(inv[:, 0, 0], 0.0))
    return height, se, usable


@dataclass(frozen=True)
class Nodes:
    """The smoothed surface's nodes: one per occupied cell, at the cell's data centroid."""

    xyz: np.ndarray  # (n, 3)
    se_m: np.ndarray  # (n,) standard error of each node's height
    level: np.ndarray  # (n,) window half-width chosen, in cells
    n_outliers: int = 0  # points left out as outliers
    at_z: np.ndarray | None = None  # at the positions asked for (`smoothed_nodes` at_xy): the chosen plane's height,
    at_se: np.ndarray | None = None  # and its standard error; NaN where the position's cell has no node


def quadratic_nodes(q: dict, cells: np.ndarray, at_xy: np.ndarray, levels: list[int], lev: np.ndarray,
                    chosen: tuple[np.ndarray, np.ndarray], windows: tuple[np.ndarray, np.ndarray], noise_scale: float,
                    z_crit: float) -> tuple[np.ndarray, np.ndarray]:
    """The nodes' heights and standard errors with each chosen window wider than its cell refitted as a quadratic
    (`quadratic_refit`), which a curved surface does not flatten, where the quadratic agrees with every narrower
    window as Lepski's rule asks of the plane (a cone's apex is no quadratic). cells, at_xy: the occupied cells (flat
    indices) and their nodes (relative to the moments' origin); chosen: the planes' heights and standard errors;
    windows: every window's (levels x nodes)."""
    z, se = chosen[0].copy(), chosen[1].copy()
    all_est, all_se = windows
    for k in np.unique(lev[lev > 0]):
        sel = np.flatnonzero(lev == k)
        height, h_se, ok = quadratic_refit(q, cells[sel], levels[k], at_xy[sel], noise_scale)
        ok &= np.all(np.abs(height - all_est[:k, sel]) <= z_crit * all_se[:k, sel], axis=0)
        z[sel[ok]], se[sel[ok]] = height[ok], h_se[ok]
    return z, se


def smoothed_nodes(points_w: np.ndarray, sigma_m: np.ndarray, shape: tuple[int, int],
                   cell_m_xy: tuple[float, float], opts: SmoothingOptions = DEFAULT_SMOOTHING,
                   at_xy: np.ndarray | None = None) -> Nodes:
    """One node per occupied cell: its Lepski-chosen local-linear height at the cell's weighted centroid
    (module docstring, steps 2-4); with at_xy (k, 2), also the chosen plane of each position's cell evaluated
    at that position (`Nodes.at_z`)."""
    nx, ny = shape
    origin = (0.5 * nx * cell_m_xy[0], 0.5 * ny * cell_m_xy[1])
    flat = cell_index(points_w, shape, cell_m_xy)
    m = binned_moments(points_w, sigma_m, flat, shape, origin)
    n_out = 0
    if opts.reject_outliers:
        k = structure_n_sigma(len(points_w)) if opts.outlier_n_sigma is None else opts.outlier_n_sigma
        bad = outliers(points_w, sigma_m, flat, m, origin, k, [1])
        n_out = int(bad.sum())
        if n_out:
            keep = ~bad
            points_w, sigma_m, flat = points_w[keep], sigma_m[keep], flat[keep]
            m = binned_moments(points_w, sigma_m, flat, shape, origin)
    occupied = m["w"] > 0
    cx = np.where(occupied, m["wx"] / np.where(occupied, m["w"], 1.0), 0.0)
    cy = np.where(occupied, m["wy"] / np.where(occupied, m["w"], 1.0), 0.0)
    levels = window_halfwidths(min(cell_m_xy), opts.max_window_m)
    at = np.empty((0, 2)) if at_xy is None else np.asarray(at_xy, dtype=float).reshape(-1, 2)
    at_flat = cell_index(at, shape, cell_m_xy)
    at_ok = occupied.ravel()[at_flat]  # a position whose cell has no node gets none
    ests, ses, at_ests, at_ses, window1 = [], [], [], [], None
    j_max = max(levels)
    integrals = {k: integral_image(v, j_max) for k, v in m.items()}  # once, for every window below
    for j in levels:  # each window's sums once, for the nodes, the positions asked for and the noise scale
        sums = window_sums(m, j, integrals, j_max)
        window1 = sums if j == 1 else window1
        e, s = planes({k: v[occupied] for k, v in sums.items()}).at(cx[occupied], cy[occupied])
        ests.append(e)
        ses.append(s)
        e, s = planes({k: v.ravel()[at_flat[at_ok]] for k, v in sums.items()}).at(at[at_ok, 0] - origin[0],
                                                                                  at[at_ok, 1] - origin[1])
        at_ests.append(e)
        at_ses.append(s)
    noise_scale = data_noise_scale(m, window1) if opts.noise_from_data else 1.0
    all_est, all_se = np.array(ests), noise_scale * np.array(ses)
    z, se, lev = lepski_select(all_est, all_se, opts.z_crit)
    if opts.quadratic and (lev > 0).any():
        cells = np.flatnonzero(occupied.ravel())
        z, se = quadratic_nodes(quadratic_moments(points_w, sigma_m, flat, m, origin), cells,
                                np.column_stack([cx.ravel()[cells], cy.ravel()[cells]]), levels, lev, (z, se),
                                (all_est, all_se), noise_scale, opts.z_crit)
    xyz = np.column_stack([cx[occupied] + origin[0], cy[occupied] + origin[1], z])
    at_z = at_se = None
    if at_xy is not None:  # each position: its cell's chosen window's plane there
        node_of = np.full(nx * ny, -1, dtype=np.int64)
        node_of[np.flatnonzero(occupied.ravel())] = np.arange(int(occupied.sum()))
        chosen, cols = lev[node_of[at_flat[at_ok]]], np.arange(int(at_ok.sum()))
        at_z, at_se = np.full(len(at), np.nan), np.full(len(at), np.nan)
        at_z[at_ok] = np.array(at_ests)[chosen, cols]
        at_se[at_ok] = noise_scale * np.array(at_ses)[chosen, cols]  # scaled as the nodes' are
    return Nodes(xyz, se, np.asarray(levels)[lev], n_out, at_z, at_se)
