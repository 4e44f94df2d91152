"""Pose correction from the building: a smooth correction of the logged trajectory that puts the floor
and the walls back on their planes.

Indoors the autopilot's pose drifts (docs/pose_error.md): decimetres to metres of position, tenths of a
degree of heading, an altitude reference that moves. Every sample is placed from that pose, so the
building's own surfaces, known exactly from the log header's storage record (floor z = 0, walls x = 0,
x = L, y = 0, y = W), come out displaced. The correction c(t) = (dx, dy, dz, dtheta)(t) in the storage
frame W is added to the logged pose: a point is p' = c_W(t) + dp(t) + Rz(dtheta(t)) v, v the beam's
vector (lever arm + range along the beam) from the logged vehicle position c_W, rotated about the
vertical through the vehicle (a heading error turns the whole sweep about the vehicle).

The correction is piecewise linear in time (knots every `knot_spacing_s`: two sweep periods, the
shortest stretch in which the beam has crossed the floor and the walls beside the track in both
directions twice; shorter knots would fit one sweep's noise, longer ones would smooth the ~1 s
altitude steps a downward rangefinder makes over a pile). Between knots a random-walk prior (each
knot's change ~ the largest drift an indoor estimator makes in that time, `PoseCorrectionOptions`)
ties the knots together: where the structure does not constrain a component (the along-track position
between two turns: the walls ahead and behind are out of the sweep plane; the heading, which a wall
beside the track does not see), that component is interpolated between the stretches that do, as a
drift is continuous, and the report says over which time it was not constrained by data.

How: (1) a vote per knot interval (the mode of the points' distance to each plane: the plane's own points
pile up at one offset, a pile's toe spreads) gives a start that pile points near the floor or a wall do
not drag; (2) robust least squares (soft-L1, scipy's trust-region solver with a sparse Jacobian: each
point moves with its two knots only) over the points near a plane, the window shrinking from what the
start leaves to the data's own noise.

No harm: a correction is applied only when it brings the structure closer to its planes by more than
fitting the same number of parameters to noise would (a chi-square test on the structure points in
the data's own noise sigmas). An error-free flight leaves the points on their planes: nothing to gain,
nothing applied.

Why this does not fight the mount's self-calibration (`ground.self_calibration`): the correction is
solved first, with the configured mount (the header's boresight, the logged servo angles), then the
mount is self-calibrated from the corrected samples. A mount error is constant and moves each sweep's
points by an amount that depends on the servo angle (a tilt of the sweep), which a per-knot
translation and heading cannot mimic across the sweep; a drift varies in time, which a constant mount
cannot mimic. The rest of what one could absorb of the other is measured (docs/pose_error.md).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame, beam_rays_w
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD
from firmware_py.core.storage import Storage

PLANE_NAMES = ("floor", "x0", "xL", "y0", "yW")
BAND = 3.0
"""A fit round takes the points within this many windows of their nearest plane."""
HELD = 1e-9
"""A held component's absolute prior, as a fraction of the free one: it stays at zero."""
KNOT_SWEEPS = 2.0
"""Knot spacing in sweep periods (module docstring)."""


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
    max_position_error_m: float = 5.0
    """The largest position error looked for (the vote's reach, the knots' absolute prior)."""
    max_heading_error_rad: float = math.radians(5.0)
    n_significant: float = 3.0
    """The correction is applied when its gain beats noise fitting by this many standard deviations."""
    max_points: int = 40_000
    """Samples used in the fit (evenly spaced in time)."""
    min_structure_points: int = 200
    """Fewer structure points than this: no correction (a warning)."""
    knot_spacing_s: float | None = None
    """None: KNOT_SWEEPS sweep periods."""
    vertical: bool = False
    """Estimate the height too. Off by default: measured, where a pile hides the floor its flat parts pass
    for the floor and the height correction made the error-free flight's Ve 6-8 % (docs/pose_error.md)."""
    heading: bool = False
    """Estimate the heading too. Off by default: the walls beside the track do not see it, and measured
    it came out worse than the uncorrected estimate (docs/pose_error.md)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if (v is None and f.name == "knot_spacing_s") or f.name in ("vertical", "heading"):
                continue
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"pose correction option {f.name} must be a finite number > 0, got {v!r}")


@dataclass(frozen=True)
class PoseCorrection:
    """What the fit found, and whether it is applied.

    Attributes:
        knot_t_s: (K,) knot times (the sample log's clock).
        values: (K, 4) the correction at the knots, added to the logged pose: dx, dy, dz in W (m),
            dtheta about W's z (rad; the NED yaw changes by -dtheta).
        constrained: (K, 4) whether the structure's points, not the prior, set each value.
        applied: the samples are re-projected with it.
        reason: one line when nothing was applied (too few points, not significant).
        points: structure points per plane in the final fit (PLANE_NAMES order).
        rms_before_m, rms_after_m: robust RMS distance of those points from their planes.
        noise_m: the data's own noise along a plane normal (consecutive samples on one plane).
        gain, gain_needed: the chi-square gain of the fit and what noise fitting would explain.
    """

    knot_t_s: np.ndarray
    values: np.ndarray
    constrained: np.ndarray
    applied: bool
    reason: str | None = None
    points: tuple[int, ...] = (0,) * 5
    rms_before_m: float = 0.0
    rms_after_m: float = 0.0
    noise_m: float = 0.0
    gain: float = 0.0
    gain_needed: float = 0.0

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 4) the correction at times t_s (linear between knots, held beyond the ends)."""
        t = np.asarray(t_s, dtype=float)
        if len(self.knot_t_s) == 0:
            return np.zeros((len(t), 4))
        return np.column_stack([np.interp(t, self.knot_t_s, self.values[:, c]) for c in range(4)])

    def size(self) -> dict[str, float]:
        """RMS and max over time of the horizontal, vertical and heading correction (at the knots)."""
        v = self.values if len(self.values) else np.zeros((1, 4))
        h = np.hypot(v[:, 0], v[:, 1])
        return {"horizontal_rms_m": _rms(h), "horizontal_max_m": float(h.max()),
                "vertical_rms_m": _rms(v[:, 2]), "vertical_max_m": float(np.abs(v[:, 2]).max()),
                "heading_rms_deg": math.degrees(_rms(v[:, 3])),
                "heading_max_deg": math.degrees(float(np.abs(v[:, 3]).max()))}

    def unconstrained_s(self) -> dict[str, float]:
        """Per component, the time (s) over which the data did not constrain it (knot intervals whose
        both ends are unconstrained)."""
        if len(self.knot_t_s) < 2:
            return {c.name.lower(): 0.0 for c in Component}
        dt = np.diff(self.knot_t_s)
        out = {}
        for c in Component:
            if not np.abs(self.values[:, c.value]).max(initial=0.0) > 1e-9:
                continue  # held at zero (not estimated)
            free = ~self.constrained[:, c.value]
            out[c.name.lower()] = float(dt[free[:-1] & free[1:]].sum())
        return out

    def as_dict(self) -> dict:
        return {"applied": self.applied, "reason": self.reason, "knot_spacing_s": _spacing(self.knot_t_s),
                "n_knots": len(self.knot_t_s), **self.size(), "unconstrained_s": self.unconstrained_s(),
                "points_per_plane": dict(zip(PLANE_NAMES, self.points, strict=True)),
                "rms_before_m": self.rms_before_m, "rms_after_m": self.rms_after_m, "noise_m": self.noise_m,
                "gain": self.gain, "gain_needed": self.gain_needed}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else 0.0


def _robust_rms(r: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(r))) if len(r) else 0.0


def _spacing(knots: np.ndarray) -> float:
    return float(np.median(np.diff(knots))) if len(knots) > 1 else 0.0


def not_applied(reason: str, knots: np.ndarray | None = None, **kw) -> PoseCorrection:
    """No correction, and why."""
    k = np.zeros(0) if knots is None else knots
    return PoseCorrection(k, np.zeros((len(k), 4)), np.zeros((len(k), 4), dtype=bool), False, reason, **kw)


def planes(storage: Storage) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (5, 3) and offsets (5,) of the floor and the four walls: n . p = d."""
    n = np.array([[0, 0, 1], [1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0]], dtype=float)
    return n, np.array([0.0, 0.0, storage.length_m, 0.0, storage.width_m])


def sweep_period_from_samples(t_s: np.ndarray, sweep_dir: np.ndarray) -> float | None:
    """The servo's period from the logged sweep direction (twice the median time between reversals)."""
    flips = np.flatnonzero(np.diff(np.asarray(sweep_dir, dtype=np.int64)) != 0)
    if len(flips) < 3:
        return None
    half = float(np.median(np.diff(np.asarray(t_s, dtype=float)[flips])))
    return 2.0 * half if half > 0 else None


def knot_times(t0_s: float, t1_s: float, spacing_s: float) -> np.ndarray:
    """Evenly spaced knots covering [t0, t1] (at least two)."""
    n = max(1, math.ceil((t1_s - t0_s) / spacing_s - 1e-9))
    return t0_s + np.arange(n + 1) * ((t1_s - t0_s) / n if t1_s > t0_s else spacing_s)


def prior_sigmas(spacing_s: float, speed_m_s: float, opts: PoseCorrectionOptions) -> np.ndarray:
    """(4,) the random-walk prior's sigma of one knot-to-knot change per component."""
    dist = speed_m_s * spacing_s
    root = math.sqrt(spacing_s)
    h = opts.horizontal_drift_rel * dist + opts.hover_walk_m_per_sqrt_s * root
    z = opts.vertical_slope * dist + opts.vertical_walk_m_per_sqrt_s * root
    psi = opts.heading_bias_rad_s * spacing_s + opts.heading_walk_rad_per_sqrt_s * root
    return np.array([h, h, z, psi])


@dataclass(frozen=True)
class Beams:
    """The usable samples' geometry: time, the vehicle's position in W and the vector to the hit point."""

    t_s: np.ndarray
    vehicle_w: np.ndarray
    to_point_w: np.ndarray
    parallel: np.ndarray | None = None
    """(N, 5) whether each point's stretch of sweep runs along each plane (`along_planes`)."""

    def take(self, idx) -> Beams:
        return Beams(self.t_s[idx], self.vehicle_w[idx], self.to_point_w[idx],
                     None if self.parallel is None else self.parallel[idx])


def beams(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame,
          boresight: Boresight = SQUARE) -> tuple[Beams, np.ndarray]:
    """Eqs. (3)-(6) split at the vehicle, for the usable samples: its position and the vector from it to
    each hit point; and their sweep directions."""
    names = ("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad", "servo_rad", "range_m", "t_s")
    ok = np.logical_and.reduce([np.isfinite(samples[f]) for f in names])
    ok &= ((samples["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0) & (samples["range_m"] > 0)
    s = samples[ok]
    pos = np.column_stack([s["x_m"], s["y_m"], s["z_m"]]).astype(float)
    origins, dirs = beam_rays_w(pos, s["roll_rad"], s["pitch_rad"], s["yaw_rad"], s["servo_rad"], lever_arm_body_m,
                                frame, boresight)
    c = frame.ned_to_w(pos)
    return (Beams(s["t_s"].astype(float), c, origins - c + dirs * s["range_m"].astype(float)[:, None]),
            s["sweep_dir"].astype(np.int64))


CHORD_HALF = 16
"""A point's stretch of sweep: the chord from the sample CHORD_HALF before it to CHORD_HALF after it."""


def along_planes(b: Beams, sigma_m: np.ndarray, angle_sigma_rad: float, sweep_dir: np.ndarray,
                 n: np.ndarray, sample_dt_s: float) -> np.ndarray:
    """(N, 5) True where the point's stretch of sweep runs along plane j: the chord between its neighbours
    has no component along j's normal beyond 3 noise sigmas of both ends (and the attitude's pointing
    error). A translation or a small turn of the pose keeps a plane's stretches flat, a pile's slope
    never is: so a pile's toe cannot pass for the floor, nor its flank for a wall it does not touch."""
    p = b.vehicle_w + b.to_point_w
    m = len(p)
    h = CHORD_HALF
    out = np.zeros((m, len(n)), dtype=bool)
    if m <= 2 * h:
        return out
    i = np.arange(h, m - h)
    same = (sweep_dir[i - h] == sweep_dir[i + h]) & (b.t_s[i + h] - b.t_s[i - h] <= (2 * h + 1.5) * sample_dt_s)
    chord = p[i + h] - p[i - h]
    length = np.linalg.norm(chord, axis=1)
    tol = 3.0 * np.hypot(sigma_m[i - h], sigma_m[i + h]) + 3.0 * angle_sigma_rad * length
    out[i] = (np.abs(chord @ n.T) <= tol[:, None]) & same[:, None] & (length > tol)[:, None]
    return out


def corrected_points(b: Beams, values: np.ndarray, k: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points with the correction `values` (K, 4) interpolated at knot index k and fraction f; and the
    rotated beam vectors."""
    a = values[k] * (1.0 - f)[:, None] + values[k + 1] * f[:, None]
    cs, sn = np.cos(a[:, 3]), np.sin(a[:, 3])
    v = b.to_point_w
    vr = np.column_stack([cs * v[:, 0] - sn * v[:, 1], sn * v[:, 0] + cs * v[:, 1], v[:, 2]])
    return b.vehicle_w + a[:, :3] + vr, vr


def _basis(t: np.ndarray, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k = np.clip(np.searchsorted(knots, t, side="right") - 1, 0, len(knots) - 2)
    f = np.clip((t - knots[k]) / (knots[k + 1] - knots[k]), 0.0, 1.0)
    return k, f


def _assign(p: np.ndarray, n: np.ndarray, d: np.ndarray, window: float,
            parallel: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(plane index, signed distance) of each point's nearest plane (among those its stretch of sweep runs
    along, when given); index -1 beyond the window or along none."""
    dist = p @ n.T - d
    if parallel is not None:
        dist = np.where(parallel, dist, math.inf)
    j = np.argmin(np.abs(dist), axis=1)
    r = dist[np.arange(len(p)), j]
    return np.where(np.abs(r) <= window, j, -1), r


INSIDE_SIGN = np.array([1.0, 1.0, -1.0, 1.0, -1.0])
"""Per plane (PLANE_NAMES order): the sign of n . p - d on the building's inside, where the pile is."""
MIN_VOTES = 10
"""A plane's peak needs this many points in a knot interval (fewer: a few stray returns)."""
STRAY_FRACTION = 0.01
"""Points beyond a plane a knot interval may hold by chance (glitches, multipath): 1 % of its points."""
PEAK_FRACTION = 0.1
"""A peak of the vote counts when it holds at least this fraction of the highest bin's points."""


def _peaks(h: np.ndarray) -> list[int]:
    """The histogram's local maxima that hold at least MIN_VOTES points and PEAK_FRACTION of the highest
    (smoothed over three bins)."""
    sm = np.convolve(h, np.ones(3), mode="same")
    need = max(MIN_VOTES, PEAK_FRACTION * float(sm.max()))
    out = []
    for m in range(len(sm)):
        left = sm[m - 1] if m > 0 else -1.0
        right = sm[m + 1] if m + 1 < len(sm) else -1.0
        if sm[m] >= need and sm[m] >= left and sm[m] > right:
            out.append(int(np.argmax(h[max(m - 1, 0):m + 2]) + max(m - 1, 0)))
    return out


def _vote(b: Beams, k: np.ndarray, n: np.ndarray, d: np.ndarray, n_knots: int, reach_m: float,
          bin_m: float) -> np.ndarray:
    """A start (K, 4). Per knot interval and plane, the peaks of the distances to the plane of the points
    whose stretch of sweep runs along it (a plane's own points pile up at one offset); the plane is the
    outermost peak beyond which lie no more points of any kind than stray returns: nothing is below the
    floor or behind a wall but noise, while a flat pile top, which may hold more points than the floor
    beside it, has the pile's flanks below it. Averaged to the knots, interpolated where no plane was
    found; heading 0."""
    p = b.vehicle_w + b.to_point_w
    dist_all = p @ n.T - d
    dist = dist_all if b.parallel is None else np.where(b.parallel, dist_all, math.inf)
    nearest = np.argmin(np.abs(dist), axis=1)
    bins = np.arange(-reach_m, reach_m + bin_m, bin_m)
    comp_of_plane = (2, 0, 0, 1, 1)
    est = np.full((n_knots - 1, 3), np.nan)
    for i in range(n_knots - 1):
        here = k == i
        sums, cnt = np.zeros(3), np.zeros(3)
        for j in range(5):
            r = dist[here & (nearest == j), j] * INSIDE_SIGN[j]  # > 0: inside the building
            r = r[np.abs(r) <= reach_m]
            if len(r) < MIN_VOTES:
                continue
            inside_all = np.sort(dist_all[here, j] * INSIDE_SIGN[j])
            stray = max(MIN_VOTES, STRAY_FRACTION * len(inside_all))
            h, _ = np.histogram(r, bins)
            for m in _peaks(h):
                sel = r[(r >= bins[m] - bin_m) & (r <= bins[m + 1] + bin_m)]
                off = float(np.median(sel))
                if np.searchsorted(inside_all, off - 2.0 * bin_m) <= stray:
                    c = comp_of_plane[j]
                    sums[c] -= off * INSIDE_SIGN[j] * len(sel)  # the correction moves them back
                    cnt[c] += len(sel)
                    break
        est[i] = np.where(cnt > 0, sums / np.maximum(cnt, 1), np.nan)
    mids = np.arange(n_knots - 1) + 0.5
    out = np.zeros((n_knots, 4))
    for c in range(3):
        ok = np.isfinite(est[:, c])
        if ok.any():
            out[:, c] = np.interp(np.arange(n_knots), mids[ok], est[ok, c])
    return out


def _jacobian(b: Beams, vr: np.ndarray, k: np.ndarray, f: np.ndarray, nj: np.ndarray, s: np.ndarray,
              n_par: int) -> sparse.csr_matrix:
    """d(residual)/d(knot values) of the points: each point moves with its two knots only."""
    m = len(k)
    g = (nj[:, 0] * -vr[:, 1] + nj[:, 1] * vr[:, 0]) / s  # heading: d(Rz v)/dtheta = (-v_y, v_x, 0)
    per = np.column_stack([nj[:, 0] / s, nj[:, 1] / s, nj[:, 2] / s, g])  # (m, 4)
    rows = np.repeat(np.arange(m), 8)
    cols = np.concatenate([4 * k[:, None] + np.arange(4), 4 * (k + 1)[:, None] + np.arange(4)], axis=1).ravel()
    data = np.concatenate([per * (1.0 - f)[:, None], per * f[:, None]], axis=1).ravel()
    return sparse.csr_matrix((data, (rows, cols)), shape=(m, n_par))


def _prior_matrix(n_knots: int, step_sigma: np.ndarray, abs_sigma: np.ndarray) -> sparse.csr_matrix:
    """Rows of the prior: knot-to-knot changes in step sigmas, then each knot's value in absolute sigmas."""
    n_par = 4 * n_knots
    rows, cols, data = [], [], []
    r = 0
    for i in range(n_knots - 1):
        for c in range(4):
            rows += [r, r]
            cols += [4 * i + c, 4 * (i + 1) + c]
            data += [-1.0 / step_sigma[c], 1.0 / step_sigma[c]]
            r += 1
    for i in range(n_knots):
        for c in range(4):
            rows.append(r)
            cols.append(4 * i + c)
            data.append(1.0 / abs_sigma[c])
            r += 1
    return sparse.csr_matrix((data, (rows, cols)), shape=(r, n_par))


def _fit_round(b: Beams, k: np.ndarray, f: np.ndarray, n: np.ndarray, d: np.ndarray, x0: np.ndarray,
               window: float, prior: sparse.csr_matrix, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One robust least-squares round over the points assigned to planes (j >= 0), in windows. The
    assignment is the start's and stays: re-assigning after each round let the floor climb a pile's
    flat top step by step where the floor itself was hidden."""
    n_knots = len(x0)
    sel = np.flatnonzero(j >= 0)
    if len(sel) < 10:
        return x0, j
    bs = b.take(sel)
    ks, fs, nj, dj = k[sel], f[sel], n[j[sel]], d[j[sel]]
    s = np.full(len(sel), window)

    def resid(x: np.ndarray) -> np.ndarray:
        v = x.reshape(n_knots, 4)
        q, _ = corrected_points(bs, v, ks, fs)
        return np.concatenate([(np.einsum("ij,ij->i", q, nj) - dj) / s, prior @ x])

    def jac(x: np.ndarray) -> sparse.csr_matrix:
        v = x.reshape(n_knots, 4)
        _, vr = corrected_points(bs, v, ks, fs)
        return sparse.vstack([_jacobian(bs, vr, ks, fs, nj, s, 4 * n_knots), prior], format="csr")

    sol = least_squares(resid, x0.ravel(), jac=jac, loss="soft_l1", f_scale=1.0, tr_solver="lsmr",
                        x_scale="jac", max_nfev=50)
    return sol.x.reshape(n_knots, 4), j


def _noise_m(j: np.ndarray, r: np.ndarray, floor_m: float) -> float:
    """The structure's noise along its normals: consecutive samples on one plane (a pose error moves
    neighbours alike, so their difference is the noise), never under floor_m."""
    on = np.flatnonzero(j >= 0)
    same = (np.diff(on) == 1) & (j[on[1:]] == j[on[:-1]])
    if not same.any():
        return floor_m
    return max(_robust_rms(np.diff(r[on])[same]) / math.sqrt(2.0), floor_m)


def estimate_pose_correction(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, storage: Storage,
                             resolution_m: float, range_sigma_m: float = 0.0, range_sigma_rel: float = 0.0,
                             angle_sigma_rad: float = 0.0, sweep_period_s: float | None = None,
                             boresight: Boresight = SQUARE,
                             opts: PoseCorrectionOptions | None = None) -> PoseCorrection:
    """Estimate the trajectory's correction from the floor and walls (module docstring).

    Args:
        samples: the survey's samples (SAMPLE_DTYPE), in time order; unusable ones are left out here.
        lever_arm_body_m, frame, storage, boresight: the log header's geometry.
        resolution_m, range_sigma_m, range_sigma_rel: the header's sensor model (the vote's bin, the
            noise floor).
        sweep_period_s: the servo's period (the header's); None: from the logged sweep directions.
    """
    opts = opts or PoseCorrectionOptions()
    b, sweep_dir = beams(samples, lever_arm_body_m, frame, boresight)
    if len(b.t_s) < opts.min_structure_points:
        return not_applied(f"too few usable samples ({len(b.t_s)}) to correct the pose from the building")
    period = sweep_period_s or sweep_period_from_samples(samples["t_s"], samples["sweep_dir"])
    spacing = opts.knot_spacing_s or (KNOT_SWEEPS * period if period else None)
    if spacing is None or not spacing > 0:
        return not_applied("the sweep period is unknown (no servo frequency in the header, too few sweeps): no knot "
                           "spacing for the pose correction")
    n, d = planes(storage)
    rng = np.linalg.norm(b.to_point_w, axis=1)
    floor_m = max(resolution_m / math.sqrt(12.0), 1e-3)
    sigma = np.maximum(np.maximum(range_sigma_m, range_sigma_rel * rng), floor_m)
    dt = float(np.median(np.diff(b.t_s))) if len(b.t_s) > 1 else 0.0
    b = replace(b, parallel=along_planes(b, sigma, angle_sigma_rad, sweep_dir, n, dt))
    stride = max(1, len(b.t_s) // opts.max_points)
    b = b.take(slice(None, None, stride))
    t0, t1 = float(b.t_s.min()), float(b.t_s.max())
    knots = knot_times(t0, t1, spacing)
    k, f = _basis(b.t_s, knots)
    # what the data alone give: the sensor's error at the median range (the vote's bin), the data's noise
    rng_med = float(np.median(np.linalg.norm(b.to_point_w, axis=1)))
    sensor_m = max(range_sigma_m, range_sigma_rel * rng_med, resolution_m)
    p0 = b.vehicle_w + b.to_point_w
    j0, r0 = _assign(p0, n, d, opts.max_position_error_m, b.parallel)
    noise = _noise_m(np.where(np.abs(r0) <= sensor_m, j0, -1), r0, floor_m)
    path = b.vehicle_w[np.argsort(b.t_s)]
    speed = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)) / max(t1 - t0, 1e-9))
    step = prior_sigmas(spacing, speed, opts)
    absolute = np.array([opts.max_position_error_m] * 3 + [opts.max_heading_error_rad])
    held = np.array([False, False, not opts.vertical, not opts.heading])
    absolute = np.where(held, absolute * HELD, absolute)  # a held component stays at zero
    prior = _prior_matrix(len(knots), step, absolute)
    x = _vote(b, k, n, d, len(knots), opts.max_position_error_m, sensor_m)
    x[:, held] = 0.0
    # windows: from what the vote leaves (its bin, the drift within a knot interval) down to the noise
    window = sensor_m
    final = 3.0 * noise
    j_fit, _ = _assign(corrected_points(b, x, k, f)[0], n, d, BAND * window, b.parallel)
    for _ in range(12):
        x, _ = _fit_round(b, k, f, n, d, x, window, prior, j_fit)
        if window <= final:
            break
        _, r = _assign(corrected_points(b, x, k, f)[0], n, d, BAND * window, b.parallel)
        on = j_fit >= 0
        window = max(final, min(window / 2.0, BAND * _robust_rms(r[on]) if on.any() else window / 2.0))
    p1, vr = corrected_points(b, x, k, f)
    r1 = np.einsum("ij,ij->i", p1, n[np.maximum(j_fit, 0)]) - d[np.maximum(j_fit, 0)]
    j1 = np.where(np.abs(r1) <= BAND * final, j_fit, -1)
    on = j1 >= 0
    counts = tuple(int(np.count_nonzero(j1 == i)) for i in range(5))
    if on.sum() < opts.min_structure_points:
        return not_applied(f"too few points on the floor and walls ({int(on.sum())}) to correct the pose",
                           points=counts)
    # Which knot components the data set (their information beats the prior's): the rest is interpolated.
    sel = np.flatnonzero(on)
    jac = _jacobian(b.take(sel), vr[sel], k[sel], f[sel], n[j1[sel]], np.full(len(sel), noise), 4 * len(knots))
    info = np.asarray(jac.multiply(jac).sum(axis=0)).ravel().reshape(len(knots), 4)
    constrained = (info * (step ** 2)[None, :] >= 1.0) & ~held[None, :]
    # The same points on the same planes before and after, in noise sigmas: the chi-square gain against
    # what fitting the constrained parameters to noise would give.
    # The points counted are those on a plane (the start's window) before the correction or after it:
    # counting only those after would reward a correction that pulls a pile onto the floor.
    j_before, _ = _assign(p0, n, d, BAND * sensor_m, b.parallel)
    both = (j_before >= 0) | on
    jj = np.where(on, j1, j_before)[both]
    r_before = np.einsum("ij,ij->i", p0[both], n[jj]) - d[jj]
    r_after = np.einsum("ij,ij->i", p1[both], n[jj]) - d[jj]
    cap = (BAND * sensor_m / noise) ** 2
    gain = float(np.sum(np.minimum((r_before / noise) ** 2, cap) - np.minimum((r_after / noise) ** 2, cap)))
    n_free = int(constrained.sum())
    needed = n_free + opts.n_significant * math.sqrt(2.0 * max(n_free, 1))
    common = dict(points=counts, rms_before_m=_robust_rms(r_before[on[both]]), rms_after_m=_robust_rms(r1[on]),
                  noise_m=noise, gain=gain, gain_needed=needed)
    if not gain > needed:
        return not_applied("not applied: it does not bring the floor and walls closer to their planes by more than "
                           f"fitting {n_free} parameters to noise would (chi-square gain {gain:.0f}, needed "
                           f"{needed:.0f})", knots, **common)
    return PoseCorrection(knots, x, constrained, True, None, **common)


def apply_pose_correction(samples: np.ndarray, corr: PoseCorrection, frame: StorageFrame) -> np.ndarray:
    """A copy of the samples with the pose re-stated: position += the correction (W to NED), yaw -= dtheta
    (a turn about W's up axis is one about NED's down axis the other way)."""
    if not corr.applied:
        return samples
    out = samples.copy()
    c = corr.at(samples["t_s"].astype(float))
    d_ned = c[:, :3] @ frame.rot_w_from_ned  # R is symmetric: W -> NED of a vector
    for i, name in enumerate(("x_m", "y_m", "z_m")):
        out[name] = samples[name] + d_ned[:, i]
    out["yaw_rad"] = np.angle(np.exp(1j * (samples["yaw_rad"].astype(float) - c[:, 3])))
    return out


def describe(corr: PoseCorrection) -> str:
    """One line for the report: the correction applied, its size over time, and where the data did not
    constrain it."""
    s = corr.size()
    line = (f"pose corrected from the building: horizontal {s['horizontal_rms_m']:.2f} m RMS "
            f"({s['horizontal_max_m']:.2f} max), vertical {s['vertical_rms_m']:.2f} m RMS "
            f"({s['vertical_max_m']:.2f} max), heading "
            f"{s['heading_rms_deg']:.2f} deg RMS ({s['heading_max_deg']:.2f} max) over time; the floor and walls "
            f"now {corr.rms_after_m * 100:.1f} cm off their planes (were {corr.rms_before_m * 100:.1f} cm)")
    return line


def unconstrained_warning(corr: PoseCorrection) -> str | None:
    """A warning naming the components the structure did not constrain over part of the flight (they were
    interpolated between the stretches that did), or None."""
    if not corr.applied or len(corr.knot_t_s) < 2:
        return None
    total = float(corr.knot_t_s[-1] - corr.knot_t_s[0])
    names = {"x": "x (along the length)", "y": "y (along the width)", "z": "height", "heading": "heading"}
    parts = [f"{names[c]} over {s:.0f} s" for c, s in corr.unconstrained_s().items() if s > 0]
    if not parts:
        return None
    return (f"the pose correction is not constrained by the floor and walls for {', '.join(parts)} of the "
            f"{total:.0f} s flown: there it is interpolated between the stretches that are (no wall in the sweep "
            "plane); trajectory errors there are only as small as the drift is smooth")
