"""The pose correction's frame of work: the planes it fits the structure to, the components it corrects, its options
(the prior: the largest drift an indoor estimator makes) and its knots (their times and spacing, each sample's place
between two, the points moved by a correction at them). The fits (`ground.pose_correction`) build on these."""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, fields

import numpy as np

from firmware_py.core.numbers import is_finite_number
from firmware_py.core.waveform import MAX_FREQUENCY_HZ
from ground.plane_stretches import MAX_HEADING_ERROR_RAD, Beams

PLANE_NAMES = ("floor", "x0", "xL", "y0", "yW")
MAX_MISFIT = 3.0
"""A correction that leaves the structure points more than this many noise levels off their planes is not
applied: the drift model does not explain them (as `ground.self_calibration.MAX_MISFIT`; measured, a pose-only
error leaves 1.1-1.5, a servo 3 deg off with a 2 deg tilt ~6)."""
BAND = 3.0
"""A fit round takes the points within this many windows of their nearest plane."""
HELD = 1e-9
"""A held component's absolute prior, as a fraction of the free one: it stays at zero."""
KNOT_SWEEPS = 2.0
"""Knot spacing in sweep periods (why two: `ground.pose_correction`'s module docstring)."""
DRIFT_LEVEL = 0.99
"""A registration on the pile seen twice must leave a trajectory the drift model allows: its knot-to-knot steps, in
the model's step sigmas, no larger in norm than the walls' fit's plus a drift's at this quantile of chi-square.
Beyond it the registration is no drift and is not used (`is_drift`)."""


class Component(enum.Enum):
    """The corrected components, in the storage frame W (heading: about W's z axis, up)."""

    X = 0
    Y = 1
    Z = 2
    HEADING = 3


@dataclass(frozen=True)
class PoseCorrectionOptions:
    """The largest drift an indoor estimator makes (the prior) and the fit's limits. Defaults: the upper
    end of the indoor estimators docs/pose_error.md describes (flow 2 %, VIO 1 % of the distance flown;
    0.01 deg/s of gyro bias; a downward rangefinder that follows a pile's slope)."""

    horizontal_drift_rel: float = 0.03
    """Horizontal drift per metre flown (the brief's 1-3 %), for the knots' random-walk prior."""
    hover_walk_m_per_sqrt_s: float = 0.02
    """Horizontal random walk in time (twice the flow profile's)."""
    vertical_slope: float = 0.2
    """Altitude-reference change per metre flown: a downward rangefinder weighted like the flow profile's
    (0.25) over a pile's 35 deg angle of repose (tan 35 deg = 0.7)."""
    vertical_walk_m_per_sqrt_s: float = 0.05
    """Barometer walk (indoor pressure changes)."""
    heading_bias_rad_s: float = math.radians(0.03)
    """Gyro-bias residual (3x the flow profile's)."""
    heading_walk_rad_per_sqrt_s: float = math.radians(0.05)
    drift_correlation_s: float = 30.0
    """The shortest correlation time believed of a velocity sensor's drift (half the SITL's Gauss-Markov 60 s):
    how smooth the position error is between turns (`bend_sigmas`)."""
    max_position_error_m: float = 5.0
    """The largest position error looked for (the vote's reach, the knots' absolute prior)."""
    max_vertical_error_m: float = 2.0
    """The largest altitude-reference error believed: the flow profile's worst, a rangefinder weighted 0.25
    over the paper's 7.3 m pile (1.8 m). A height correction beyond it means a flat pile top was taken for
    the floor (measured on the paper's pile 2, which hides the floor: 1.4 m RMS of wrong height) and is
    not applied."""
    max_heading_error_rad: float = MAX_HEADING_ERROR_RAD
    n_significant: float = 3.0
    """The correction is applied when its gain beats noise fitting by this many standard deviations."""
    max_points: int = 40_000
    """Samples used in the fit (evenly spaced in time)."""
    min_structure_points: int = 200
    """Fewer structure points than this: no correction (a warning)."""
    knot_spacing_s: float | None = None
    """None: KNOT_SWEEPS sweep periods."""
    vertical: bool = True
    """Estimate the height too (from the floor where it is seen and, with `crossings`, from the pile)."""
    crossings: bool = True
    """With `vertical`: the height also from the pile seen at different times (the same surface must come
    out at the same height), not only from the floor, which a pile hides along most of a track."""
    crossings_horizontal: bool = True
    """With `crossings`: the position too from the pile seen at different times (a shift moves a sloped surface's
    height), which observes the along-track position between turns that the walls leave to interpolation."""
    crossings_heading: bool = True
    """With `crossings_horizontal`: the heading too (a heading error moves the points along the track by their
    lateral distance times it), kept only when significant."""
    open_floor: bool = False
    """Anchor the height on a floor seen only away from the walls (nothing seen at any wall comes down to it) however
    far it moves the height. Off, such a floor is used only when it moves the height by no more than the barometer
    walks over the flight (vertical_walk_m_per_sqrt_s), else the height is corrected from the pile seen at
    different times alone, at the logged reference's level: the lowest flat part of a pile that hides the floor
    wall to wall passes for the floor, and was taken for it 0.3-0.8 m up (Ve 13-44 %: docs/design-notes.md). The
    report turns it on when the autopilot's height came from its downward rangefinder and the crossings could not
    take its share out (`ground.rangefinder_height`): that error follows the pile, and only a floor takes it out."""
    heading: bool = False
    """Estimate the heading too (kept only when significant). Off by default: the walls beside a track do not
    see it, and measured on seven SITL flights it made Ve worse on five (it took up a few systematic
    millimetres on the walls as degrees: docs/pose_error.md)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if (v is None and f.name == "knot_spacing_s") or f.name in ("vertical", "heading", "crossings",
                                                                                "crossings_horizontal",
                                                                                "crossings_heading", "open_floor"):
                continue
            if not is_finite_number(v) or v <= 0:
                raise ValueError(f"pose correction option {f.name} must be a finite number > 0, got {v!r}")


def sweep_period_from_samples(t_s: np.ndarray, sweep_dir: np.ndarray) -> float | None:
    """The servo's period from the logged sweep direction (twice the median time between reversals)."""
    flips = np.flatnonzero(np.diff(np.asarray(sweep_dir, dtype=np.int64)) != 0)
    if len(flips) < 3:
        return None
    half = float(np.median(np.diff(np.asarray(t_s, dtype=float)[flips])))
    return 2.0 * half if 2.0 * half >= 1.0 / MAX_FREQUENCY_HZ else None  # faster is no sweep a servo can make


def path_speed_m_s(t_s: np.ndarray, vehicle_w: np.ndarray, window_s: float) -> float:
    """The vehicle's mean speed along its logged path: the path through the logged positions' means over windows of
    window_s (a sweep period), not through every sample. A logged position carries its own white noise per pose
    message (the paper's Appendix A: 0.11 m), and summed sample to sample that noise was the path: 11 m/s
    "flown" on a 1 m/s survey, which made the crossings' cells 16 m wide and the priors' steps 6 m."""
    if len(t_s) < 2 or not window_s > 0:
        return 0.0
    order = np.argsort(t_s)
    t, p = t_s[order], vehicle_w[order]
    w = ((t - t[0]) / window_s).astype(np.int64)
    _, first, count = np.unique(w, return_index=True, return_counts=True)
    mean_p = np.add.reduceat(p, first, axis=0) / count[:, None]
    mean_t = np.add.reduceat(t, first) / count
    if len(mean_t) < 2:
        return 0.0
    return float(np.sum(np.linalg.norm(np.diff(mean_p, axis=0), axis=1)) / max(mean_t[-1] - mean_t[0], 1e-9))


def knot_times(t0_s: float, t1_s: float, spacing_s: float) -> np.ndarray:
    """Evenly spaced knots covering [t0, t1] (at least two)."""
    n = max(1, math.ceil((t1_s - t0_s) / spacing_s - 1e-9))
    return t0_s + np.arange(n + 1) * ((t1_s - t0_s) / n if t1_s > t0_s else spacing_s)


def median_spacing_s(knots: np.ndarray) -> float:
    """The knots' typical spacing (0 for fewer than two)."""
    return float(np.median(np.diff(knots))) if len(knots) > 1 else 0.0


def prior_sigmas(spacing_s: float, speed_m_s: float, opts: PoseCorrectionOptions) -> np.ndarray:
    """(4,) the random-walk prior's sigma of one knot-to-knot change per component."""
    dist = speed_m_s * spacing_s
    root = math.sqrt(spacing_s)
    h = opts.horizontal_drift_rel * dist + opts.hover_walk_m_per_sqrt_s * root
    z = opts.vertical_slope * dist + opts.vertical_walk_m_per_sqrt_s * root
    psi = opts.heading_bias_rad_s * spacing_s + opts.heading_walk_rad_per_sqrt_s * root
    return np.array([h, h, z, psi])


def corrected_points(b: Beams, values: np.ndarray, k: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points with the correction `values` (K, 4) interpolated at knot index k and fraction f; and the
    rotated beam vectors."""
    a = values[k] * (1.0 - f)[:, None] + values[k + 1] * f[:, None]
    cs, sn = np.cos(a[:, 3]), np.sin(a[:, 3])
    v = b.to_point_w
    vr = np.column_stack([cs * v[:, 0] - sn * v[:, 1], sn * v[:, 0] + cs * v[:, 1], v[:, 2]])
    return b.vehicle_w + a[:, :3] + vr, vr


def knot_basis(t: np.ndarray, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each time's knot interval k and fraction f in it: a piecewise-linear value at t is v[k] (1 - f) + v[k + 1] f
    (held beyond the ends)."""
    k = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2)
    f = np.clip((t - knots[k]) / (knots[k + 1] - knots[k]), 0.0, 1.0)
    return k, f


MIN_VOTES = 10
"""A plane's peak needs this many points in a knot interval (fewer: a few stray returns)."""
MIN_CELL_POINTS = 3
"""A cell's points in one knot interval give one height when there are at least this many."""
STRAY_FRACTION = 0.01
"""Points beyond a plane a knot interval may hold by chance (glitches, multipath): 1 % of its points."""
