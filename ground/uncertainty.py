"""A 90 % interval on the volume, from what the survey itself shows about its errors.

A grid volume is wrong for six reasons, each measurable in the survey that made it (all in m³,
each a scale of the error it describes, not yet a probability):

- **unseen**: cells the surface never reached were filled (``surface.fill_empty``). Nothing was
  measured there, but the seen surface at the region's edge says how fast the ground was changing
  where the measurements stopped: a cell at distance d from the nearest seen cell may lie about
  |grad h| d above or below what the fill copied (first order, as the interpolation term is second
  order between tracks; a flat edge gives no reason to expect a step, a flank gives a big one; the edge's slope is
  the steepest within a metre of the nearest seen cell, since the fit flattens at its very edge). The
  truth also lies between a lower bound (the floor, 0, unless a caller knows better) and an upper one
  (the roof, or the free space the beams crossed above it, ``ground.unseen``, when known). Low side:
  sum of min(|grad h| d, fill - lower bound); high side: sum of min(|grad h| d, upper bound - fill).
- **interpolation**: between sweep tracks the surface is guessed from its neighbours; the error of
  a smooth guess over a gap grows with the gap squared and the surface's curvature
  (d^2/2 |laplacian h| per cell, the textbook bound of piecewise-linear interpolation). The curvature is
  the fitted surface's, and a noisy fit's Laplacian holds its noise, which |.| would turn into bend: the
  noise's share, measured over the gaps, is taken out (``curvature_noise_m_inv``), and at least as much as
  the bridged floor, which is flat, shows at a like distance from the data (``floor_curvature_noise_m_inv``).
- **noise**: the points' scatter about the fitted surface, averaged over the seen cells (one
  independent value per cell: the errors of neighbouring points are not independent), the part a pose message's
  samples share (a simulated pose draw) added per message instead (``SharedDraws``).
- **blur**: the same scatter over the pile's footprint: noisy points blur a curved pile (high at the
  toes, low on the crests), an error of one sign over the pile that does not average out.
- **sweeps**: the mean height difference between rising and falling sweeps over the cells both
  saw, a systematic servo or mounting error the self-calibration left.
- **faces**: cells whose points lie further apart vertically than their cell's slope and the
  sensor's noise allow: an overhang or a vertical face, which one height per cell cannot hold;
  half that excess height over each such cell.
- **pose**: when the trajectory's height was corrected from the building (ground.pose_correction),
  the standard error of that correction's mean over the survey times the surfaced area: a height
  error common to the survey moves every cell (0 when no height was corrected).
- **level**: when the corrected trajectory's level rests on the logged altitude reference (no floor was
  seen, none the walls' feet confirm was kept, or the floor's height was refused), nothing in the data
  checks it: its error is the barometer's walk averaged over the flight
  (``ground.pose_height.level_sigma_m``) times the surfaced area. Not fitted: a Gaussian error of a
  stated sigma, so its 90 % half-width is LEVEL_Z sigmas. (A level anchored on a floor seen only away
  from the walls has no level term: the report warns with the other reading's volume and interval,
  ``ground.volume_warnings.open_floor_warning``.)
- **untied**: when the level rests on a floor but stretches of the flight saw neither that floor nor enough of the
  same pile again on passes that did (``ground.pose_height.MIN_TIE_CELLS`` cells, over routes that share none), the
  height there rests on the pile seen from one moment to the next, or on a handful of cells, and the data
  do not check the altitude reference's drift over the stretch: the walk pinned at the tied moments, averaged over
  each stretch and weighted by its share of the flight (``ground.pose_height.untied_sigma_m``), times the
  surfaced area. Not fitted either: LEVEL_Z sigmas.

The interval combines them in quadrature with one scale factor each (``IntervalModel``). The
factors are not tuned by hand: ``tools/calibrate_interval.py`` fits them on the calibration part of
a large evaluation set of simulated surveys (piles, buildings, altitudes, P_traj, servo phases,
noise models) as the smallest median width that holds the truth in 90 % of those surveys, and
reports the coverage on the held-out part (docs/uncertainty.md). Those surveys fly the true pose, so
the pose term's factor is fitted apart, on drifting flights (``tools/calibrate_pose_interval.py``:
the paper's piles to fit, other piles in another building and noisy flights held out).
"""

from __future__ import annotations

import functools
import math
import statistics
from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

from ground import smoothing
from ground.carry_down import SLOPE_RADIUS_M
from ground.plane_stretches import STEEPEST_PILE_DEG
from ground.surface import Grid, fill_empty

INTERVAL_LEVEL = 0.90
"""The probability the interval is calibrated to hold the true volume."""


@dataclass(frozen=True)
class ErrorTerms:
    """The survey's error scales in m³ (module docstring)."""

    unseen_low_m3: float = 0.0
    unseen_high_m3: float = 0.0
    interpolation_m3: float = 0.0
    noise_m3: float = 0.0
    sweeps_m3: float = 0.0
    faces_m3: float = 0.0
    blur_m3: float = 0.0
    pose_m3: float = 0.0
    level_m3: float = 0.0
    untied_m3: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


# --- calibrated pose factor (tools/calibrate_pose_interval.py --write-model) ---
POSE_FACTOR = 6.953366151617167
POSE_FACTOR_SOURCE = 'fitted on 38 drifting flights (tools/calibrate_pose_interval.py, 2026-12-06)'
# --- end of calibrated pose factor ---


LEVEL_Z = 1.6448536269514722
"""The standard normal's 95th percentile: a two-sided 90 % interval of a Gaussian error is +/- this many sigmas (the
level term's factor: its sigma is stated by the drift model, not fitted)."""


@dataclass(frozen=True)
class IntervalModel:
    """One scale factor per error term; 90 % of calibration surveys fall inside k-scaled quadrature sums."""

    k_unseen: float
    k_interpolation: float
    k_noise: float
    k_sweeps: float
    k_faces: float
    k_blur: float = 0.0
    source: str = "uncalibrated"
    k_pose: float = POSE_FACTOR
    """The pose term's: fitted on drifting flights, apart from the others (module docstring)."""
    k_level: float = LEVEL_Z
    """The level term's: not fitted, the normal's (its sigma is stated by the drift model: module docstring)."""
    k_untied: float = LEVEL_Z
    """The untied stretches' term's: not fitted, as the level's."""

    def __post_init__(self) -> None:
        for name in ("k_unseen", "k_interpolation", "k_noise", "k_sweeps", "k_faces", "k_blur", "k_pose", "k_level",
                     "k_untied"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"interval model {name} must be a finite number >= 0, got {v!r}")

    def half_widths_m3(self, t: ErrorTerms) -> tuple[float, float]:
        """(below, above) the volume."""
        common = ((self.k_interpolation * t.interpolation_m3) ** 2 + (self.k_noise * t.noise_m3) ** 2
                  + (self.k_sweeps * t.sweeps_m3) ** 2 + (self.k_faces * t.faces_m3) ** 2
                  + (self.k_blur * t.blur_m3) ** 2 + (self.k_pose * t.pose_m3) ** 2
                  + (self.k_level * t.level_m3) ** 2 + (self.k_untied * t.untied_m3) ** 2)
        return (math.sqrt(common + (self.k_unseen * t.unseen_low_m3) ** 2),
                math.sqrt(common + (self.k_unseen * t.unseen_high_m3) ** 2))

    def unseen_m3(self, t: ErrorTerms) -> float:
        """The unseen term's part of the interval: its larger side, scaled (what the volume warnings and the verdict
        weigh it by)."""
        return self.k_unseen * max(t.unseen_low_m3, t.unseen_high_m3)

    def interval_m3(self, volume_m3: float, t: ErrorTerms) -> tuple[float, float]:
        """The interval, never below 0 (a volume cannot be negative, whatever the noise made of it)."""
        below, above = self.half_widths_m3(t)
        return max(0.0, volume_m3 - below), max(0.0, volume_m3 + above)


def widened_interval_m3(volume_m3: float, below_m3: float, above_m3: float, extra_below_m3: float,
                        extra_above_m3: float, clip_at_zero: bool = True) -> tuple[float, float]:
    """The interval of half-widths (below, above) widened in quadrature by a base's own error on each side: the
    survey's over a fitted floor (`ground.base.Base.interval_m3`), and each pile's over it with the base's error
    over the pile's cells (ground.piles)."""
    lo, hi = volume_m3 - math.hypot(below_m3, extra_below_m3), volume_m3 + math.hypot(above_m3, extra_above_m3)
    return (max(0.0, lo), max(0.0, hi)) if clip_at_zero else (lo, hi)


# --- calibrated interval model (tools/calibrate_interval.py --write-model) ---
DEFAULT_INTERVAL_MODEL = IntervalModel(
    k_unseen=0.613766,
    k_interpolation=1.74426,
    k_noise=4.48864,
    k_sweeps=0.525708,
    k_faces=0.254651,
    k_blur=0.0939729,
    source='fitted on 693 calibration runs of the evaluation set (tools/calibrate_interval.py, 2026-12-05)')
# --- end of calibrated interval model ---


# ----- the terms -----------------------------------------------------------------------------------

def cell_index(points_xy: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """(ix, iy) of each point's cell, clamped to the grid (a point on the far wall is in the last cell)."""
    nx, ny = grid.shape
    flat = smoothing.cell_index(points_xy, grid.shape, (grid.length_m / nx, grid.width_m / ny))
    return flat // ny, flat % ny


def edge_slope(heights_fit: np.ndarray, grid: Grid) -> np.ndarray:
    """|grad h| of the fitted surface in each surfaced cell (NaN elsewhere), from the differences to the
    surfaced neighbours only: at the surface's edge that is the one-sided slope where the measurements
    stopped, not a slope half-flattened by the fill beside it."""
    nx, ny = heights_fit.shape
    steps = (grid.length_m / nx, grid.width_m / ny)
    grads = []
    for axis, step in enumerate(steps):
        d = np.diff(heights_fit, axis=axis) / step  # NaN where either cell is unsurfaced
        pad_lo = [(0, 0), (0, 0)]
        pad_hi = [(0, 0), (0, 0)]
        pad_lo[axis], pad_hi[axis] = (1, 0), (0, 1)
        both = np.stack([np.pad(d, pad_lo, constant_values=np.nan), np.pad(d, pad_hi, constant_values=np.nan)])
        n = np.isfinite(both).sum(axis=0)
        grads.append(np.where(n > 0, np.nansum(both, axis=0) / np.maximum(n, 1), 0.0))
    g = np.hypot(*grads)
    return np.where(np.isfinite(heights_fit), g, np.nan)


EDGE_SLOPE_RADIUS_M = SLOPE_RADIUS_M
"""How far around the nearest surfaced cell the unseen term looks for the slope where sight stopped (`unseen_reach_m`):
the `carry-down` fill's own window. At the surface's edge the fit is flattened (an estimator's window reaches past
the last points), so the one cell's slope can read near zero on a flank that climbs on into the unseen corner."""


def unseen_reach_m(heights_fit: np.ndarray, grid: Grid, edge_m: np.ndarray | None = None) -> np.ndarray:
    """Per cell outside the surface, the steepest |grad h| of the surfaced cells within EDGE_SLOPE_RADIUS_M of the
    nearest surfaced cell, times the distance to it: how far the ground there may be from the fill's copy (module
    docstring); 0 in surfaced cells. edge_m: the heights to take that slope from in the surfaced cells (None:
    heights_fit's; `edge_heights_m`)."""
    seen = np.isfinite(heights_fit)
    out = np.zeros(heights_fit.shape)
    if seen.all() or not seen.any():
        return out
    steps = grid.cell_xy_m
    dist, (ix, iy) = ndimage.distance_transform_edt(~seen, sampling=steps, return_indices=True)
    window = tuple(2 * max(0, round(EDGE_SLOPE_RADIUS_M / step)) + 1 for step in steps)
    slope = ndimage.maximum_filter(np.nan_to_num(edge_slope(edge_heights_m(heights_fit, edge_m), grid), nan=0.0),
                                   size=window)
    out[~seen] = (slope[ix, iy] * dist)[~seen]
    return out


def edge_heights_m(heights_fit: np.ndarray, edge_m: np.ndarray | None) -> np.ndarray:
    """The surfaced cells' heights to take the slope where sight stopped from: edge_m's where both surfaced (None:
    heights_fit). With the GP's slopes edge_m is the same nodes' cubic with scipy's slopes
    (`ground.surface.SurfaceFit`): the GP smooths the edge nodes' heights and so flattens the slope the unseen
    ground may keep on at. Measured with `--surface-slopes gp-bridges` (docs/design-notes.md, "GP slopes at the
    bridges only" and "`gp-bridges` the default"): on a flight whose unseen floor lay out of the rangefinder's reach
    the term fell 214 -> 165 m³ while the fill there grew 279 -> 346 m³, and the interval's held-out coverage fell to
    94.2 %; with scipy's slopes at the edge 95.2 %."""
    if edge_m is None:
        return heights_fit
    seen = np.isfinite(heights_fit)
    return np.where(seen & np.isfinite(edge_m), edge_m, heights_fit)


def unseen_terms_m3(heights_fit: np.ndarray, heights: np.ndarray, grid: Grid,
                    lower_m: np.ndarray | None = None, upper_m: np.ndarray | float | None = None,
                    mask: np.ndarray | None = None, edge_m: np.ndarray | None = None) -> tuple[float, float]:
    """(low, high) error scales of the filled cells (module docstring); bounds are per-cell arrays, a
    number (the roof) or None (unbounded). With mask, only its cells count (one pile's: the terms are
    per-cell sums, so the piles' add up to the whole). edge_m: the heights the slope where sight stopped is taken
    from (`edge_heights_m`; None: heights_fit).

    Cells left empty (`--empty-cells leave`) hold no volume, so nothing was invented (low 0) but the
    material the nearest surface suggests there may be missing: that is the high side."""
    filled = ~np.isfinite(heights_fit)
    counted = filled if mask is None else filled & np.asarray(mask, dtype=bool)
    if not counted.any():
        return 0.0, 0.0
    if not np.isfinite(heights[filled]).any() and np.isfinite(heights_fit).any():  # left empty
        nearest = fill_empty(heights_fit, "nearest")[counted]
        return 0.0, float(np.clip(nearest, 0.0, None).sum() * grid.cell_area_m2)
    reach = unseen_reach_m(heights_fit, grid, edge_m)[counted]
    h = np.where(np.isfinite(heights), heights, 0.0)[counted]
    lo = np.zeros_like(h) if lower_m is None else np.nan_to_num(np.asarray(lower_m, float)[counted], nan=0.0)
    low = float(np.minimum(reach, np.clip(h - lo, 0.0, None)).sum() * grid.cell_area_m2)
    if upper_m is None:
        hi = np.full_like(h, np.inf)
    else:
        hi = np.broadcast_to(np.asarray(upper_m, float), heights.shape)[counted]
        hi = np.where(np.isnan(hi), np.inf, hi)  # no bound known in that cell
    return low, float(np.minimum(reach, np.clip(hi - h, 0.0, None)).sum() * grid.cell_area_m2)


def interpolation_term_m3(heights_fit: np.ndarray, counts: np.ndarray, grid: Grid,
                          mask: np.ndarray | None = None, scatter_m: float = 0.0) -> float:
    """Sum over surfaced cells without points of d^2/2 |laplacian h| times the cell area (d: distance
    to the nearest cell holding points); over the cells of mask only when given (one pile's). scatter_m: the
    points' scatter about the surface (`scatter_sigma_m`), which bounds the share of the curvature taken as
    noise (`curvature_noise_m_inv`); 0 takes none of it as noise."""
    seen = np.isfinite(heights_fit)
    all_gaps = seen & (counts == 0)
    gaps = all_gaps & (True if mask is None else mask)
    if not gaps.any() or not (counts > 0).any():
        return 0.0
    c = grid.length_m / grid.shape[0], grid.width_m / grid.shape[1]
    d_m = ndimage.distance_transform_edt(counts == 0, sampling=c)
    # Curvature at the scale of the gaps: the one-cell Laplacian of a noisy fit is its noise, not the
    # bend an interpolant misses over a gap of d, so it is averaged over the gaps' typical size.
    h = np.where(seen, heights_fit, 0.0)
    _, (ix, iy) = ndimage.distance_transform_edt(~seen, return_indices=True)
    h = h[ix, iy]
    lap = np.zeros_like(h)
    for axis, step in ((0, c[0]), (1, c[1])):
        if h.shape[axis] >= 3:
            second = np.zeros_like(h)
            inner = [slice(None)] * 2
            inner[axis] = slice(1, -1)
            second[tuple(inner)] = np.diff(h, n=2, axis=axis) / step**2
            lap += second
    # The scale is the whole survey's, whatever the mask: a pile's term is then its share of the survey's (the
    # piles' terms and the rest's add up to it), where a pile's own gaps' scale made a pile's exceed the whole's.
    scale_cells = max(1.0, float(np.median(d_m[all_gaps])) / min(c))
    lap = ndimage.gaussian_filter(lap, scale_cells, mode="nearest")
    tau = curvature_noise_m_inv(lap[all_gaps], scale_cells, c, scatter_m)
    if scatter_m > 0:  # at least the noise the flat floor's bridges show at a like distance (the whole survey's)
        band_m = FLOOR_BAND_SIGMAS * max(scatter_m, MIN_FLOOR_BAND_M)
        # the floor's interior, where the Laplacian's stencil and filter see no toe (whose kink is bend); closed
        # first, so that the noise's own tail (a cell out of the band here and there) does not erode it away
        reach = round(scale_cells) + 1
        on_floor = ndimage.binary_erosion(ndimage.binary_closing(
            np.abs(np.where(seen, heights_fit, np.inf)) < band_m, iterations=reach), iterations=reach)
        floor_tau = floor_curvature_noise_m_inv(lap[all_gaps], d_m[all_gaps] / min(c), on_floor[all_gaps],
                                                FLOOR_NOISE_Z * scatter_m * laplacian_peak_gain_m2_inv(scale_cells, c))
        tau = np.maximum(tau, floor_tau[gaps[all_gaps]])
    bend = np.sqrt(np.maximum(lap[gaps] ** 2 - tau**2, 0.0))
    return float((0.5 * d_m[gaps] ** 2 * bend).sum() * grid.cell_area_m2)


FLOOR_NOISE_QUANTILE = 0.95
"""Curvature on the bridged floor below this quantile of its |L| is taken as noise (`floor_curvature_noise_m_inv`):
a one-sided 95 % level, the curvature a cell must exceed before it counts as bend. Measured on the evaluation set
against 0.80, 0.90 and 0.99 (docs/design-notes.md, "The interpolation term: the floor's bridges say what noise
bends"); all four narrowed the held-out intervals by a fifth."""
FLOOR_NOISE_Z = statistics.NormalDist().inv_cdf(0.5 + 0.5 * FLOOR_NOISE_QUANTILE)
"""That quantile of |L| for Gaussian noise, in its standard deviations (1.96): the cap on the floor's quantile is the
most the points' scatter can put into L's standard deviation (`curvature_noise_m_inv`) times this."""
GAP_BINS_CELLS = (2.0, 4.0, 8.0, 16.0)
"""Edges of the gap-distance bins (in cells, from the nearest cell with points) over which the floor's noise is
measured: the noise's |L| does not fall with the distance, while d^2/2 grows with it, so each distance gets its own."""
MIN_FLOOR_CELLS = 30
"""Floor cells a distance bin needs for its own quantile; a bin with fewer takes the nearer bin's."""
FLOOR_BAND_SIGMAS = 2.0
"""A surfaced cell is on the floor when its height is within this many of the points' scatters of z = 0 (and so
are its neighbours, as far as the term's filter reaches: a pile's toe is not floor)."""
MIN_FLOOR_BAND_M = 0.01
"""The scatter the floor band assumes at least: the rangefinder's 1 cm range quantum (LIDAR-Lite v3)."""


def floor_curvature_noise_m_inv(lap_at_gaps: np.ndarray, d_cells: np.ndarray, on_floor: np.ndarray,
                                cap: float) -> np.ndarray:
    """Per gap cell, the noise's |L| at its distance from the data (1/m): FLOOR_NOISE_QUANTILE of |L| over the gap
    cells on the floor in its distance bin (GAP_BINS_CELLS), where the truth is flat and L is noise alone; a bin of
    fewer than MIN_FLOOR_CELLS floor cells takes the nearer bin's, 0 before any. Capped by cap (the caller's: that
    quantile of the most the points' scatter can put into L, FLOOR_NOISE_Z), so a quiet survey keeps its bend.

    Why: much of the term's noise sat on the floor far from the fan lines (a building's corners, where the vehicle
    turns, and the bare floor between heaps): over the evaluation set about half of a noisy survey's term lay on floor
    cells, whose true bend is 0, and on the surveys traced |L| there was as large 3 m from the data as at 0.5 m, where
    d^2/2 is 36 times smaller.
    One spread for the whole survey (`curvature_noise_m_inv`) is set by the many near cells and leaves that tail."""
    tau = np.zeros(len(lap_at_gaps))
    if cap <= 0:
        return tau
    bins = np.digitize(d_cells, GAP_BINS_CELLS)
    level = None
    for b in range(len(GAP_BINS_CELLS) + 1):
        ref = (bins == b) & on_floor
        if ref.sum() >= MIN_FLOOR_CELLS:
            level = min(float(np.quantile(np.abs(lap_at_gaps[ref]), FLOOR_NOISE_QUANTILE)), cap)
        if level is not None:
            tau[bins == b] = level
    return tau


def curvature_noise_m_inv(lap_at_gaps: np.ndarray, scale_cells: float, cell_m: tuple[float, float],
                          scatter_m: float) -> float:
    """The noise's share of the smoothed Laplacian at the gaps (1/m, one sigma), which the interpolation term
    takes out: E[L^2] = bend^2 + tau^2 for a noisy L, so sqrt(L^2 - tau^2) estimates the bend, where |L| alone
    rectifies noise into curvature (a noisy flat floor bridged between far fan lines read as bend: over the
    evaluation set the term was a median 4.6 times its noise-free twin's under the datasheet's noise, 9 times under
    Appendix A's).

    tau is measured in the survey itself: the robust spread (1.4826 x median |L|) over the gaps, most of which
    lie on floor and planar flanks, where the true Laplacian is zero. It is capped by the largest noise the
    points' scatter can put into L (scatter_m times the filter's peak gain: no fitted height is noisier than
    one point), so a quiet survey of a curved surface, whose spread is its curvature, keeps its bend."""
    if scatter_m <= 0 or not len(lap_at_gaps):
        return 0.0
    spread = 1.4826 * float(np.median(np.abs(lap_at_gaps)))
    return min(spread, scatter_m * laplacian_peak_gain_m2_inv(scale_cells, cell_m))


@functools.lru_cache(maxsize=32)
def laplacian_peak_gain_m2_inv(scale_cells: float, cell_m: tuple[float, float]) -> float:
    """The largest gain over all wavelengths of the term's filter (the grid's second differences, then a Gaussian
    of scale_cells cells), 1/m^2: the most a height noise of 1 m, of any spatial pattern, can put into L."""
    n = max(64, 2 ** math.ceil(math.log2(8 * scale_cells + 8)))
    wx = 2 * np.pi * np.fft.fftfreq(n)[:, None]
    wy = 2 * np.pi * np.fft.fftfreq(n)[None, :]
    second = 4 * np.sin(wx / 2) ** 2 / cell_m[0] ** 2 + 4 * np.sin(wy / 2) ** 2 / cell_m[1] ** 2
    return float((second * np.exp(-0.5 * scale_cells**2 * (wx**2 + wy**2))).max())


def point_residuals_m(points_w: np.ndarray, heights_fit: np.ndarray, grid: Grid) -> np.ndarray:
    """Each point's height above the fitted surface, interpolated bilinearly between cell centres at the
    point (so a slope within a cell is not scatter); NaN where the surface is undefined."""
    nx, ny = grid.shape
    fx = np.clip(points_w[:, 0] / grid.length_m * nx - 0.5, 0.0, nx - 1.0)
    fy = np.clip(points_w[:, 1] / grid.width_m * ny - 0.5, 0.0, ny - 1.0)
    surface = ndimage.map_coordinates(np.nan_to_num(heights_fit, nan=0.0), [fx, fy], order=1, mode="nearest")
    defined = ndimage.map_coordinates(np.isfinite(heights_fit).astype(float), [fx, fy], order=1, mode="nearest")
    return np.where(defined > 0.999, points_w[:, 2] - surface, np.nan)


def scatter_sigma_m(points_w: np.ndarray, heights_fit: np.ndarray, grid: Grid) -> float:
    """The points' robust scatter about the fitted surface (1.4826 MAD of their residuals); 0 with too few."""
    if len(points_w) < 2:
        return 0.0
    r = point_residuals_m(points_w, heights_fit, grid)
    r = r[np.isfinite(r)]
    return 1.4826 * float(np.median(np.abs(r - np.median(r)))) if len(r) >= 2 else 0.0


@dataclass(frozen=True)
class SharedDraws:
    """The part of the points' error that the samples between two pose messages share: a simulated pose error is one
    draw per message (the header's ``sensor_noise`` record: position sigma and message rate), and the payload tags
    the ten or so samples between two messages from the same two draws, a metre or more of fan line moved as one."""

    sigma_m: float
    group: np.ndarray  # (n,) each point's pose message interval (its time times the message rate, floored)


def shared_draws(t_s: np.ndarray | None, sigma_m: float, stream_hz: float) -> SharedDraws | None:
    """The points' shared pose draws from their sample times; None without times or without such a draw."""
    if t_s is None or not (sigma_m > 0 and stream_hz > 0):
        return None
    return SharedDraws(float(sigma_m), np.floor(np.asarray(t_s, dtype=float) * stream_hz).astype(np.int64))


def noise_term_m3(sigma: float, heights_fit: np.ndarray, counts: np.ndarray, grid: Grid,
                  mask: np.ndarray | None = None, points_xy: np.ndarray | None = None,
                  shared: SharedDraws | None = None) -> float:
    """The points' scatter sigma carried into the volume: every surfaced cell takes its height from the
    nearest cell holding points, so a cell j of n_j points whose error (sigma / sqrt(n_j)) spreads over
    an area a_j contributes a_j sigma / sqrt(n_j); independent cells add in quadrature.

    With shared draws (and the points, points_xy, in the order of shared.group) the part of sigma they state is not
    independent from point to point: each point stands for a_j / n_j of the area, and the points of one pose message
    move together, so that part adds as sigma_shared^2 times the sum over messages of their areas squared; the rest,
    sigma^2 - sigma_shared^2, as before. Counted as independent, the shared part looked ten times smaller than it
    is, and the interval's fit made up for it with a noise factor that then over-covered every survey without it."""
    seen = np.isfinite(heights_fit)
    if sigma <= 0 or not (counts > 0).any():
        return 0.0
    c = grid.length_m / grid.shape[0], grid.width_m / grid.shape[1]
    _, (ix, iy) = ndimage.distance_transform_edt(counts == 0, sampling=c, return_indices=True)
    owner = (ix * grid.shape[1] + iy)[seen & (True if mask is None else mask)]
    area_cells = np.bincount(owner, minlength=counts.size)
    n = counts.ravel()
    has = (area_cells > 0) & (n > 0)
    independent = float((area_cells[has] ** 2 / n[has]).sum())
    if shared is None or points_xy is None or not len(points_xy):
        return sigma * grid.cell_area_m2 * math.sqrt(independent)
    px, py = cell_index(np.asarray(points_xy, dtype=float), grid)
    flat = px * grid.shape[1] + py
    per_point = np.where(n[flat] > 0, area_cells[flat] / np.maximum(n[flat], 1), 0.0)  # area each point stands for
    _, message = np.unique(shared.group, return_inverse=True)
    together = float((np.bincount(message, weights=per_point) ** 2).sum())
    var = max(sigma**2 - shared.sigma_m**2, 0.0) * independent + shared.sigma_m**2 * together
    return grid.cell_area_m2 * math.sqrt(var)


def blur_term_m3(sigma: float, heights_fit: np.ndarray, grid: Grid, mask: np.ndarray | None = None) -> float:
    """The scatter sigma over the pile's footprint (cells more than 2 sigma above the floor): noisy
    points blur a curved pile, and that error has one sign over the whole pile (points sit high at
    the toes, low on the crests), so it does not average out as the noise term assumes."""
    if sigma <= 0:
        return 0.0
    material = np.isfinite(heights_fit) & (np.nan_to_num(heights_fit, nan=0.0) > 2.0 * sigma) \
        & (True if mask is None else mask)
    return sigma * float(material.sum()) * grid.cell_area_m2


def sweeps_term_m3(points_w: np.ndarray, sweep_dir: np.ndarray | None, heights_fit: np.ndarray, grid: Grid,
                   min_points: int = 2, mask: np.ndarray | None = None) -> float:
    """Half the mean (rising - falling) height difference over cells both saw, times those cells' area."""
    if sweep_dir is None or len(points_w) == 0:
        return 0.0
    ix, iy = cell_index(points_w, grid)
    flat = ix * grid.shape[1] + iy
    n_all = grid.shape[0] * grid.shape[1]
    means, counts = [], []
    r = point_residuals_m(points_w, heights_fit, grid)  # heights less the surface: a slope is no difference
    ok = np.isfinite(r)
    for direction in (1, -1):
        m = (np.asarray(sweep_dir) == direction) & ok
        c = np.bincount(flat[m], minlength=n_all)
        s = np.bincount(flat[m], weights=r[m], minlength=n_all)
        counts.append(c)
        means.append(s / np.maximum(c, 1))
    both = (counts[0] >= min_points) & (counts[1] >= min_points) & (True if mask is None else mask.ravel())
    if not both.any():
        return 0.0
    return 0.5 * abs(float(np.mean(means[0][both] - means[1][both]))) * int(both.sum()) * grid.cell_area_m2


@dataclass(frozen=True)
class FaceCells:
    """Cells whose points disagree vertically beyond their slope and noise (see `face_cells`)."""

    mask: np.ndarray  # (nx, ny) bool
    excess_m: np.ndarray  # (nx, ny) vertical spread beyond what the cell's slope and noise allow; 0 elsewhere

    @property
    def n(self) -> int:
        return int(self.mask.sum())


MAX_SLOPE_DEG = STEEPEST_PILE_DEG
"""The steepest surface a stockpile can hold: loose bulk material stands at its angle of repose, 30-45
degrees for grains, coal, ores and aggregates; 60 leaves room for cohesive or compacted faces. Points in
one cell further apart than this slope across the cell (and the noise) are a vertical face or an overhang."""


def face_spread_m(grid: Grid, point_sigma_m: float, n_sigma: float, max_slope_deg: float = MAX_SLOPE_DEG) -> float:
    """The most height the points of one cell may span on a pile: the steepest slope across the cell's
    diagonal plus n_sigma point sigmas each way."""
    diagonal_m = math.hypot(grid.length_m / grid.shape[0], grid.width_m / grid.shape[1])
    return diagonal_m * math.tan(math.radians(max_slope_deg)) + 2.0 * n_sigma * point_sigma_m


def cell_spread_m(points_w: np.ndarray, grid: Grid) -> np.ndarray:
    """(nx, ny) max - min height of each cell's points (0 where fewer than one)."""
    nx, ny = grid.shape
    if len(points_w) == 0:
        return np.zeros((nx, ny))
    ix, iy = cell_index(points_w, grid)
    flat = ix * ny + iy
    zmax = np.full(nx * ny, -np.inf)
    zmin = np.full(nx * ny, np.inf)
    np.maximum.at(zmax, flat, points_w[:, 2])
    np.minimum.at(zmin, flat, points_w[:, 2])
    spread = (zmax - zmin).reshape(nx, ny)
    spread[~np.isfinite(spread)] = 0.0
    return spread


def face_cells(points_w: np.ndarray, grid: Grid, point_sigma_m: float, n_sigma: float,
               max_slope_deg: float = MAX_SLOPE_DEG) -> FaceCells:
    """Cells whose points span more height than a max_slope_deg slope across the cell's diagonal plus
    n_sigma point sigmas each way: a vertical face or an overhang."""
    spread = cell_spread_m(points_w, grid)
    excess = np.clip(spread - face_spread_m(grid, point_sigma_m, n_sigma, max_slope_deg), 0.0, None)
    return FaceCells(excess > 0, excess)


def faces_term_m3(faces: FaceCells, grid: Grid, mask: np.ndarray | None = None) -> float:
    return float(0.5 * faces.excess_m[True if mask is None else mask].sum() * grid.cell_area_m2)


# ----- one survey ------------------------------------------------------------------------------------

def point_sigma_m(range_m: np.ndarray, range_sigma: np.ndarray, position_sigma_m: float,
                  angle_sigma_rad: float) -> float:
    """A typical (median) point's 1-sigma height error: its range error, the vehicle's position error and
    the pointing error at its range (r sigma_angle: the most a small rotation moves it vertically)."""
    if len(range_m) == 0:
        return 0.0
    r = float(np.median(range_m))
    return math.sqrt(float(np.median(range_sigma)) ** 2 + position_sigma_m**2 + (r * angle_sigma_rad) ** 2)


@dataclass(frozen=True)
class SurveyErrors:
    """The error terms of one survey and the cells behind them (for warnings and figures)."""

    terms: ErrorTerms
    faces: FaceCells
    point_sigma_m: float


def over_surface_m3(height_m: float, heights: np.ndarray, grid: Grid, mask: np.ndarray | None = None) -> float:
    """What moving the whole surface up by height_m moves the volume by: that height over the surfaced cells (of
    mask), m³ (signed as height_m)."""
    cells = np.isfinite(heights) if mask is None else np.isfinite(heights) & mask
    return float(height_m * np.count_nonzero(cells) * grid.cell_area_m2)


def pose_term_m3(height_sigma_m: float | None, heights: np.ndarray, grid: Grid,
                 mask: np.ndarray | None = None) -> float:
    """The pose term: the height correction's standard error over the surfaced cells (of mask), m³; also the level
    term, of the level's standard error (module docstring)."""
    if not height_sigma_m:
        return 0.0
    return over_surface_m3(height_sigma_m, heights, grid, mask)


def survey_errors(points_w: np.ndarray, sweep_dir: np.ndarray | None, heights_fit: np.ndarray,
                  heights: np.ndarray, counts: np.ndarray, grid: Grid, point_sigma: float, n_sigma: float,
                  lower_m: np.ndarray | None = None, upper_m: np.ndarray | float | None = None,
                  mask: np.ndarray | None = None, shared: SharedDraws | None = None,
                  edge_m: np.ndarray | None = None) -> SurveyErrors:
    """The terms over the whole floor, or over the cells of mask (one pile's: ground.piles); the points'
    scatter is the survey's either way. upper_m bounds the unseen cells from above (the roof, or the
    free-space ceiling where it was computed). shared: the points' shared pose draws (`noise_term_m3`). edge_m:
    the heights the unseen term takes the slope where sight stopped from (`edge_heights_m`; None: heights_fit)."""
    low, high = unseen_terms_m3(heights_fit, heights, grid, lower_m, upper_m, mask, edge_m)
    faces = face_cells(points_w, grid, point_sigma, n_sigma)
    scatter = scatter_sigma_m(points_w, heights_fit, grid)
    terms = ErrorTerms(unseen_low_m3=low, unseen_high_m3=high,
                       interpolation_m3=interpolation_term_m3(heights_fit, counts, grid, mask, scatter),
                       noise_m3=noise_term_m3(scatter, heights_fit, counts, grid, mask, points_w[:, :2], shared),
                       blur_m3=blur_term_m3(scatter, heights_fit, grid, mask),
                       sweeps_m3=sweeps_term_m3(points_w, sweep_dir, heights_fit, grid, mask=mask),
                       faces_m3=faces_term_m3(faces, grid, mask))
    return SurveyErrors(terms, faces, point_sigma)
