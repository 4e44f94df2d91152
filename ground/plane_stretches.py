"""The stretches of a sweep that run along the building's planes.

A LiDAR sweep draws a line over whatever it crosses: along the floor or a wall the line is straight in the
plane, over a pile's toe or flank it climbs. A point whose stretch of sweep (its neighbours in time, either side)
runs along a plane may be that plane's; a point on a climbing stretch cannot be, however near the plane it
lies. Both estimates from the building use the test: the pose correction (`ground.pose_correction`) and the
mount's self-calibration (`ground.self_calibration`), so that a pile's toe within the noise of the floor is
neither's floor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame, beam_rays_w, premultiply, rot_body_to_ned
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD
from firmware_py.core.storage import Storage
from ground.group_stats import JACKKNIFE_BLOCKS, jackknife_sd, robust_rms


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


def planes(storage: Storage) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (5, 3) and offsets (5,) of the floor and the four walls: n . p = d (the order every (N, 5)
    array of this module and of both estimates from the building follows: floor, x = 0, x = L, y = 0, y = W)."""
    n = np.array([[0, 0, 1], [1, 0, 0], [1, 0, 0], [0, 1, 0], [0, 1, 0]], dtype=float)
    return n, np.array([0.0, 0.0, storage.length_m, 0.0, storage.width_m])


INSIDE_SIGN = np.array([1.0, 1.0, -1.0, 1.0, -1.0])
"""Per plane (`planes`' order): the sign of n . p - d on the building's inside, where the pile is."""


def neighbour_noise_m(plane: np.ndarray, r: np.ndarray) -> float | None:
    """The points' noise along their planes' normals, from consecutive samples on one plane (an error of the pose or
    the mount moves neighbours alike, so their difference is the noise): the robust RMS of those differences over
    sqrt 2. plane: each point's plane (-1: none); r: its signed distance from it. None: no two consecutive samples
    share a plane."""
    on = np.flatnonzero(plane >= 0)
    same = (np.diff(on) == 1) & (plane[on[1:]] == plane[on[:-1]])
    if not same.any():
        return None
    return robust_rms(np.diff(r[on])[same]) / math.sqrt(2.0)


MAX_GAP_STEPS = 4.0
"""Two samples either side of a point give its beam's turn rate when they lie at most this many median sample spacings
apart (a gap: flagged samples between them, or the stride of a thinned cloud across a pause)."""


TIMING_ROUNDS = 20
"""At most this many rounds of `beside_a_servo_delay`'s fit (each keeps the points near their planes once the offset
found so far is out); it stops earlier when they stay the same."""


@dataclass(frozen=True)
class TimingSplit:
    """What a servo timing offset explains of the points' distances from their planes (`beside_a_servo_delay`)."""

    misfit_m: float  # the robust RMS of the distances once the offset is taken out
    delay_s: float  # the offset: the beam reached each logged angle this much after the log says (negative: before)
    delay_sigma_s: float = math.inf  # its standard error: least squares', or the flight's stretches' if larger
    shift_m: float = 0.0  # the RMS the offset moves those points along their planes' normals: what it matters

    def measured(self, n_sigma: float) -> bool:
        """Whether the offset lies n_sigma standard errors from zero."""
        return abs(self.delay_s) > n_sigma * self.delay_sigma_s

    def significant(self, n_sigma: float, noise_m: float) -> bool:
        """Whether the offset is both measured (`measured`) and large enough to matter: it moves the points more than
        the data's own noise."""
        return self.measured(n_sigma) and self.shift_m > noise_m

    def as_dict(self) -> dict:
        return {"delay_s": self.delay_s, "delay_sigma_s": self.delay_sigma_s if math.isfinite(self.delay_sigma_s)
                else None, "shift_m": self.shift_m, "misfit_m": self.misfit_m}


def beside_a_servo_delay(t_s: np.ndarray, beam_w: np.ndarray, r: np.ndarray, plane: np.ndarray,
                         normals: np.ndarray, window_m: float | None = None,
                         groups: np.ndarray | None = None) -> TimingSplit:
    """The points' distances from their planes with a servo timing offset fitted beside them. Why: a beam whose servo
    lags the angle logged for it by tau is placed r (d(t) - d(t - tau)) ~ r d' tau off, d' the beam's turn rate,
    which flips with the sweep's direction: no drift of the pose explains it (it moves the points of one sweep
    direction one way and of the other the other way), yet it is no mounting error either. A fraction of a
    millisecond leaves a centimetre at 20 m, as the networked SITL's servo behind its TCP bridge does (docs/design-
    notes.md, 2026-12-07). t_s, beam_w: the samples in time order, their beam vectors (vehicle to point, W); r: the
    signed distances; plane: each point's plane (-1: none), normals: the planes' normals; window_m: the distance
    within which a point counts as on its plane for the misfit (None: every point given a plane).

    The offset is fitted by least squares on the points within three robust RMS of their plane once it is taken out,
    from none, in rounds until those points stay the same: a servo 3 ms late puts the walls' points centimetres off,
    beyond three noise levels, and a single fit on the points near their planes found 1.66 ms of it (2.97 in rounds).
    A lag that puts them beyond the windows the caller gave them planes in (10 ms) is not reached (docs/design-
    notes.md, 2026-12-07 eighty-third session) by the distances a drift's fit leaves; with groups (per point, an
    integer: the pose correction's are a knot interval, a plane and a logged angle's bin, `by_angle`), it is fitted
    on distances no fit has touched, each group's points about their own mean (the within-group estimator): a drift
    moves a plane's points in a knot interval together, a lag moves the two sweep directions' apart, so the offset is
    found before, and without, the drift's fit (a 10 ms lag under a `flow` drift: 9.8 ms). 0 where too few points
    carry a turn rate."""
    on = np.flatnonzero(plane >= 0)
    rr = r[on]

    def misfit(left: np.ndarray) -> float:
        return robust_rms(left if window_m is None else left[np.abs(left) <= window_m])

    plain = TimingSplit(misfit(rr), 0.0)
    if len(on) < 10 or len(t_s) < 3:
        return plain
    # the beam's turn rate from its time neighbours, at the points on a plane only (a fifth of the samples)
    step = float(np.median(np.diff(t_s)))
    inner = on[(on > 0) & (on < len(t_s) - 1)]
    dt = t_s[inner + 1] - t_s[inner - 1]
    ok = (dt > 0) & (dt <= 2.0 * MAX_GAP_STEPS * step)
    i = inner[ok]

    def unit(v: np.ndarray) -> np.ndarray:
        return v / np.maximum(np.linalg.norm(v, axis=1), 1e-9)[:, None]

    rate = np.zeros((len(t_s), 3))
    rate[i] = (unit(beam_w[i + 1]) - unit(beam_w[i - 1])) / dt[ok, None]
    a = np.linalg.norm(beam_w[on], axis=1) * np.einsum("ij,ij->i", normals[plane[on]], rate[on])
    # a point without a turn rate says nothing of the offset, nor, with groups, may it set its group's mean
    turned = rate[on].any(axis=1) if groups is not None else np.ones(len(on), dtype=bool)
    if groups is not None:
        _, g = np.unique(np.asarray(groups)[on], return_inverse=True)
    a0, r0 = a, rr

    def about_groups(v: np.ndarray, kept: np.ndarray) -> np.ndarray:
        w = kept.astype(float)
        return v - (np.bincount(g, v * w) / np.maximum(np.bincount(g, w), 1.0))[g]
    tau, keep, den = 0.0, None, 0.0
    for _ in range(TIMING_ROUNDS):
        left = rr - a * tau  # (with groups: about the means of the points the last round kept)
        now = (np.abs(left) <= 3.0 * max(robust_rms(left[turned]), 1e-12)) & turned
        if keep is not None and np.array_equal(now, keep):
            break
        keep = now
        if groups is not None:
            a, rr = about_groups(a0, keep), about_groups(r0, keep)
        den = float(np.sum(a[keep] ** 2))
        if not den > 0:
            return plain
        tau = float(np.sum(a[keep] * rr[keep]) / den)
    left = rr - a * tau
    n_kept = int(np.count_nonzero(keep))
    sigma = math.sqrt(float(np.sum(left[keep] ** 2)) / max(n_kept - 1, 1) / den)
    # The points' residuals are not independent (what a drift or a mount leaves runs along the walls for seconds),
    # so the standard error is also taken from the flight's stretches (a jackknife over JACKKNIFE_BLOCKS stretches of
    # time, each left out in turn): an offset that a mount's error projects onto the turn rate changes from stretch to
    # stretch, a servo's lag does not (docs/design-notes.md, 2026-12-07 eighty-third session).
    sigma = max(sigma, slope_jackknife_sd(a[keep], rr[keep], JACKKNIFE_BLOCKS))
    return TimingSplit(misfit(left), tau, sigma, abs(tau) * math.sqrt(den / n_kept))


def by_angle(groups: np.ndarray, servo_rad: np.ndarray) -> np.ndarray:
    """The groups (integers, per sample) split further by the logged servo angle's bin (`angle_bins`): the groups
    `beside_a_servo_delay` fits a lag in, where a mount's error, the same at one angle both ways, cancels."""
    bins = angle_bins(servo_rad)
    return np.asarray(groups, dtype=np.int64) * (int(bins.max(initial=0)) + 1) + bins


def angle_bins(servo_rad: np.ndarray) -> np.ndarray:
    """Each sample's bin of the logged servo angle (0, 1, ...), two median steps between consecutive samples wide: a
    sweep leaves a point or two in each, so a bin holds both sweep directions' points at the same logged angle, where
    a mount's error is the same and a servo's lag is not (`beside_a_servo_delay`'s groups)."""
    a = np.asarray(servo_rad, dtype=float)
    if len(a) == 0:
        return np.zeros(0, dtype=np.int64)
    steps = np.abs(np.diff(a))
    width = 2.0 * float(np.median(steps[steps > 0])) if (steps > 0).any() else 1.0
    return np.floor((a - a.min()) / width).astype(np.int64)


def slope_jackknife_sd(a: np.ndarray, r: np.ndarray, n_groups: int) -> float:
    """The delete-one-group jackknife's standard error (`jackknife_sd`) of the least-squares slope of r on a (no
    intercept), over n_groups consecutive groups of the points in their order (0 when too few points or groups)."""
    if len(a) < 2 * n_groups or n_groups < 2:
        return 0.0
    g = np.arange(len(a)) * n_groups // len(a)
    saa = np.bincount(g, a * a, n_groups)
    sar = np.bincount(g, a * r, n_groups)
    rest = saa.sum() - saa
    if not np.all(rest > 0):
        return 0.0
    return jackknife_sd((sar.sum() - sar) / rest)


def nearest_plane(p: np.ndarray, n: np.ndarray, d: np.ndarray, window: float | np.ndarray,
                  allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(plane index, signed distance) of each point's nearest plane (n, d: `planes`), among those it may lie on when
    allowed (N, 5) is given (its stretch of sweep runs along them: `stretches_along`); index -1 beyond the window
    (one for all, or per point) or where no plane is allowed."""
    dist = p @ n.T - d  # (N, 5)
    if allowed is not None:
        dist = np.where(allowed, dist, math.inf)
    j = np.argmin(np.abs(dist), axis=1)
    r = dist[np.arange(len(p)), j]
    return np.where(np.abs(r) <= window, j, -1), r


def usable(samples: np.ndarray) -> np.ndarray:
    """(N,) the samples `beams` keeps: every field it reads finite, a range, no flag that excludes it."""
    names = ("x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad", "servo_rad", "range_m", "t_s")
    ok = np.logical_and.reduce([np.isfinite(samples[f]) for f in names])
    return ok & ((samples["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0) & (samples["range_m"] > 0)


def body_axes_w(samples: np.ndarray, frame: StorageFrame) -> np.ndarray:
    """(N, 3, 3) the body's forward, right and down axes in W (the columns) for each of the samples (`usable` ones:
    `beams`' order when taken as it takes them): what moves a point when the lever arm, fixed to the body, is off."""
    return premultiply(frame.rot_w_from_ned,
                       rot_body_to_ned(samples["roll_rad"], samples["pitch_rad"], samples["yaw_rad"]))


def beams(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame,
          boresight: Boresight = SQUARE) -> tuple[Beams, np.ndarray]:
    """Eqs. (3)-(6) split at the vehicle, for the usable samples (`usable`): its position and the vector from it to
    each hit point; and their sweep directions."""
    s = samples[usable(samples)]
    pos = np.column_stack([s["x_m"], s["y_m"], s["z_m"]]).astype(float)
    origins, dirs = beam_rays_w(pos, s["roll_rad"], s["pitch_rad"], s["yaw_rad"], s["servo_rad"], lever_arm_body_m,
                                frame, boresight)
    c = frame.ned_to_w(pos)
    return (Beams(s["t_s"].astype(float), c, origins - c + dirs * s["range_m"].astype(float)[:, None]),
            s["sweep_dir"].astype(np.int64))


def sweep_ids(t_s: np.ndarray, sweep_dir: np.ndarray, sample_dt_s: float) -> np.ndarray:
    """A number per point, the same for the points of one sweep: a new one at each turn of the servo and after
    any gap in time longer than two samples."""
    t = np.asarray(t_s, dtype=float)
    d = np.asarray(sweep_dir)
    if len(t) == 0:
        return np.zeros(0, dtype=np.int64)
    new = np.zeros(len(t), dtype=bool)
    new[1:] = (d[1:] != d[:-1]) | (np.diff(t) > 2.0 * sample_dt_s)
    return np.cumsum(new)


CHORD_HALF = 16
"""A point's stretch of sweep: the chord from the sample CHORD_HALF before it to CHORD_HALF after it."""


def unbroken(t_s: np.ndarray, sweep_dir: np.ndarray, i: np.ndarray, sample_dt_s: float) -> np.ndarray:
    """Whether the stretch of sweep around each sample i (CHORD_HALF either side) is one: one sweep direction at
    both ends, and no sample missing between them (a gap in the log, a turn of the servo)."""
    h = CHORD_HALF
    return (sweep_dir[i - h] == sweep_dir[i + h]) & (t_s[i + h] - t_s[i - h] <= (2 * h + 1.5) * sample_dt_s)


def to_nearest_wall_m(xy: np.ndarray, length_m: float, width_m: float) -> np.ndarray:
    """Each position's distance to the nearest of the four walls (negative outside the building)."""
    return np.minimum.reduce([xy[:, 0], length_m - xy[:, 0], xy[:, 1], width_m - xy[:, 1]])


def along_planes(b: Beams, sigma_m: np.ndarray, angle_sigma_rad: float, sweep_dir: np.ndarray,
                 n: np.ndarray, sample_dt_s: float, position_sigma_m: float = 0.0) -> np.ndarray:
    """(N, 5) True where the point's stretch of sweep runs along plane j: the chord between its neighbours
    has no component along j's normal beyond 3 noise sigmas of both ends (and the attitude's pointing
    error), where the sweep's plane crosses plane j, and the stretch is straight (both below; position_sigma_m:
    the position error drawn per pose message, which may bend it). A translation or a small turn of the pose keeps a
    plane's stretches flat, a pile's slope never is: so a pile's toe cannot pass for the floor, nor its flank
    for a wall it does not touch."""
    p = b.vehicle_w + b.to_point_w
    m = len(p)
    h = CHORD_HALF
    out = np.zeros((m, len(n)), dtype=bool)
    if m <= 2 * h:
        return out
    i = np.arange(h, m - h)
    same = unbroken(b.t_s, sweep_dir, i, sample_dt_s)
    chord = p[i + h] - p[i - h]
    length = np.linalg.norm(chord, axis=1)
    tol = 3.0 * np.hypot(sigma_m[i - h], sigma_m[i + h]) + 3.0 * angle_sigma_rad * length
    # The test says something only where the sweep plane crosses plane j: every chord of a sweep lies in
    # its own plane, so a plane parallel to the sweep's (a wall ahead when flying towards it) passes any
    # chord. It needs the angle between the two planes above the chord's own resolution, tol / length
    # (measured: a VIO flight's last leg, 4.7 m from the end wall ahead, took its sweeps' floor and side
    # wall points for that wall and moved 4.5 m along the track). A chord at angle a to the planes' line of
    # crossing has length * sin(angle) * sin(a) along plane j's normal; a pile's chord is at least
    # 90 - STEEPEST_PILE_DEG off a wall's (vertical) line, so the planes must cross by tol / (length * cos(that
    # steepest slope)) for such a chord to show. At tol / length a flank of the pile in a sweep a fraction of a
    # degree from parallel to the wall ahead passed for that wall (measured: a `flow` flight on its true pose,
    # 5.6 m from the wall at its end, had its last knots moved 2-8 m along the track).
    sweep_n = np.cross(b.to_point_w[i - h], b.to_point_w[i + h])
    sweep_n /= np.maximum(np.linalg.norm(sweep_n, axis=1), 1e-12)[:, None]
    resolvable = tol / (np.maximum(length, 1e-12) * math.cos(math.radians(STEEPEST_PILE_DEG)))
    crossing = np.sqrt(np.clip(1.0 - (sweep_n @ n.T) ** 2, 0.0, 1.0)) > resolvable[:, None]
    # And the stretch is straight: a plane cuts the sweep's plane in a line, so the point lies on its chord. A
    # stretch over a corner (a wall's foot and the floor, an L in the sweep's plane) has its chord along
    # neither of the two planes it spans, yet along any plane parallel to the L's plane (measured: a `flow` flight
    # turning for home near a corner took the foot of the wall x = 0 for the wall y = 0 and moved its last leg
    # 1.3 m along the track). The point's own tolerance adds the pointing error at its range and the position
    # error drawn per pose message (the point and the chord's ends may be placed from different messages).
    off = np.linalg.norm(np.cross(p[i] - p[i - h], chord), axis=1) / np.maximum(length, 1e-12)
    straight = off <= (tol + 3.0 * angle_sigma_rad * np.linalg.norm(b.to_point_w[i], axis=1)
                       + 3.0 * math.sqrt(2.0) * position_sigma_m)
    out[i] = ((np.abs(chord @ n.T) <= tol[:, None]) & same[:, None] & (length > tol)[:, None] & crossing
              & straight[:, None])
    return out


def stretches_along(b: Beams, sweep_dir: np.ndarray, n: np.ndarray, range_sigma_m: float, range_sigma_rel: float,
                    angle_sigma_rad: float, floor_m: float, position_sigma_m: float = 0.0) -> np.ndarray:
    """`along_planes` with each point's range sigma from the header's sensor model (never under floor_m) and the
    samples' own period: what both estimates from the building ask."""
    rng_m = np.linalg.norm(b.to_point_w, axis=1)
    sigma = np.maximum(np.maximum(range_sigma_m, range_sigma_rel * rng_m), floor_m)
    dt = float(np.median(np.diff(b.t_s))) if len(b.t_s) > 1 else 0.0
    return along_planes(b, sigma, angle_sigma_rad, sweep_dir, n, dt, position_sigma_m)


def stretch_floor_m(resolution_m: float) -> float:
    """The least range sigma a stretch is judged with: the range's quantisation (a uniform error over one
    resolution step, step / sqrt(12)), never under a millimetre."""
    return max(resolution_m / math.sqrt(12.0), 1e-3)


def placed_beams(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, boresight: Boresight,
                 storage: Storage, range_sigma_m: float, range_sigma_rel: float, angle_sigma_rad: float,
                 floor_m: float, position_sigma_m: float = 0.0) -> tuple[Beams, np.ndarray]:
    """`beams` with their stretches along the building's planes (`stretches_along`): what the pose correction
    starts from, and the mount's self-calibration asks too (made once when both run on the same samples)."""
    b, sweep_dir = beams(samples, lever_arm_body_m, frame, boresight)
    along = stretches_along(b, sweep_dir, planes(storage)[0], range_sigma_m, range_sigma_rel, angle_sigma_rad,
                            floor_m, position_sigma_m)
    return Beams(b.t_s, b.vehicle_w, b.to_point_w, along), sweep_dir


STEEPEST_PILE_DEG = 60.0
"""No stockpile stands steeper: loose bulk material lies at its angle of repose, 30-45 degrees; 60 leaves room for
cohesive or compacted faces. The faces term (`ground.uncertainty.MAX_SLOPE_DEG`) takes the same figure."""
MAX_HEADING_ERROR_RAD = math.radians(5.0)
"""The largest heading error an indoor estimator is believed to make: what the pose correction looks for
(`PoseCorrectionOptions.max_heading_error_rad`) and how far beside a wall a stretch of it may be seen."""


LINE_FIT_CHUNK = 8192
"""Windows fitted at once by `sliding_line_fit`: their gathered coordinates (2h+1 a window) stay a few MB."""


def sliding_line_fit(p: np.ndarray, h: int, at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the windows of 2h+1 consecutive points centred on the points at (indices h .. N-h-1): the line through
    each by principal components: its centroid (M, 3), its unit direction (M, 3) and the points' RMS distance from
    it (M,). Each window's own points are gathered, relative to its middle point (so its moments are small numbers):
    a survey asks for the few per cent of its points beside a wall, and running sums over the whole series would cost
    the series' length every call (the servo's timing search calls it once a candidate)."""
    p = np.asarray(p, dtype=float)
    at = np.asarray(at, dtype=np.int64)
    offsets = np.arange(-h, h + 1)
    k = len(offsets)
    centre, u, off = np.empty((len(at), 3)), np.empty((len(at), 3)), np.empty(len(at))
    for s in range(0, len(at), LINE_FIT_CHUNK):
        rows = slice(s, s + LINE_FIT_CHUNK)
        idx, middle = at[rows, None] + offsets, p[at[rows]]
        d = [p[idx, j] - middle[:, j, None] for j in range(3)]  # (c, 2h+1) each axis, one contiguous block
        mean = [dj.sum(axis=1) / k for dj in d]
        cov = np.empty((len(middle), 3, 3))
        for i in range(3):
            for j in range(i, 3):
                cov[:, i, j] = cov[:, j, i] = np.einsum("ck,ck->c", d[i], d[j]) / k - mean[i] * mean[j]
        vals, vecs = np.linalg.eigh(cov)  # ascending: the last is the line's direction
        centre[rows], u[rows] = middle + np.column_stack(mean), vecs[:, :, 2]
        off[rows] = np.sqrt(np.maximum(vals[:, 0] + vals[:, 1], 0.0))
    return centre, u, off


def wall_stretches(points_w: np.ndarray, t_s: np.ndarray, sweep_dir: np.ndarray, beam_w: np.ndarray,
                   sigma_m: np.ndarray, length_m: float, width_m: float, sample_dt_s: float,
                   only: np.ndarray | None = None, reach_m: float | None = None) -> np.ndarray:
    """True for points whose stretch of sweep (CHORD_HALF samples either side, one sweep direction, unbroken in
    time) is a straight line steeper than any stockpile stands (STEEPEST_PILE_DEG), beside a wall: within the
    reach of a heading error (MAX_HEADING_ERROR_RAD at the beam's horizontal length) plus 3 of its points'
    sigmas. Such a stretch is the wall, placed off its plane by what the structure tolerance does not hold: a
    heading error, which moves a wall seen at grazing incidence 20 m away by 0.35 m a degree, a pointing error, or
    a wall a few centimetres off the header's plane. beam_w: each point's vector from the vehicle; sigma_m: each
    point's 1-sigma error that straightness is judged by (`ground.pointcloud.beside_walls` leaves the pointing
    error out of it); only: the points to judge (None: all), their stretches still taken from every point; reach_m:
    how far beside a wall (None: a heading error's reach, above)."""
    h = CHORD_HALF
    m = len(points_w)
    out = np.zeros(m, dtype=bool)
    if m <= 2 * h:
        return out
    i = np.arange(h, m - h)
    p = np.asarray(points_w, dtype=float)
    reach = (np.hypot(beam_w[i, 0], beam_w[i, 1]) * math.tan(MAX_HEADING_ERROR_RAD) + 3.0 * sigma_m[i]
             if reach_m is None else np.full(len(i), float(reach_m)))
    near = (to_nearest_wall_m(p[i], length_m, width_m) <= reach) & unbroken(t_s, sweep_dir, i, sample_dt_s)
    if only is not None:
        near &= only[i]
    i, reach = i[near], reach[near]
    if not len(i):
        return out
    centre, u, off = sliding_line_fit(p, h, i)
    noise = np.sqrt(np.mean(np.square(sigma_m[i[:, None] + np.arange(-h, h + 1)]), axis=1))  # over its own window
    own_off = np.linalg.norm(np.cross(p[i] - centre, u), axis=1)  # the point itself lies on the line
    straight = (off <= 3.0 * noise) & (own_off <= 3.0 * sigma_m[i])
    steep = np.abs(u[:, 2]) >= math.sin(math.radians(STEEPEST_PILE_DEG))
    long_enough = off < 0.5 * np.linalg.norm(p[i + h] - p[i - h], axis=1)
    line_beside = to_nearest_wall_m(centre, length_m, width_m) <= reach  # the line too lies beside the wall
    out[i] = straight & steep & long_enough & line_beside
    return out
