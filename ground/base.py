"""The base surface a volume is measured from: the floor plane z = 0, a plane fitted to the floor the LiDAR
saw, or the surface of an earlier survey (`pilescan-ground report --base`).

The volume is the volume between the survey's surface and the base, summed with its sign over every cell
that has a surface (eq. 7 with H_z less the base): material below the base counts negative. That keeps the
volume unbiased where the surface only wanders about the base with the sensor's noise (clipping at the
base would add half the noise everywhere), and it is the net change against an earlier survey. Survey tools
report cut and fill apart as well, and so does the report's ``base`` record: ``above_m3`` (material above
the base) and ``below_m3`` (room below it).

**Fitted floor.** The floor is the lowest large flat surface in the building: the plane z = a + b x + c y that the
most points lie on, within their noise, with (almost) none below it. Points on a pile's flat top are rejected by
"none below": the floor around the pile lies under that plane. The fit is RANSAC over three-point planes no
steeper than MAX_FLOOR_TILT_DEG (score: points within n sigma of the plane less points more than n sigma below it;
n is `ground.pointcloud.N_SIGMA`, 3, each point's vertical sigma from the sensor model in the log header), then a
weighted least-squares refit on the points from the deepest that noise alone reaches below the plane
(`structure_n_sigma` of their number) to n sigma above it, re-selected until they stop changing: points under a
floor are kept, not dropped as outliers, so the floor seen beyond a pile's long toe pulls back a plane the toe
tilted up. Each round also leaves out the cells whose points sit above the plane as a whole (`toe_cells`: a cell
median beyond what the cells' own scatter reaches): a toe's points each lie within the band, but a cell of them
does not lie about the plane as a floor cell does. Nothing is tuned: the band is the sensor's noise, the tilt
limit is a building fact. The plane's standard errors (scaled by the residuals' reduced chi-square, and by the
points per cell: neighbouring points share the pose's error, so one cell counts as one independent value) give the
base's own volume error over the surface's cells, added to the interval in quadrature at the interval's level.
Pile toes inside the band lie only above the floor and pull a least-squares plane up; the median of the residuals
is pulled less, so the plane is moved to it, and the move itself, over the surface's area, is added as a
systematic error (the data cannot say which of the two locations is right). Refused: fewer than MIN_FLOOR_POINTS
floor points, or floor points along a line (the cross-slope is unknown), or a plane steeper than the limit, or a plane
that lies on material (`on_material`: more points under it than its noise puts there and a floor's worth lower still;
the paper's pile 2, whose flank the plane climbed through the corner of floor at its foot, read 31.9 % low over it
with a 90 % interval that did not hold the truth).
Warned: more points over n sigma under the plane than its noise puts there (a binomial test at BELOW_FLOOR_ALPHA:
the plane climbs material lying on the floor, or the floor is not one plane), a plane more than its noise below
z = 0 somewhere in the building (the storage frame's z = 0 is its lowest floor corner; points below it were dropped
as glitches), and floor points that cover little of the building (the plane is then extrapolated under the piles).

**Earlier survey.** A report directory's saved surface (`ground.surface_file`) or a run directory's
(computed as its report would be). It must be of the same building (dimensions, and site when both logs
state one); a different cell size is resampled bilinearly, with a warning. The volume over it is the net
change since that survey, and its interval is exactly `pilescan-ground compare`'s for the net
(`ground.compare`: both surveys' own half-widths over the cells that changed, each cell's noise and any
offset between the flights over those that did not), not clipped at 0: material may have gone.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path
from statistics import NormalDist

import numpy as np
from scipy.special import betainc

from firmware_py.core.cli import UserError
from ground.compare import Z_INTERVAL, compare_surfaces
from ground.group_stats import medians_by_key
from ground.pointcloud import structure_n_sigma
from ground.surface import Grid, grid_volume
from ground.surface_file import SavedSurface, building_mismatch, resampled
from ground.uncertainty import ErrorTerms, IntervalModel, blur_term_m3, cell_index, unseen_terms_m3, widened_interval_m3

MAX_FLOOR_TILT_DEG = 5.0
"""The steepest plane taken as a building's floor: warehouse floors are laid to falls of 1-2 % (0.6-1.1 deg)
for drainage, and 5 deg (8.7 %) is already a vehicle ramp's grade; a steeper "floor" is a pile's flank."""
MIN_FLOOR_POINTS = 30
"""Fewest floor points a plane (3 parameters) is fitted to: ten per parameter, the usual minimum for a
regression whose residuals should say something about its fit."""
RANSAC_SAMPLE = 5_000
"""Points the RANSAC scores its candidate planes on (a seeded random subset: reports replay); the refit uses all."""
RANSAC_CONFIDENCE = 0.999
RANSAC_MAX_TRIALS = 5_000
BELOW_FLOOR_ALPHA = 0.01
"""The warning of points under a fitted floor fires when noise alone would put that many there with less than
this chance: one report in a hundred over a true floor at most, while a plane tilted through pile toes leaves
hundreds of times its noise's count (measured: docs/design-notes.md, "A fitted floor tilted through toes")."""
MIN_FLOOR_COVER = 0.05
"""Floor points spread over less than this share of the building's cells: the plane is extrapolated under
the piles from a corner, and the report says so."""


class BaseKind(Enum):
    FLOOR = "floor"
    FITTED_FLOOR = "fitted-floor"
    SURVEY = "survey"


@dataclass(frozen=True)
class BaseSpec:
    """What the user asked for: a kind, and for SURVEY the run or report directory."""

    kind: BaseKind = BaseKind.FLOOR
    source: Path | None = None

    @classmethod
    def parse(cls, text: str) -> BaseSpec:
        """`floor`, `fitted-floor`, or an existing run or report directory (checked when resolved)."""
        t = str(text).strip()
        if not t:
            raise UserError("--base must be floor, fitted-floor or a run or report directory, got an empty value")
        for kind in (BaseKind.FLOOR, BaseKind.FITTED_FLOOR):
            if t == kind.value:
                return cls(kind)
        return cls(BaseKind.SURVEY, Path(t))

    def __str__(self) -> str:
        return str(self.source) if self.kind is BaseKind.SURVEY else self.kind.value


FLOOR = BaseSpec()


LEAST_LAID_FALL_PCT = 1.0
"""The least fall a warehouse floor is laid to for drainage (1-2 %, as MAX_FLOOR_TILT_DEG says): a floor the pose
correction's floor route would leave falling this much was not moved by a height error (`FloorFall.laid`,
`ground.pose_correction.down_onto_a_fall`)."""
FLOOR_FALL_SHOWN_PCT = LEAST_LAID_FALL_PCT / 2.0
"""A floor's fall the report names (`FloorFall.laid_to_fall`): half the least a floor is laid to. A level floor's fit
away from material stays under it: at most 0.31 % over the 1,197 runs of the evaluation set whose piles leave the
floor bare (the whole plane's fit, which a pile's toes tilt, up to 0.53 %), while the lowest flat surface of material
covering the floor may fall more (11 of the 142 runs whose piles may hide it and that saw a floor not lying on
material, `on_material`: up to 5.4 %), which the report names alike (docs/pose_error.md,
`floor-level`)."""


@dataclass(frozen=True)
class FloorFall:
    """A floor's slope: its rise along x and along y (m/m)."""

    rise_x: float
    rise_y: float

    @property
    def fall_pct(self) -> float:
        return 100.0 * math.hypot(self.rise_x, self.rise_y)

    @property
    def rise_azimuth_deg(self) -> float:
        """The direction the floor rises in, from the building's x axis towards y."""
        return math.degrees(math.atan2(self.rise_y, self.rise_x))

    @property
    def laid_to_fall(self) -> bool:
        """It falls by more than a level floor's fit shows (`FLOOR_FALL_SHOWN_PCT`): named in the report."""
        return self.fall_pct >= FLOOR_FALL_SHOWN_PCT

    @property
    def laid(self) -> bool:
        """It falls as much as a floor is laid to (`LEAST_LAID_FALL_PCT`): no height error makes that."""
        return self.fall_pct >= LEAST_LAID_FALL_PCT


@dataclass(frozen=True)
class PlaneFit:
    """z = offset_m + slope_x * x + slope_y * y, fitted to n_points floor points."""

    offset_m: float
    slope_x: float
    slope_y: float
    covariance: np.ndarray  # (3, 3) of (offset, slope_x, slope_y), per-cell independence
    n_points: int
    n_cells: int
    rms_residual_m: float
    inliers: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=bool))
    median_shift_m: float = 0.0  # the least-squares plane less the median one: one-sided contamination (toes)

    @property
    def tilt_deg(self) -> float:
        return math.degrees(math.atan(math.hypot(self.slope_x, self.slope_y)))

    @property
    def fall(self) -> FloorFall:
        return FloorFall(self.slope_x, self.slope_y)

    @property
    def fall_pct(self) -> float:
        return self.fall.fall_pct

    @property
    def rise_azimuth_deg(self) -> float:
        """The direction the floor rises in, from the building's x axis towards y."""
        return self.fall.rise_azimuth_deg

    def at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return self.offset_m + self.slope_x * np.asarray(x) + self.slope_y * np.asarray(y)

    def volume_sigma_m3(self, grid: Grid, where: np.ndarray) -> float:
        """1-sigma error of the plane's volume over the cells `where` (from the parameters' covariance)."""
        cx, cy = grid.centres()
        g = grid.cell_area_m2 * np.array([where.sum(), cx[where].sum(), cy[where].sum()], dtype=float)
        return math.sqrt(max(0.0, float(g @ self.covariance @ g)))


def _planes(p: np.ndarray) -> np.ndarray:
    """(K, 3) coefficients (a, b, c) of z = a + b x + c y through each (K, 3, 3) triple; NaN if degenerate."""
    a = np.concatenate([np.ones((len(p), 3, 1)), p[:, :, :2]], axis=2)
    det = np.linalg.det(a)
    ok = np.abs(det) > 1e-9
    out = np.full((len(p), 3), np.nan)
    if ok.any():
        out[ok] = np.linalg.solve(a[ok], p[ok, :, 2][..., None])[..., 0]
    return out


def _refit(points: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares of z on (1, x, y); coefficients and (X^T W X)^-1."""
    x = np.column_stack([np.ones(len(points)), points[:, 0], points[:, 1]])
    xtw = x.T * w
    inv = np.linalg.inv(xtw @ x)
    return inv @ (xtw @ points[:, 2]), inv


def _check_spread(points: np.ndarray, cell_m: float, what: str) -> None:
    """UserError when the points lie along a line (less than a cell across it): no cross-slope to fit."""
    centred = points[:, :2] - points[:, :2].mean(axis=0)
    minor_m = math.sqrt(max(0.0, float(np.linalg.eigvalsh(centred.T @ centred / len(points))[0])))
    if minor_m < cell_m:
        raise UserError(f"--base fitted-floor: the {len(points)} {what} lie along a line (spread {minor_m:.2f} m "
                        "across it), so the floor's cross-slope is unknown")


def toe_cells(cell: np.ndarray, r_m: np.ndarray) -> np.ndarray:
    """The cells whose points, within a floor plane's band, sit above it as a whole: a pile's toe, not the floor.

    cell: each point's cell; r_m: its height above the plane. A floor cell's median residual scatters about the
    others' by the points' noise and the pose's error they share; a cell of toe sits above them all, though each of
    its points lies within its band (a band a few noise levels thick holds a gentle toe over metres). Flagged: a
    median more than `structure_n_sigma` of the number of cells (the deepest noise alone reaches among them) robust
    standard deviations above the cells' median. The spread is the cells' own, not the sensor model's: a model sized
    for the worst range of the flight puts the band's edge far beyond what most floor points scatter (8 cm stated,
    millimetres seen on a simulated flight), and that gap is where a toe hides. Measured on a 30 x 20 m flight whose
    floor was seen mostly in one corner: a handful of toe points in the other three corners tilted the plane 0.47
    deg, +8.6 cm at the building's centre; without their cells it lies within 0.2 cm of the floor."""
    if len(cell) == 0:
        return cell
    uniq, med, _ = medians_by_key(cell, r_m)
    centre = float(np.median(med))
    spread = 1.4826 * float(np.median(np.abs(med - centre))) or float(np.std(med))
    return uniq[med > centre + structure_n_sigma(len(uniq)) * max(spread, 1e-6)]


def fit_floor_plane(points_w: np.ndarray, sigma_m: np.ndarray, grid: Grid, n_sigma: float,
                    max_tilt_deg: float = MAX_FLOOR_TILT_DEG, seed: int = 0) -> PlaneFit:
    """The floor plane (module docstring) of the points (N, 3), each with its vertical 1-sigma error.

    Raises UserError when no plausible floor is found (too few points, points on a line, too steep)."""
    pts = np.asarray(points_w, dtype=float)
    sig = np.asarray(sigma_m, dtype=float)
    if len(pts) < MIN_FLOOR_POINTS:
        raise UserError(f"--base fitted-floor: only {len(pts)} points on the floor and piles, fewer than the "
                        f"{MIN_FLOOR_POINTS} a floor plane needs")
    cell_m = min(grid.length_m / grid.shape[0], grid.width_m / grid.shape[1])
    _check_spread(pts, cell_m, "points")
    band = n_sigma * np.maximum(sig, 1e-6)
    rng = np.random.default_rng(seed)
    sub = rng.choice(len(pts), min(len(pts), RANSAC_SAMPLE), replace=False)
    ps, bs = pts[sub], band[sub]
    # Triples are drawn from the lower half of the points: the floor lies under everything else, so this
    # only raises the chance of an all-floor triple; every candidate is still scored on all of ps.
    low = np.flatnonzero(ps[:, 2] <= np.median(ps[:, 2]))
    max_slope = math.tan(math.radians(max_tilt_deg))
    best, best_score, trials, done, batch = None, -np.inf, RANSAC_MAX_TRIALS, 0, 200
    while done < trials:
        k = min(batch, trials - done)
        planes = _planes(ps[low[rng.integers(0, len(low), (k, 3))]])
        planes = planes[np.isfinite(planes).all(axis=1) & (np.hypot(planes[:, 1], planes[:, 2]) <= max_slope)]
        done += k
        if not len(planes):
            continue
        r = ps[None, :, 2] - (planes[:, :1] + planes[:, 1:2] * ps[None, :, 0] + planes[:, 2:] * ps[None, :, 1])
        score = (np.abs(r) <= bs).sum(axis=1) - (r < -bs).sum(axis=1)
        i = int(np.argmax(score))
        if score[i] > best_score:
            best, best_score = planes[i], float(score[i])
            w = max(1e-6, min(1.0, (np.abs(r[i][low]) <= bs[low]).mean()))  # the adaptive RANSAC trial count
            need = math.log(1 - RANSAC_CONFIDENCE) / math.log(max(1e-12, 1 - w**3)) if w < 1 else 1
            trials = min(RANSAC_MAX_TRIALS, max(done, math.ceil(need)))
    if best is None:
        raise UserError(f"--base fitted-floor: no plane within {max_tilt_deg:g} deg of level fits the points")
    coef, inliers = best, np.zeros(len(pts), dtype=bool)
    # The refit keeps points below the band too, down to the deepest that noise alone reaches among these points
    # (a glitch beyond): a floor has nothing under it, so a plane tilted up through pile toes, which lifts it
    # off the floor seen elsewhere, is pulled back by that floor instead of dropping it as outliers.
    deep = structure_n_sigma(len(pts)) * np.maximum(sig, 1e-6)
    ix, iy = cell_index(pts, grid)
    cell = ix * grid.shape[1] + iy
    for _ in range(20):  # refit on the inliers until they stop changing
        r = pts[:, 2] - (coef[0] + coef[1] * pts[:, 0] + coef[2] * pts[:, 1])
        now = (r <= band) & (r >= -deep)
        now &= ~np.isin(cell, toe_cells(cell[now], r[now]))
        if now.sum() < MIN_FLOOR_POINTS:
            raise UserError(f"--base fitted-floor: only {int(now.sum())} points lie on a floor plane (within "
                            f"{n_sigma:.1f} sigma), fewer than the {MIN_FLOOR_POINTS} a plane needs: the floor "
                            "was hardly seen")
        if np.array_equal(now, inliers):
            break
        inliers = now
        coef, inv = _refit(pts[inliers], 1.0 / np.maximum(sig[inliers], 1e-6) ** 2)
    fp = pts[inliers]
    _check_spread(fp, cell_m, "floor points")
    tilt = math.degrees(math.atan(math.hypot(coef[1], coef[2])))
    if tilt > max_tilt_deg:
        raise UserError(f"--base fitted-floor: the fitted plane is tilted {tilt:.2f} deg, more than the "
                        f"{max_tilt_deg:g} deg a floor can be: not a floor")
    r = fp[:, 2] - (coef[0] + coef[1] * fp[:, 0] + coef[2] * fp[:, 1])
    w = 1.0 / np.maximum(sig[inliers], 1e-6) ** 2
    chi2 = float((w * r**2).sum()) / max(1, len(fp) - 3)
    # Pile toes within the band lie only above the floor: they pull the least-squares plane up, the median
    # of the residuals less. The plane is moved to the median, and the shift is kept as a systematic error.
    shift = float(np.median(r))
    coef = np.array([coef[0] + shift, coef[1], coef[2]])
    r = r - shift
    n_cells = len(np.unique(cell[inliers]))
    cov = inv * max(1.0, chi2) * len(fp) / max(1, n_cells)
    return PlaneFit(float(coef[0]), float(coef[1]), float(coef[2]), cov, len(fp), n_cells,
                    float(np.sqrt(np.mean(r**2))), inliers, shift)


@dataclass(frozen=True)
class BelowFloor:
    """The points more than n sigma below a fitted floor, against what its noise puts there."""

    count: int
    expected: float  # the normal tail beyond n sigma of the plane's floor points (its inliers)
    p_value: float  # the chance of at least `count` from noise alone (binomial)
    median_depth_m: float  # how far below the plane they lie (0 when none)


def binomial_tail(k: int, n: int, p: float) -> float:
    """P(X >= k) for X ~ Binomial(n, p): the regularised incomplete beta I_p(k, n - k + 1), what scipy.stats'
    binomial survival function computes, from scipy.special (importing scipy.stats added a quarter of a second to
    every `pilescan-ground` start: 0.99 -> 0.73 s without it)."""
    if k <= 0:
        return 1.0
    if k > n:
        return 0.0
    return float(betainc(k, n - k + 1, p))


def points_below(points_w: np.ndarray, sigma_m: np.ndarray, plane: PlaneFit, n_sigma: float) -> BelowFloor:
    """A floor has nothing under it but its own noise's tail; a plane tilted through pile toes leaves the floor
    seen elsewhere under it, by far more points than that tail (module docstring: the warning it gives)."""
    pts = np.asarray(points_w, dtype=float)
    r = (pts[:, 2] - plane.at(pts[:, 0], pts[:, 1])) / np.maximum(np.asarray(sigma_m, dtype=float), 1e-6)
    deep = r < -n_sigma
    tail = NormalDist().cdf(-n_sigma)
    n_floor = int((np.abs(r) <= n_sigma).sum())
    count = int(deep.sum())
    p = binomial_tail(count, n_floor, tail)
    depth = float(np.median(plane.at(pts[deep, 0], pts[deep, 1]) - pts[deep, 2])) if count else 0.0
    return BelowFloor(count, tail * n_floor, p, depth)


def on_material(under: BelowFloor, z_m: np.ndarray, band_m: np.ndarray, level_m: float) -> bool:
    """The plane with the most floor points lies on material, not on the floor: more points lie under it than its
    noise puts there (under: its `points_below`, at BELOW_FLOOR_ALPHA), and a floor's worth of the points (heights
    z_m, each with its band) lies lower, more than two bands under its level (`lowest_level_m`). Measured on the
    evaluation set: no run whose floor is in view has points under its plane beyond its noise (0 of 1,197); of the
    315 runs of piles that may hide the floor, 191 have, and the plane climbs material in those whose lowest points
    lie far under it (the paper's pile 2 leaves a corner of floor at the foot of its long flank, and the plane, through
    that corner, is 1.8 m up at its level and falls 3.9 %), while the floors under a few stray points stay within
    their band of the lowest."""
    if under.p_value >= BELOW_FLOOR_ALPHA:
        return False
    return level_m - lowest_level_m(z_m, band_m) > 2.0 * float(np.median(band_m))


def lowest_level_m(z_m: np.ndarray, band_m: np.ndarray) -> float:
    """The lowest height that holds a floor's worth of points (MIN_FLOOR_POINTS) within the points' median band
    either side of it: the median of the first such window from below (stray points under it are passed over)."""
    z = np.sort(np.asarray(z_m, dtype=float))
    if len(z) == 0:
        return math.nan  # nothing lies lower (on_material's comparison is then False)
    count = np.searchsorted(z, z + 2.0 * float(np.median(band_m)), side="right") - np.arange(len(z))
    first = int(np.argmax(count >= MIN_FLOOR_POINTS)) if (count >= MIN_FLOOR_POINTS).any() else 0
    return float(np.median(z[first:first + max(1, int(count[first]))]))


@dataclass(frozen=True)
class Base:
    """A resolved base: its heights on the survey's grid (None: z = 0 exactly) and what it adds to the interval."""

    kind: BaseKind
    description: str
    heights_m: np.ndarray | None = None
    extra_below_m3: float = 0.0  # the base's own error, 90 % half-widths added in quadrature
    extra_above_m3: float = 0.0
    clip_at_zero: bool = True  # a volume above a floor cannot be negative; a change from a survey can
    details: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    extra_over: Callable[[np.ndarray], float] | None = field(default=None, repr=False, compare=False)
    """The base's own 90 % half-width over a mask of cells (one pile's: ground.piles); None: nothing."""

    @property
    def piles_over(self) -> str:
        """What a pile table of this base measures its piles over (ground.piles): the base itself, except an
        earlier survey's, whose change per pile is `pilescan-ground compare`'s; the piles are then this survey's
        over the floor."""
        if self.kind is BaseKind.SURVEY:
            return ("the floor z = 0: the piles of this survey as they stand (the headline is the change since the "
                    "earlier survey; pilescan-ground compare gives the change per pile)")
        return "the floor z = 0" if self.kind is BaseKind.FLOOR else "the fitted floor plane"

    def pile_heights(self, heights: np.ndarray) -> np.ndarray:
        """The heights a pile table segments and sums: above this base, or above z = 0 for an earlier survey's."""
        return heights if self.kind is BaseKind.SURVEY else self.above(heights)

    def above(self, heights: np.ndarray) -> np.ndarray:
        """The surface's height above the base per cell (NaN where either has none)."""
        return heights if self.heights_m is None else heights - self.heights_m

    def volume_m3(self, heights: np.ndarray, grid: Grid) -> float:
        """Eq. (7) over the base: the signed sum (module docstring)."""
        return grid_volume(self.above(heights), grid)

    def interval_m3(self, volume_m3: float, terms: ErrorTerms, model: IntervalModel) -> tuple[float, float]:
        if self.kind is BaseKind.FLOOR:
            return model.interval_m3(volume_m3, terms)
        if self.kind is BaseKind.SURVEY:  # both surveys' errors, as `compare` combines them (extra_*: the sides)
            return volume_m3 - self.extra_below_m3, volume_m3 + self.extra_above_m3
        return widened_interval_m3(volume_m3, *model.half_widths_m3(terms), self.extra_below_m3, self.extra_above_m3,
                                   self.clip_at_zero)

    def record(self, heights: np.ndarray, grid: Grid) -> dict:
        """report.json's ``base``: which base, its details, material above it and room below it."""
        d = self.above(heights)
        return {"kind": self.kind.value, "description": self.description, **self.details,
                "above_m3": float(np.nansum(np.clip(d, 0.0, None)) * grid.cell_area_m2),
                "below_m3": float(np.nansum(np.clip(-d, 0.0, None)) * grid.cell_area_m2),
                "interval_extra_m3": [self.extra_below_m3, self.extra_above_m3]}


FLOOR_BASE = Base(BaseKind.FLOOR, "the floor plane z = 0")


def fitted_floor_base(points_w: np.ndarray, sigma_m: np.ndarray, heights: np.ndarray, grid: Grid,
                      n_sigma: float, max_tilt_deg: float = MAX_FLOOR_TILT_DEG) -> Base:
    plane = fit_floor_plane(points_w, sigma_m, grid, n_sigma, max_tilt_deg)
    pts = np.asarray(points_w, dtype=float)
    under = points_below(pts, sigma_m, plane, n_sigma)
    if on_material(under, pts[:, 2], n_sigma * np.asarray(sigma_m, dtype=float),
                   float(np.median(pts[plane.inliers, 2]))):
        raise UserError(f"--base fitted-floor: the plane the most points lie on lies on material, not on the floor "
                        f"({under.count} points under it where its noise would put {under.expected:.0f}, and a "
                        "floor's worth of points further down): the floor shows only at the material's foot, too "
                        "little to fit a plane to; report over the floor with --base floor")
    cx, cy = grid.centres()
    b = plane.at(cx, cy)
    surfaced = np.isfinite(heights)

    def errors_over(mask: np.ndarray) -> tuple[float, float]:
        """The plane's 1-sigma statistical volume error and its systematic (median shift) over the surfaced cells
        of mask: the whole survey's, or one pile's (`Base.extra_over`)."""
        where = surfaced & mask
        return (plane.volume_sigma_m3(grid, where),
                abs(plane.median_shift_m) * float(where.sum()) * grid.cell_area_m2)

    def extra_over(mask: np.ndarray) -> float:
        sigma, shift = errors_over(mask)
        return math.hypot(Z_INTERVAL * sigma, shift)

    sigma_v, systematic = errors_over(surfaced)
    extra = extra_over(surfaced)
    warnings = []
    noise = Z_INTERVAL * math.sqrt(max(0.0, float(plane.covariance[0, 0])))
    if float(b.min()) < -max(noise, plane.rms_residual_m):
        warnings.append(f"the fitted floor lies {-float(b.min()):.2f} m below z = 0 at its lowest: the building's "
                        "z = 0 should be its lowest floor corner, and floor points below z = 0 were left out as "
                        "glitches, so the floor there was not seen")
    # A floor's points scatter about it by their own noise; a plane laid through a pile's flank within the band
    # spreads them over the whole band. Their mean square in sigmas tells the two apart: about 1 for a floor (a
    # normal cut at n_sigma), n_sigma^2 / 3 for points spread evenly over the band; the warning sits midway.
    fp = pts[plane.inliers]
    r = fp[:, 2] - plane.at(fp[:, 0], fp[:, 1])
    spread = float(np.mean((r / np.maximum(np.asarray(sigma_m, dtype=float)[plane.inliers], 1e-6)) ** 2))
    if spread > (1.0 + n_sigma**2 / 3.0) / 2.0:
        warnings.append(f"the points taken for the floor scatter {plane.rms_residual_m:.2f} m (rms) about the fitted "
                        f"plane, {math.sqrt(spread):.1f} times their noise: they fill its band rather than lie on a "
                        "floor, so the plane may run through the piles (a floor the material hides); the volume over "
                        "it may be far off, compare it with --base floor")
    if under.p_value < BELOW_FLOOR_ALPHA:
        warnings.append(f"{under.count} points lie more than {n_sigma:g} sigma below the fitted floor (median "
                        f"{under.median_depth_m:.2f} m), where its noise would put {under.expected:.0f}: the plane "
                        "is tilted up through material lying on the floor (a pile's toes), or the floor is not one "
                        "plane, so the volume over it may be off; compare it with --base floor")
    cover = plane.n_cells / (grid.shape[0] * grid.shape[1])
    if cover < MIN_FLOOR_COVER:
        warnings.append(f"the floor was seen in only {cover * 100:.1f} % of the building's cells: the fitted floor "
                        "is extrapolated under the piles, and their toes may be taken for floor; compare the volume "
                        "with --base floor, or fly legs that see more of the floor")
    cl, cw = grid.length_m / 2, grid.width_m / 2
    desc = (f"a plane fitted to the floor: tilt {plane.tilt_deg:.2f} deg ({plane.fall_pct:.2f} % rising towards "
            f"{plane.rise_azimuth_deg:.0f} deg from x), {float(plane.at(cl, cw)):+.3f} m at the building's centre, "
            f"{plane.n_points} floor points")
    details = {"tilt_deg": plane.tilt_deg, "fall_pct": plane.fall_pct, "rise_azimuth_deg": plane.rise_azimuth_deg,
               "offset_at_origin_m": plane.offset_m, "offset_at_centre_m": float(plane.at(cl, cw)),
               "slope_x": plane.slope_x, "slope_y": plane.slope_y, "n_floor_points": plane.n_points,
               "n_floor_cells": plane.n_cells, "rms_residual_m": plane.rms_residual_m,
               "median_shift_m": plane.median_shift_m, "volume_sigma_m3": sigma_v, "systematic_m3": systematic,
               "max_tilt_deg": max_tilt_deg, "n_below_floor": under.count,
               "expected_below_floor": under.expected, "below_floor_p_value": under.p_value}
    return Base(BaseKind.FITTED_FLOOR, desc, b, extra, extra, True, details, tuple(warnings), extra_over)


def survey_base(earlier: SavedSurface, current: SavedSurface, source: str) -> Base:
    """An earlier survey's surface as the base of the current one (module docstring)."""
    why = building_mismatch(earlier, current)
    if why is not None:
        raise UserError(f"--base {source}: not the same building as this survey: {why}")
    grid = current.grid
    heights = resampled(earlier, grid)
    warnings = []
    resampled_from = None
    if heights is not earlier.heights_m:
        resampled_from = earlier.cell_m
        warnings.append(f"the base survey's {earlier.cell_m:g} m grid was resampled (bilinear) to this survey's "
                        f"{current.cell_m:g} m cells")
    missing = np.isfinite(current.heights_m) & ~np.isfinite(heights)
    if missing.any():
        warnings.append(f"the base survey has no surface under {int(missing.sum())} cells "
                        f"({missing.sum() * grid.cell_area_m2:,.0f} m²) of this one's: no volume counted there")
    desc = f"the surface of an earlier survey, {source} ({earlier.volume_m3:,.1f} m³ above z = 0)"
    details = {"source": source, "base_volume_m3": earlier.volume_m3,
               "base_half_widths_m3": [earlier.below_m3, earlier.above_m3], "resampled_from_cell_m": resampled_from}
    change = compare_surfaces(earlier, current)  # the same change, and interval, as `pilescan-ground compare`
    lo, hi = change.net_interval_m3
    details["level_of_detection_m"] = change.lod_m
    return Base(BaseKind.SURVEY, desc, heights, change.net_m3 - lo, hi - change.net_m3, False, details,
                tuple(warnings))


def rebased_terms(terms: ErrorTerms, heights_fit: np.ndarray, heights: np.ndarray, grid: Grid,
                  scatter_sigma_m: float, base: Base, roof_m: float, mask: np.ndarray | None = None,
                  edge_m: np.ndarray | None = None) -> ErrorTerms:
    """The terms that measure material from the floor (the unseen fill's lower bound, the blur's pile
    footprint) measured from a fitted floor instead; the others do not depend on the base, but for the pose
    and level terms: a height error common to the survey moves the floor fitted from its own points with the pile, so
    above that floor it cancels. Not the untied stretches' term: no floor was seen there, so the floor fitted
    elsewhere does not move with them. An earlier survey's base keeps the terms as they are: its own interval is
    added whole (module docstring). mask: the terms over those cells only (one pile's, as `terms` are). edge_m: the
    heights the unseen term takes its slope from (`ground.uncertainty.edge_heights_m`; None: heights_fit)."""
    if base.kind is not BaseKind.FITTED_FLOOR or base.heights_m is None:
        return terms
    low, high = unseen_terms_m3(heights_fit - base.heights_m, heights - base.heights_m, grid,
                                upper_m=roof_m - base.heights_m, mask=mask,
                                edge_m=None if edge_m is None else edge_m - base.heights_m)
    return replace(terms, unseen_low_m3=low, unseen_high_m3=high,
                   blur_m3=blur_term_m3(scatter_sigma_m, heights_fit - base.heights_m, grid, mask), pose_m3=0.0,
                   level_m3=0.0)
