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

How: (1) a vote per knot interval (only points whose stretch of sweep runs along a plane vote for it;
the plane is the outermost peak of their distances with nothing but stray points beyond it: a pile's flat
top, which may out-number a floor it hides, has the pile's flanks below it) gives a start and says where
each plane is seen; (2) robust least squares for the horizontal position (scipy's soft-L1 loss; each point
moves with its two knots only, linearly while the heading is held, so Newton's method finds the one minimum,
else scipy's trust-region solver with a sparse Jacobian) over the points the vote put on a plane, the
window shrinking to the data's own noise; (3) the height from the floor and from the pile
seen at different times (`vertical_from_crossings`: over a pile the floor is hidden, and that is where a
rangefinder-aided estimator's height is wrong), the vote's floor screened first across the flight
(`screen_floor`: a flat pile top the vote took for the floor lies above the floor's level once the crossings
align the flight); (4) optionally the heading from the walls, kept only when significant
(off by default: measured, it did more harm than good, docs/pose_error.md); (5) the position and the
heading registered on the pile seen at different times (`register_from_crossings`: on a slope a shift of a
stretch's points moves their height, so a sloped cell seen twice observes the along-track position the
walls leave to interpolation, and the heading, which moves a point by its lateral distance times it), with
a drift-smoothness prior (`bend_sigmas`), kept only when significant and when it leaves the walls on their
planes.

No harm: applied only when it brings the structure closer to its planes by more than fitting the same
number of parameters to noise would (a chi-square test in the data's own noise), the height only when
the crossings' misfit drops by more than noise fitting explains, and never when the drift fit to the floor and
walls leaves them more than MAX_MISFIT noise levels off their planes (a drift does not explain that; a mount
fault does). The walls see no height, so a height error alone (a lever arm's z, an altitude reference's offset)
matters to the floor only: the height alone is applied when it brings a floor the walls' feet confirm up onto z = 0
(`floor_brought_on`, judged on the floor's sightings: below z = 0 it is surely a height error, while above it may be
material covering the floor).
A height that drifts while the horizontal does not (a good horizontal estimate on a barometer that walks) leaves the
floor's points off every plane the walls' fit holds, so the floor and walls call it too small to matter; the pile seen
at different times sees it: the height alone is applied when it brings those sightings together by more than the
noise and more than is left (`crossings_brought_together`). A height off by a constant moves every sighting alike and
stays the floor's question.
And a horizontal lever arm entered off moves every point by one vector fixed to the body, which the knots would
follow leg by leg: where two numbers of the lever arm put the floor and walls on their planes as well as the knots do
(`lever_shift`), the points are placed with that lever arm instead, and the report names it.
The registration on the pile seen twice may trade some of the walls' fit for the crossings', up to MAX_MISFIT times
what the drift fit left; the height is solved again after it (`_height_again`).

The pieces this module builds on: its planes, options and knots (`ground.pose_knots`), the no-harm decisions above
(`ground.pose_decisions`), the robust sparse least squares of its linear fits (`ground.huber_lsq`); the report's words
for what it did are `ground.pose_warnings`.

With the mount's self-calibration (`ground.self_calibration`; item 3 of issue 15): the report calibrates
the mount first, from the logged poses, and corrects the pose after, with the calibrated mount. The
other order let the knots' shifts take up part of a constant mount error and the self-calibration then
found nothing (measured: docs/pose_error.md). A drift and a mount fault together are not solved: that
needs a joint estimate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import linalg, sparse
from scipy.optimize import least_squares
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame, rot_body_to_ned
from firmware_py.core.sensor_noise import POSE_STREAM_HZ
from firmware_py.core.storage import Storage
from ground.group_stats import group_median, median_sd_m, rms, robust_rms
from ground.huber_lsq import huber_loss, irls_huber, knot_covariance, mean_sigma_m
from ground.plane_stretches import (
    Beams,
    beams,
    body_axes_w,
    planes,
    stretch_floor_m,
    stretches_along,
    to_nearest_wall_m,
    usable,
)
from ground.pose_decisions import (
    capped_gain,
    crossings_brought_together,
    floor_brought_on,
    is_drift,
    matters,
)
from ground.pose_knots import (
    BAND,
    HELD,
    KNOT_SWEEPS,
    MAX_MISFIT,
    MIN_CELL_POINTS,
    MIN_VOTES,
    PLANE_NAMES,
    Component,
    PoseCorrectionOptions,
    corrected_points,
    knot_basis,
    knot_times,
    path_speed_m_s,
    prior_sigmas,
    sweep_period_from_samples,
)
from ground.sweep_heights import SweepHeights
from ground.uncertainty import shared_draws


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
    notes: tuple[str, ...] = ()
    """What was left out and why (e.g. the height, when the floor seen is not consistent)."""
    closest_wall: tuple[float, str, float, float] | None = None
    """The corrected path's nearest approach to a wall or the roof: (signed distance m, the surface, t_s on the log's
    clock, s since the log's first sample: what the report says, as its other times)."""
    height_sigma_m: float | None = None
    """The formal standard error of the height correction's mean over the survey (`mean_sigma_m`); None when the
    height was not corrected. The volume's interval carries it (ground.uncertainty, the pose term)."""
    open_floor_shift_m: float | None = None
    """How far on average anchoring the height on a floor seen only away from the walls moved it (`_screen`: nothing
    seen at a wall came down to it, so it may be a hollow in the pile); None when the floor was confirmed or not used.
    The report warns with what it moved the volume (`ground.volume_warnings.open_floor_warning`)."""
    height_unanchored_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """How long the corrected height was not tied to the floor (`floor_anchored`): (total s, and the longest such
    stretch's start and end on the log's clock; all 0 when tied throughout or not corrected)."""
    level_sigma_m: float | None = None
    """The standard error of the height's level (its mean over the flight) when that level does not rest on a floor
    the walls' feet confirm: then it is the logged altitude reference's, which the flight's data cannot check, and
    its error is the barometer's walk averaged over the flight (`level_sigma_m`). None when it rests on a confirmed
    floor, and when the height came from a downward rangefinder whose share was left in (`PoseCorrectionOptions.
    open_floor`): that error follows the pile, not a walk, and the report warns of it on its own. With
    open_floor_shift_m it is the other reading's: the level had the open floor not been the floor."""
    unexplained: bool = False
    """Not applied because the drift model, fitted, left the floor and walls more than MAX_MISFIT noise levels off
    their planes: something else bends the structure (a mounting error). The report then fits the mount with a drift
    (`ground.self_calibration.DriftNuisance`) and tries again."""
    step_sigma: np.ndarray | None = None
    """(4,) the knots' random-walk prior (`prior_sigmas`: x, y, z in m, heading in rad) when `unexplained`."""
    drift_fit: np.ndarray | None = None
    """(knots, 4) what the drift model's fit found (to the floor and walls, and the pile seen twice), when
    `unexplained` (not applied: `values` stay zero). A start for the mount fitted with a drift: bent by the mount, it
    is still nearer the drift than none is where the structure pins it only loosely."""
    lever_change_m: tuple[float, float] | None = None
    """The LiDAR's lever arm moved by this much (body forward, right; m) puts the floor and walls on their planes as
    well as a drift's correction does (`lever_shift`): a lever arm entered off. Applied in place of the knots (which
    then stay zero): every sample is placed with it. The report warns with the lever arm they fit."""
    untied_sigma_m: float | None = None
    """The standard error the stretches of the flight whose height no floor tied (`floor_anchored`) put on the height's
    mean over the survey: the altitude reference's walk over each such stretch, weighted by its share of the flight
    (`untied_sigma_m`); 0 when tied throughout, None when the height was not corrected or came from a downward
    rangefinder whose share was left in. The volume's interval carries it when the level itself rests on a floor
    (else the level term, `level_sigma_m`, already spans the whole flight)."""
    sweep_heights: SweepHeights | None = None
    """The height refined sweep by sweep from the floor each sweep saw, on top of the knots (`ground.sweep_heights`);
    None when not made (not applied, or the height's level rests on no confirmed floor)."""

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """(N, 4) the correction at times t_s (linear between knots, held beyond the ends; the sweeps' heights on
        top)."""
        t = np.asarray(t_s, dtype=float)
        if len(self.knot_t_s) == 0:
            return np.zeros((len(t), 4))
        out = np.column_stack([np.interp(t, self.knot_t_s, self.values[:, c]) for c in range(4)])
        if self.sweep_heights is not None:
            out[:, 2] += self.sweep_heights.at(t)
        return out

    def size(self) -> dict[str, float]:
        """RMS and max over time of the horizontal, vertical and heading correction (at the knots)."""
        v = self.values if len(self.values) else np.zeros((1, 4))
        h = np.hypot(v[:, 0], v[:, 1])
        return {"horizontal_rms_m": rms(h), "horizontal_max_m": float(h.max()),
                "vertical_rms_m": rms(v[:, 2]), "vertical_max_m": float(np.abs(v[:, 2]).max()),
                "heading_rms_deg": math.degrees(rms(v[:, 3])),
                "heading_max_deg": math.degrees(float(np.abs(v[:, 3]).max()))}

    def free_intervals(self, component: Component) -> np.ndarray | None:
        """(K - 1,) the knot intervals whose both ends the data did not constrain (the prior interpolated the
        component there); None when the component was held at zero (not estimated)."""
        if not np.abs(self.values[:, component.value]).max(initial=0.0) > 1e-9:
            return None
        free = ~self.constrained[:, component.value]
        return free[:-1] & free[1:]

    def unconstrained_s(self) -> dict[str, float]:
        """Per component, the time (s) over which the data did not constrain it (`free_intervals`)."""
        if len(self.knot_t_s) < 2:
            return {c.name.lower(): 0.0 for c in Component}
        dt = np.diff(self.knot_t_s)
        free = {c: self.free_intervals(c) for c in Component}
        return {c.name.lower(): float(dt[f].sum()) for c, f in free.items() if f is not None}

    def as_dict(self) -> dict:
        return {"applied": self.applied, "reason": self.reason, "knot_spacing_s": _spacing(self.knot_t_s),
                "knot_t_s": [float(v) for v in self.knot_t_s], "knot_values": self.values.tolist(),
                "n_knots": len(self.knot_t_s), **self.size(), "unconstrained_s": self.unconstrained_s(),
                "points_per_plane": dict(zip(PLANE_NAMES, self.points, strict=True)),
                "rms_before_m": self.rms_before_m, "rms_after_m": self.rms_after_m, "noise_m": self.noise_m,
                "gain": self.gain, "gain_needed": self.gain_needed, "notes": list(self.notes),
                "height_sigma_m": self.height_sigma_m, "open_floor_shift_m": self.open_floor_shift_m,
                "level_sigma_m": self.level_sigma_m, "untied_sigma_m": self.untied_sigma_m,
                "lever_change_m": None if self.lever_change_m is None else list(self.lever_change_m),
                "height_unanchored_s": self.height_unanchored_s[0],
                "height_unanchored_longest_s": [self.height_unanchored_s[1], self.height_unanchored_s[2]],
                "closest_wall": None if self.closest_wall is None else dict(
                    zip(("distance_m", "surface", "t_s", "since_start_s"), self.closest_wall, strict=True)),
                "sweep_heights": None if self.sweep_heights is None else self.sweep_heights.as_dict()}


def _spacing(knots: np.ndarray) -> float:
    return float(np.median(np.diff(knots))) if len(knots) > 1 else 0.0


def not_applied(reason: str, knots: np.ndarray | None = None, **kw) -> PoseCorrection:
    """No correction, and why."""
    k = np.zeros(0) if knots is None else knots
    return PoseCorrection(k, np.zeros((len(k), 4)), np.zeros((len(k), 4), dtype=bool), False, reason, **kw)


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
STRAY_FRACTION = 0.01
"""Points beyond a plane a knot interval may hold by chance (glitches, multipath): 1 % of its points."""
PEAK_FRACTION = 0.1
"""A peak of the vote counts when it holds at least this fraction of the highest bin's points."""


def _peaks(h: np.ndarray) -> list[int]:
    """The histogram's local maxima that hold at least MIN_VOTES points and PEAK_FRACTION of the highest
    (smoothed over three bins)."""
    sm = np.convolve(h, np.ones(3), mode="same")
    need = max(MIN_VOTES, PEAK_FRACTION * float(sm.max()))
    left = np.concatenate([[-1.0], sm[:-1]])
    right = np.concatenate([sm[1:], [-1.0]])
    top = np.flatnonzero((sm >= need) & (sm >= left) & (sm > right))
    return [int(np.argmax(h[max(m - 1, 0):m + 2]) + max(m - 1, 0)) for m in top]


WALLS = np.array([name != "floor" for name in PLANE_NAMES])


def ambiguous_walls(dist: np.ndarray, reach_m: float) -> np.ndarray:
    """(N,) True where a point's stretch runs along two walls within reach (dist: (N, 5) its distances from the
    planes it runs along, inf elsewhere). A sweep plane cuts every wall in a vertical line, so when it crosses two
    of them (a diagonal heading: the yaw of a turn) a stretch up one wall runs along both, and with metres of drift
    the nearer of the two is a guess: measured on a `flow` flight's last corner (4 m of drift in x), the wall x = 0
    taken for y = 0 moved the last knot 0.85 m along the track. Such a point votes in `_vote`'s second round, for the
    wall it is nearest once the unambiguous intervals around it have set the drift."""
    near = np.isfinite(dist[:, WALLS]) & (np.abs(dist[:, WALLS]) <= reach_m)
    return near.sum(axis=1) > 1


def _vote(b: Beams, k: np.ndarray, n: np.ndarray, d: np.ndarray, n_knots: int, reach_m: float,
          bin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A start (K, 4), and which planes were found in each knot interval (K - 1, 5).

    Per knot interval and plane, the peaks of the distances to the plane of the points whose stretch of
    sweep runs along it (a plane's own points pile up at one offset); the plane is the outermost peak
    beyond which lie no more points of any kind than stray returns: nothing is below the floor or behind
    a wall but noise, while a flat pile top, which may hold more points than the floor beside it, has the
    pile's flanks below it. Averaged to the knots, interpolated where no plane was found; heading 0.

    A point whose stretch runs along two walls within reach (`ambiguous_walls`) votes in a second round only,
    for the wall it is nearest once the first round's correction (the unambiguous points', interpolated over
    the intervals) has moved it: the drift of the intervals around it, not its logged position, says which."""
    p = b.vehicle_w + b.to_point_w
    dist_all = p @ n.T - d
    dist = dist_all if b.parallel is None else np.where(b.parallel, dist_all, math.inf)
    amb = ambiguous_walls(dist, reach_m)
    est, found = _tally(np.where(amb[:, None], math.inf, dist), dist_all, k, n_knots, reach_m, bin_m)
    filled = _across_intervals(est, np.arange(n_knots - 1) + 0.5)  # each interval's, or its neighbours'
    if amb.any() and np.isfinite(filled).any():
        moved = dist[amb] + np.nan_to_num(filled)[k[amb]] @ n.T  # the correction c moves plane j's distance by n_j . c
        pick = np.argmin(np.abs(moved), axis=1)
        keep = np.full(dist[amb].shape, math.inf)
        rows = np.arange(int(amb.sum()))
        keep[rows, pick] = dist[amb][rows, pick]
        dist = dist.copy()
        dist[amb] = keep
        est, found = _tally(dist, dist_all, k, n_knots, reach_m, bin_m)
    out = np.zeros((n_knots, 4))
    out[:, :3] = np.nan_to_num(_across_intervals(est, np.arange(n_knots, dtype=float)))
    return out, found


def _across_intervals(est: np.ndarray, at: np.ndarray) -> np.ndarray:
    """est (K - 1, 3), one row per knot interval (placed at its middle, i + 0.5), interpolated per component at
    positions `at` (knot indices) from the intervals that have it; NaN where no interval has it."""
    mids = np.arange(len(est)) + 0.5
    out = np.full((len(at), est.shape[1]), np.nan)
    for c in range(est.shape[1]):
        ok = np.isfinite(est[:, c])
        if ok.any():
            out[:, c] = np.interp(at, mids[ok], est[ok, c])
    return out


def _tally(dist: np.ndarray, dist_all: np.ndarray, k: np.ndarray, n_knots: int, reach_m: float,
           bin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """`_vote`'s count: per knot interval, the correction (K - 1, 3; NaN where no plane was found) and which planes
    were found, from the points' distances to the planes they may vote for (dist, inf elsewhere)."""
    bins = np.arange(-reach_m, reach_m + bin_m, bin_m)
    comp_of_plane = (2, 0, 0, 1, 1)
    est = np.full((n_knots - 1, 3), np.nan)
    found = np.zeros((n_knots - 1, 5), dtype=bool)
    # each interval's points as one contiguous slice (a stable sort: the samples come in time order, so it is
    # usually the identity), not a mask over the whole survey per interval and plane
    order = np.argsort(k, kind="stable")
    k, dist, dist_all = k[order], dist[order], dist_all[order]
    nearest = np.argmin(np.abs(dist), axis=1)
    bounds = np.searchsorted(k, np.arange(n_knots))
    for i in range(n_knots - 1):
        here = slice(bounds[i], bounds[i + 1])
        near_i, dist_i, all_i = nearest[here], dist[here], dist_all[here]
        sums, cnt = np.zeros(3), np.zeros(3)
        for j in range(5):
            r = dist_i[near_i == j, j] * INSIDE_SIGN[j]  # > 0: inside the building
            r = r[np.abs(r) <= reach_m]
            if len(r) < MIN_VOTES:
                continue
            inside_all = np.sort(all_i[:, j] * INSIDE_SIGN[j])
            stray = max(MIN_VOTES, STRAY_FRACTION * len(inside_all))
            h, _ = np.histogram(r, bins)
            for m in _peaks(h):
                sel = r[(r >= bins[m] - bin_m) & (r <= bins[m + 1] + bin_m)]
                off = float(np.median(sel))
                if np.searchsorted(inside_all, off - 2.0 * bin_m) <= stray:
                    c = comp_of_plane[j]
                    sums[c] -= off * INSIDE_SIGN[j] * len(sel)  # the correction moves them back
                    cnt[c] += len(sel)
                    found[i, j] = True
                    break
        est[i] = np.where(cnt > 0, sums / np.maximum(cnt, 1), np.nan)
    return est, found


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
    """Rows of the prior: knot-to-knot changes in step sigmas, then each knot's value in absolute sigmas
    ((4,) or per knot (K, 4))."""
    abs_sigma = np.broadcast_to(abs_sigma, (n_knots, 4))
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
            data.append(1.0 / abs_sigma[i, c])
            r += 1
    return sparse.csr_matrix((data, (rows, cols)), shape=(r, n_par))


def _fit_round(b: Beams, k: np.ndarray, f: np.ndarray, n: np.ndarray, d: np.ndarray, x0: np.ndarray,
               window: float, prior: sparse.csr_matrix, j: np.ndarray,
               bound: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
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

    hi = np.full(x0.size, np.inf) if bound is None else bound.ravel()
    start = np.clip(x0.ravel(), -hi * 0.999, hi * 0.999)
    held = hi <= HELD
    if held.reshape(n_knots, 4)[:, 3].all() and np.isinf(hi[~held]).all():
        # the heading held: the points move linearly with the knots, a convex problem solved exactly (Newton)
        jd = _jacobian(bs, corrected_points(bs, start.reshape(n_knots, 4), ks, fs)[1], ks, fs, nj, s, 4 * n_knots)
        return _soft_l1_linear(sparse.vstack([jd, prior], format="csr"), resid(start), start, ~held
                               ).reshape(n_knots, 4), j
    sol = least_squares(resid, start, jac=jac, loss="soft_l1", f_scale=1.0,
                        tr_solver="lsmr", x_scale="jac", max_nfev=50, bounds=(-hi, hi))
    return sol.x.reshape(n_knots, 4), j


SOFT_L1_TOL_M = 1e-7
"""The linear soft-L1 fit stops when a Newton step moves no knot by more than this (a tenth of a micrometre: far
below any sensor's resolution, so the answer is the minimum's)."""


def _soft_l1_linear(a: sparse.csr_matrix, r0: np.ndarray, x0: np.ndarray, free: np.ndarray,
                    max_steps: int = 100) -> np.ndarray:
    """argmin sum rho(r^2), rho(z) = 2 (sqrt(1 + z) - 1) (scipy's soft-L1, on every row, the prior's too), for
    residuals linear in x: r = r0 + a (x - x0), only the `free` columns moving. The loss is convex in r, so
    Newton's method with a backtracking line search finds the one minimum, in a few dense solves of the small
    normal equations; scipy's trust-region solver took 5-14 evaluations, each with inner sparse iterations, and
    stopped on its cost tolerance a little short of it (0.28 s of a report)."""
    if not free.any():
        return x0.copy()
    af = a[:, np.flatnonzero(free)].tocsc()
    aft = af.T.tocsr()
    dx = np.zeros(af.shape[1])

    def cost(r: np.ndarray) -> float:
        return float(np.sum(np.sqrt(1.0 + r * r) - 1.0))
    r = r0.copy()
    c = cost(r)

    def step_with(curvature: np.ndarray) -> np.ndarray:
        hess = (aft @ af.multiply(curvature[:, None])).toarray()
        try:
            return -linalg.solve(hess, grad, assume_a="pos")
        except linalg.LinAlgError:
            return -linalg.lstsq(hess, grad)[0]
    for _ in range(max_steps):
        q = 1.0 + r * r
        grad = aft @ (r / np.sqrt(q))
        # Newton's step where it lowers the cost enough (near the minimum: quadratic convergence); else, far out where
        # the loss's curvature vanishes and Newton overshoots, the re-weighted least-squares step, which always
        # lowers it (it minimises a quadratic that lies above the loss and touches it here)
        step = step_with(q ** -1.5)
        r_new = r + af @ step
        c_new = cost(r_new)
        if not c_new <= c + 1e-4 * float(grad @ step):
            step = step_with(q ** -0.5)
            r_new = r + af @ step
            c_new = cost(r_new)
        dx += step
        r, c = r_new, c_new
        if np.max(np.abs(step), initial=0.0) < SOFT_L1_TOL_M:
            break
    x = x0.copy()
    x[free] += dx
    return x


def _noise_m(j: np.ndarray, r: np.ndarray, floor_m: float) -> float:
    """The structure's noise along its normals: consecutive samples on one plane (a pose error moves
    neighbours alike, so their difference is the noise), never under floor_m."""
    on = np.flatnonzero(j >= 0)
    same = (np.diff(on) == 1) & (j[on[1:]] == j[on[:-1]])
    if not same.any():
        return floor_m
    return max(robust_rms(np.diff(r[on])[same]) / math.sqrt(2.0), floor_m)


def estimate_pose_correction(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, storage: Storage,
                             resolution_m: float, range_sigma_m: float = 0.0, range_sigma_rel: float = 0.0,
                             angle_sigma_rad: float = 0.0, sweep_period_s: float | None = None,
                             boresight: Boresight = SQUARE,
                             opts: PoseCorrectionOptions | None = None,
                             position_sigma_m: float = 0.0,
                             placed: tuple[Beams, np.ndarray] | None = None,
                             pose_draw_sigma_m: float = 0.0, pose_stream_hz: float = POSE_STREAM_HZ) -> PoseCorrection:
    """Estimate the trajectory's correction from the floor and walls (module docstring).

    Args:
        samples: the survey's samples (SAMPLE_DTYPE), in time order; unusable ones are left out here.
        lever_arm_body_m, frame, storage, boresight: the log header's geometry.
        resolution_m, range_sigma_m, range_sigma_rel: the header's sensor model (the vote's bin, the
            noise floor).
        sweep_period_s: the servo's period (the header's); None: from the logged sweep directions.
        angle_sigma_rad, position_sigma_m: each sample's own pointing and position errors (the header's
            ``sensor_noise``): white, so no drift, but they scatter the points about the planes.
        placed: `placed_beams` of these samples with these arguments, if the caller has made it (the mount's
            self-calibration asks the same stretches: made once).
        pose_draw_sigma_m, pose_stream_hz: of position_sigma_m, the part one pose message's samples share, and the
            messages a second (the header's): what a floor seen in few messages knows of its level (`level_clear`).
    """
    opts = opts or PoseCorrectionOptions()
    b, sweep_dir = placed or beams(samples, lever_arm_body_m, frame, boresight)
    if len(b.t_s) < opts.min_structure_points:
        return not_applied(f"too few usable samples ({len(b.t_s)}) to correct the pose from the building")
    period = sweep_period_s or sweep_period_from_samples(samples["t_s"], samples["sweep_dir"])
    spacing = opts.knot_spacing_s or (KNOT_SWEEPS * period if period else None)
    if spacing is None or not spacing > 0:
        return not_applied("the sweep period is unknown (no servo frequency in the header, too few sweeps): no knot "
                           "spacing for the pose correction")
    n, d = planes(storage)
    floor_m = stretch_floor_m(resolution_m)
    if placed is None:
        b = replace(b, parallel=stretches_along(b, sweep_dir, n, range_sigma_m, range_sigma_rel, angle_sigma_rad,
                                                floor_m, position_sigma_m))
    stride = max(1, len(b.t_s) // opts.max_points)
    b = b.take(slice(None, None, stride))
    t0, t1 = float(b.t_s.min()), float(b.t_s.max())
    knots = knot_times(t0, t1, spacing)
    k, f = knot_basis(b.t_s, knots)
    # what the data alone give: the sensor's error at the median range (the vote's bin), the data's noise.
    # The pointing and position errors the header states are in it: a degree at 12 m scatters the points by
    # 0.2 m, and with the range's 2.5 cm alone the noise was read from a sliver of that scatter, so a knot fitted
    # to the rest looked significant (an error-free flight with the paper's Appendix A noise: 33 pp of Ve).
    rng_med = float(np.median(np.linalg.norm(b.to_point_w, axis=1)))
    sensor_m = max(math.hypot(max(range_sigma_m, range_sigma_rel * rng_med), angle_sigma_rad * rng_med,
                              position_sigma_m), resolution_m)
    p0 = b.vehicle_w + b.to_point_w
    j0, r0 = _assign(p0, n, d, opts.max_position_error_m, b.parallel)
    # The data's noise comes from neighbouring samples, which share a pose message: a position error drawn per
    # message (the header's; Appendix A's 0.11 m) is not in it, yet it scatters the points about their planes
    # and no knot seconds apart can fit it (an error-free flight: 0.32 m of "correction" on 1 of 648 runs).
    noise = math.hypot(_noise_m(np.where(np.abs(r0) <= sensor_m, j0, -1), r0, floor_m), position_sigma_m)
    speed = path_speed_m_s(b.t_s, b.vehicle_w, period or spacing / KNOT_SWEEPS)
    if not speed > 0:  # a log of one instant, or one sweep longer than it, or a vehicle that never moved
        return not_applied(f"the logged path does not move over the sweeps ({t1 - t0:.1f} s of samples): nothing "
                           "along a path to correct the pose from")
    step = prior_sigmas(spacing, speed, opts)
    absolute = np.array([opts.max_position_error_m] * 3 + [opts.max_heading_error_rad])
    held = np.array([False, False, not opts.vertical or opts.crossings, not opts.heading])
    absolute = np.where(held, absolute * HELD, absolute)  # a held component stays at zero
    # The heading's absolute prior grows from the log's start as the gyro's drift does (one knot step at the
    # start): a gyro-integrated heading cannot be degrees off after a minute, and a few systematic
    # millimetres on the walls would otherwise buy a heading the drift model does not allow.
    elapsed = knots - knots[0]
    absolute = np.tile(absolute, (len(knots), 1))
    absolute[:, 3] = np.minimum(absolute[:, 3], step[3] + opts.heading_bias_rad_s * elapsed
                                + opts.heading_walk_rad_per_sqrt_s * np.sqrt(elapsed))
    if held[3]:
        absolute[:, 3] = opts.max_heading_error_rad * HELD
    prior = _prior_matrix(len(knots), step, absolute)
    # Nor may the data push a component beyond N_SIGNIFICANT of its prior (a few pile points taken for a
    # wall bought six degrees of heading in one stretch): a drift that large is not this model's.
    bound = np.where(held[None, :], 1e-12, opts.n_significant * absolute)
    bound[:, :3] = np.where(held[None, :3], 1e-12, np.inf)
    x, found = _vote(b, k, n, d, len(knots), opts.max_position_error_m, sensor_m)
    z_vote = x[:, 2].copy()
    x[:, held] = 0.0
    # Only the planes the vote found in a knot interval hold it: where the floor is hidden (under a pile),
    # a flat part of the pile near where the floor would be must not pass for it.
    b = replace(b, parallel=b.parallel & found[k])
    final = 3.0 * noise
    j_fit, _ = _assign(corrected_points(b, x, k, f)[0], n, d, BAND * sensor_m, b.parallel)
    jf = np.maximum(j_fit, 0)

    def on_fit_planes(v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The points placed with correction v, their beam vectors, their signed distances from the planes the
        start gave them, and each one's plane where within BAND final windows of it (-1: none)."""
        p, beam = corrected_points(b, v, k, f)
        r = np.einsum("ij,ij->i", p, n[jf]) - d[jf]
        return p, beam, r, np.where(np.abs(r) <= BAND * final, j_fit, -1)

    def plane_fit(x: np.ndarray, prior: sparse.csr_matrix, bound: np.ndarray) -> np.ndarray:
        # windows: from what the vote leaves (its bin) down to the data's noise
        window = sensor_m
        for _ in range(12):
            x, _ = _fit_round(b, k, f, n, d, x, window, prior, j_fit, bound)
            if window <= final:
                break
            _, r = _assign(corrected_points(b, x, k, f)[0], n, d, BAND * window, b.parallel)
            on = j_fit >= 0
            window = max(final, min(window / 2.0, BAND * robust_rms(r[on]) if on.any() else window / 2.0))
        return x

    # First without the heading, then with it, which is kept only when it brings the floor and walls closer
    # by more than fitting its knots to noise would: the walls beside a track do not see it, and on an
    # error-free flight a few systematic millimetres bought a tenth of a degree.
    no_heading = absolute.copy()
    no_heading[:, 3] = opts.max_heading_error_rad * HELD
    bound_nh = bound.copy()
    bound_nh[:, 3] = 1e-12
    x = plane_fit(x, _prior_matrix(len(knots), step, no_heading), bound_nh)
    heading_gain = 0.0
    if not held[3]:
        x_h = plane_fit(x, prior, bound)
        sel0 = j_fit >= 0
        jj0 = np.maximum(j_fit, 0)
        cap0 = (BAND * sensor_m / noise) ** 2

        def chi2(v: np.ndarray) -> float:
            q = corrected_points(b, v, k, f)[0]
            r = (np.einsum("ij,ij->i", q, n[jj0]) - d[jj0])[sel0] / noise
            return float(np.sum(np.minimum(r * r, cap0)))
        heading_gain = chi2(x) - chi2(x_h)
        if heading_gain > len(knots) + opts.n_significant * math.sqrt(2.0 * len(knots)):
            x = x_h
        else:
            held = held.copy()
            held[3] = True
    p1, vr, r1, j1 = on_fit_planes(x)
    on = j1 >= 0
    counts = tuple(int(np.count_nonzero(j1 == i)) for i in range(5))
    if np.count_nonzero(j_fit >= 0) < opts.min_structure_points:  # the start's: the floor's height comes later
        return not_applied(f"too few points on the floor and walls ({int(np.count_nonzero(j_fit >= 0))}) to correct "
                           "the pose", points=counts)
    z_info = None
    tied: np.ndarray | None = None  # per knot interval, whether the height is tied to the floor (`floor_anchored`)
    first_refused: str | None = None  # why the height solved before the registration was refused
    z_sigma: list[float] = []  # the standard errors of the height's mean, the last solve's last
    notes: list[str] = []
    open_floor_shift: float | None = None  # what a floor the walls' feet do not confirm moved the height, when used
    height_floor: np.ndarray | None = None  # the floor the applied height rests on, when the walls' feet confirm it
    # whether the height's level rests on a floor the walls' feet confirm (else on the logged reference): without
    # the crossings the walls' fit solves the height from the floor plane, when it saw one
    level_on_floor = opts.vertical and not opts.crossings and counts[0] > 0
    if opts.vertical and opts.crossings:
        cell_m = speed * (period or spacing / KNOT_SWEEPS)
        # how far a floor seen only away from the walls may move the height (`_screen`): anywhere when the height
        # came from the rangefinder, else the barometer's walk over the flight (`PoseCorrectionOptions.open_floor`)
        open_shift = math.inf if opts.open_floor else opts.vertical_walk_m_per_sqrt_s * math.sqrt(t1 - t0)
        # the floor: points along it, in intervals where the vote found it, near the height it found
        z_at = np.interp(b.t_s, knots, z_vote)
        voted = b.parallel[:, 0] & (np.abs(p1[:, 2] + z_at) <= BAND * sensor_m)
        wall = (j1 >= 1) | (j_fit >= 1)

        def height_from(floor: np.ndarray, shift: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None,
                                                                              str | None]:
            """The height correction on this floor (shift: the screen's, when it dropped most of the vote's
            floor), its information, and why it was refused (None: not refused)."""
            z, z_info = height_rounds(p1, b.t_s, knots, wall, floor, storage, cell_m, step[2], noise,
                                      opts.max_position_error_m, opts.n_significant, z_sigma)
            if z is None:
                return None, None, None
            if shift is not None:
                z = shift  # most of the vote's floor was a flat pile top: the crossings, at the floor's level
            refused = height_refused(z, knots, step[2], opts.n_significant, opts.max_vertical_error_m)
            if refused is not None:
                return None, None, refused
            return z, z_info, None

        floor, z_shift, floor_note, confirmed = screen_floor(p1, b.t_s, knots, wall, voted, storage, cell_m, step[2],
                                                             noise, sensor_m, opts.max_position_error_m)
        z, z_info, refused = height_from(floor, z_shift)
        if refused is not None and z_shift is not None:
            # The screen's level is the lowest the crossings' frame shows, and a stretch the crossings place a few
            # decimetres low can set it (measured: a networked `flow` flight over pile 1, which has no flat top).
            # When what it leaves is refused, the vote's own floor is tried, under the same two checks.
            z_voted, info_voted, refused_voted = height_from(voted, None)
            if refused_voted is None:
                why = refused.removeprefix("the height was not corrected: ")
                floor_note = (f"{floor_note}, but the height from what was left was refused ({why}), so the "
                              "floor as voted was used")
                floor, z, z_info, refused = voted, z_voted, info_voted, None
        unconfirmed = None if z is None else floor_unconfirmed_note(z, confirmed, open_shift)
        if unconfirmed is not None:
            floor, floor_note = np.zeros_like(floor), unconfirmed
            z, z_info, refused = height_from(floor, None)
        elif z is not None and not confirmed and floor.any():
            # used, and said (as a note of its own: a floor note would have the height solved again): the surveyor
            # reads that the level rests on a floor nothing at a wall confirms
            open_floor_shift = float(np.mean(z))
            notes.append(open_floor_note("anchored", open_floor_shift))
        level_on_floor = z is not None and confirmed and bool(floor.any())
        notes.extend(note for note in (floor_note, refused) if note)
        first_refused = refused
        if z is not None:
            x[:, 2] = z
            p1, vr = corrected_points(b, x, k, f)
            floor = floor_from_below(p1, b.t_s, knots, np.zeros(len(knots)), floor, opts.n_significant)
            tied = floor_anchored(p1, b.t_s, knots, wall, floor, storage, cell_m, opts.max_position_error_m)
            height_floor = floor if level_on_floor else None
    # Which knot components the data set (their information beats the prior's): the rest is interpolated.
    sel = np.flatnonzero(on)
    jac = _jacobian(b.take(sel), vr[sel], k[sel], f[sel], n[j1[sel]], np.full(len(sel), noise), 4 * len(knots))
    info = np.asarray(jac.multiply(jac).sum(axis=0)).ravel().reshape(len(knots), 4)
    if held[3]:
        # The walls' fit held the heading at zero: what they would say of it was not used, so it neither anchors the
        # registration's heading at that zero nor counts as constraining it (measured: it held the heading of our own
        # building's flights 1-2.5 deg short where only the far side of a pile was seen twice: docs/design-notes.md).
        info[:, 3] = 0.0
    if z_info is not None:
        info[:, 2] = z_info
    cross_info = None
    # The walls decide whether anything is applied (below), and the registration is anchored on them: when the
    # correction so far is too small to matter to them, the registration is not tried (it cost ~6 s on an
    # error-free 94k-sample log, which it never changed: docs/design-notes.md, 2026-11-28).
    j_pre, _ = _assign(p0, n, d, BAND * sensor_m, b.parallel)
    pre = (j_pre >= 0) | on
    jj_pre = np.where(j_pre >= 0, j_pre, j1)[pre]
    to_matter = matters(np.einsum("ij,ij->i", p0[pre], n[jj_pre]) - d[jj_pre], r1[on],
                        np.einsum("ij,ij->i", p1[pre], n[jj_pre]) - d[jj_pre], jj_pre, noise)

    def misfit(v: np.ndarray) -> float:
        _, _, r, j = on_fit_planes(v)
        return robust_rms(r[j >= 0])
    # What the drift model, fitted to the floor and walls, leaves on them: the measure of whether a drift
    # explains them at all (MAX_MISFIT was measured on it: a drift leaves 1.1-1.5 noise levels, a mount fault ~6)
    drift_misfit = misfit(x)
    if opts.vertical and opts.crossings and opts.crossings_horizontal and to_matter:
        # the height joins the registration when it was solved, or refused only in the frame before it
        z_free = z_info is not None or first_refused is not None
        x_reg, cross_info, cross_notes = _registered(b, x, knots, k, f, wall, floor, storage, cell_m, step, noise,
                                                     sensor_m, info, sel, z_free, held[3], opts)
        if cross_info is not None:
            # No harm to the walls: the registration trades some of their fit for the pile seen twice, but one that
            # leaves them more than MAX_MISFIT times as far off as the drift fit did (or the noise, if more) is
            # dropped. (Against the noise alone, an ideal sensor's 0.3 cm range quantum, this refused registrations
            # that took two `flow` flights from 1.15 and 0.84 m of trajectory error to 0.09 m: docs/design-notes.md.)
            reg_misfit = misfit(x_reg)
            if reg_misfit > MAX_MISFIT * max(noise, drift_misfit):
                notes.append(f"the position from the pile seen at different times was not used: it left the floor "
                             f"and walls {reg_misfit * 100:.1f} cm off their planes, against "
                             f"{drift_misfit * 100:.1f} cm without it")
                cross_info, cross_notes = None, []
            else:
                x = x_reg
                if (z_info is not None and floor_note is not None) or first_refused is not None:
                    # The first height was solved in the frame before the registration (`_height_again`); refused
                    # there, it is tried again in the registered frame: on slopes the horizontal error before it
                    # shows as height (measured: a two-knot zigzag of +0.95 / -0.88 m on our own ridge, refused
                    # as a jump, and the flight's volume 32 % off without any height correction).
                    x, z_again, again_note, sigma_again, floor_again, shift_again = _height_again(
                        b, x, k, f, knots, wall, voted, storage, cell_m, step[2], noise, sensor_m,
                        opts.max_position_error_m, opts.n_significant, opts.max_vertical_error_m, open_shift)
                    if again_note:
                        z_info = info[:, 2] = z_again
                        if sigma_again is not None:
                            z_sigma.append(sigma_again)
                        if first_refused is not None:
                            notes.remove(first_refused)
                            why = first_refused.removeprefix("the height was not corrected: ")
                            again_note = (f"the height solved before the pile seen at different times aligned the "
                                          f"flight was refused ({why}); {again_note}")
                        notes.append(again_note)
                        open_floor_shift = shift_again  # this height replaces the first
                        level_on_floor = shift_again is None
                        height_floor = floor_again if level_on_floor else None
                        if shift_again is not None:  # on a floor the walls' feet do not confirm: said, as the first
                            notes.append(open_floor_note("solved again", shift_again))
                        tied = floor_anchored(corrected_points(b, x, k, f)[0], b.t_s, knots, wall, floor_again,
                                              storage, cell_m, opts.max_position_error_m)
                    elif first_refused is not None:
                        x[:, 2] = 0.0  # refused again: no height, as before (the registration's own is unchecked)
                        level_on_floor = False
                        height_floor = None
        notes += cross_notes
        if cross_info is not None:
            info[:, :2] += cross_info[:, :2]
            if np.abs(x[:, 3]).max() > 0:
                info[:, 3] += cross_info[:, 3]
                held = held.copy()
                held[3] = False
            p1, vr, r1, j1 = on_fit_planes(x)
            on = j1 >= 0
    estimated = np.array([True, True, opts.vertical and (z_info is not None or not opts.crossings), not held[3]])
    constrained = (info * (step ** 2)[None, :] >= 1.0) & estimated[None, :]
    # The same points on the same planes before and after, in noise sigmas: the chi-square gain against
    # what fitting the constrained parameters to noise would give.
    # The points counted are those on a plane before the correction (the start's window) or after it, of
    # those whose stretch of sweep runs along the plane where the vote found it (so a pile pulled onto the
    # floor does not count as a gain).
    j_before, _ = _assign(p0, n, d, BAND * sensor_m, b.parallel)
    both = (j_before >= 0) | on
    jj = np.where(j_before >= 0, j_before, j1)[both]
    r_before = np.einsum("ij,ij->i", p0[both], n[jj]) - d[jj]
    r_after = np.einsum("ij,ij->i", p1[both], n[jj]) - d[jj]
    cap = (BAND * sensor_m / noise) ** 2
    gain = capped_gain(r_before, r_after, noise, cap)
    n_free = int(constrained.sum())
    needed = n_free + opts.n_significant * math.sqrt(2.0 * max(n_free, 1))
    common = dict(notes=tuple(notes), points=counts, rms_before_m=robust_rms(r_before),
                  rms_after_m=robust_rms(r1[on]), noise_m=noise, gain=gain, gain_needed=needed)
    if drift_misfit > MAX_MISFIT * noise:
        return not_applied(f"not applied: the floor and walls stay {drift_misfit * 100:.1f} cm off their "
                           f"planes "
                           f"after it, against {noise * 100:.1f} cm of noise: a drifting pose does not explain them "
                           "(a mounting error the self-calibration did not fit?)", knots, unexplained=True,
                           step_sigma=step, drift_fit=x.copy(), **common)
    # The floor the height rests on counts when the correction brings it up onto z = 0 (`floor_brought_on`): the
    # walls see no height and the fit's points hold no floor it moved, so a height off by a constant (a lever arm's z,
    # an altitude reference's offset) was "too small to matter" to them (measured: a flight whose only error was a
    # lever arm's z 0.2 m too far down, 6.8 % low; docs/design-notes.md).
    # Then the height alone is applied: what the walls' fit found did not matter to them, and its significance is
    # the floor's (the same chi-square gain, on the floor's points, against fitting the height's knots to noise).
    raised = None
    mattered = matters(r_before, r1[on], r_after, jj, noise)
    if height_floor is not None and not mattered:
        x_z = np.zeros_like(x)
        x_z[:, 2] = x[:, 2]
        z_before, z_after = p0[height_floor, 2], corrected_points(b, x_z, k, f)[0][height_floor, 2]
        on_floor = p0[height_floor]
        _, _, cid = _cells(on_floor, storage, cell_m)
        wall_distance = to_nearest_wall_m(on_floor, storage.length_m, storage.width_m)
        material = (_in_building(p0, wall, storage, opts.max_position_error_m) & ~height_floor
                    & (p0[:, 2] > float(np.median(z_before)) + MAX_MISFIT * noise))
        material_distance = (cKDTree(p0[material, :2]).query(on_floor[:, :2])[0] if material.any() else None)
        draws = shared_draws(b.t_s[height_floor], pose_draw_sigma_m, pose_stream_hz)
        if floor_brought_on(z_before, z_after, cid * len(knots) + k[height_floor], noise, open_shift, wall_distance,
                            material_distance, draws, opts.n_significant, resolution_m):
            raised = float(np.median(z_after - z_before))
            x, constrained = x_z, constrained & np.array([False, False, True, False])[None, :]
            n_free = int(constrained.sum())
            needed = n_free + opts.n_significant * math.sqrt(2.0 * max(n_free, 1))
            gain = capped_gain(z_before, z_after, noise, cap)
            note = raised_floor_note(raised, robust_rms(z_after), x[:, 2], open_shift)
            common.update(notes=(*common["notes"], note), gain=gain, gain_needed=needed)
    # A height that drifts while the horizontal does not (a good horizontal estimate on a barometer that walks) is
    # none of the walls' business, and the walls' fit holds the height, so the floor's points lie off every plane it
    # fits: "too small to matter" to them (measured: 30 of 38 drifting flights re-posed on their true horizontal
    # position and heading were left as logged, Ve up to 8 % off, docs/design-notes.md). The pile seen at different
    # times does see it: the height, solved and significant on it (`vertical_from_crossings`), matters when it brings
    # the pile's sightings together (`crossings_brought_together`). Then the height alone is applied.
    crossed = None
    if raised is None and not mattered and z_info is not None and opts.vertical and opts.crossings:
        before, rows_noise = crossings_misfit_m(p0, b.t_s, knots, np.zeros(len(knots)), wall, storage, cell_m,
                                                opts.max_position_error_m, noise)
        after, _ = crossings_misfit_m(p0, b.t_s, knots, x[:, 2], wall, storage, cell_m, opts.max_position_error_m,
                                      noise)
        if crossings_brought_together(before, after, rows_noise):
            crossed = (before, after)
            x_z = np.zeros_like(x)
            x_z[:, 2] = x[:, 2]
            x, constrained = x_z, constrained & np.array([False, False, True, False])[None, :]
            common.update(notes=(*common["notes"], f"the height alone corrected (the floor and walls saw no drift "
                                                   f"that mattered): the pile seen at different times disagreed by "
                                                   f"{before * 100:.1f} cm, {after * 100:.1f} cm after"))
    if raised is None and crossed is None and not mattered:
        return not_applied("not applied: too small to matter (the floor and walls "
                           f"{common['rms_before_m'] * 100:.2f} cm off their planes before it, "
                           f"{common['rms_after_m'] * 100:.2f} cm after, against "
                           f"{noise * 100:.2f} cm of noise)", knots, **common)
    if crossed is None and not gain > needed:
        return not_applied("not applied: it does not bring the floor and walls closer to their planes by more than "
                           f"fitting {n_free} parameters to noise would (chi-square gain {gain:.0f}, needed "
                           f"{needed:.0f})", knots, **common)
    if raised is None and crossed is None:
        # A lever arm entered off moves every point by one vector fixed to the body, which flips in W with the legs'
        # direction: the drift's knots follow it leg by leg, and on slopes take it for height (measured: a lever arm's
        # y 0.2 m off read 68 % high once "corrected", 9.6 % as logged). When two numbers of the lever arm put the
        # floor and walls on their planes as well as the drift's knots do (no more than the noise further off, in
        # quadrature: the knots, many more, also fit a few systematic millimetres), the pose is not what drifted.
        axes = body_axes_w(samples[usable(samples)][::stride][both], frame)  # b's samples, b's order, on a plane
        dl, lever_rms = lever_shift(axes, n[jj], r_before, final)
        drift_rms = robust_rms(r_after)
        # Then the points are placed with that lever arm, exactly (`apply_pose_correction`), in place of the drift's
        # knots, which emulate it leg by leg and, through a turn or on a slope, get it wrong.
        if lever_rms <= math.hypot(drift_rms, noise) and robust_rms(r_before) ** 2 - lever_rms ** 2 > noise ** 2:
            note = (f"the floor and walls sit on their planes with the LiDAR's lever arm moved by "
                    f"{dl[0] * 100:+.1f} cm forward and {dl[1] * 100:+.1f} cm right ({lever_rms * 100:.1f} cm off "
                    f"them) as well as with a drifting pose ({drift_rms * 100:.1f} cm): a lever arm entered off, not a "
                    "drift")
            return PoseCorrection(knots, np.zeros_like(x), np.zeros_like(constrained), True, None,
                                  lever_change_m=(float(dl[0]), float(dl[1])),
                                  **{**common, "notes": (*common["notes"], note), "rms_after_m": lever_rms})
    # (a solve that failed numerically gives no term rather than a NaN interval)
    height_sigma = z_sigma[-1] if z_info is not None and z_sigma and math.isfinite(z_sigma[-1]) else None
    return PoseCorrection(knots, x, constrained, True, None, height_sigma_m=height_sigma,
                          level_sigma_m=(None if level_on_floor or opts.open_floor
                                         else level_sigma_m(opts.vertical_walk_m_per_sqrt_s, t1 - t0)),
                          open_floor_shift_m=(open_floor_shift if z_info is not None and open_floor_shift is not None
                                              and math.isfinite(open_floor_shift) else None),
                          height_unanchored_s=(unanchored_stretches(knots, tied)
                                               if z_info is not None and tied is not None else (0.0, 0.0, 0.0)),
                          untied_sigma_m=(untied_sigma_m(knots, tied, opts.vertical_walk_m_per_sqrt_s)
                                          if z_info is not None and tied is not None and not opts.open_floor
                                          else None), **common)


LEVER_ROUNDS = 10
"""Reweighting rounds of `lever_shift`'s robust fit (its weights settle in a few)."""
MAX_LEVER_CHANGE_M = 1.0
"""`lever_shift`'s prior: a lever arm is measured on a drone of tens of centimetres, so a metre off is a gross error."""


def lever_shift(axes_w: np.ndarray, normals: np.ndarray, r: np.ndarray, window_m: float | np.ndarray,
                prior_m: float | None = MAX_LEVER_CHANGE_M, n_axes: int = 2) -> tuple[np.ndarray, float]:
    """The lever arm's horizontal change (body forward, right; m) that best puts points back on their planes, and the
    robust RMS distance it leaves. axes_w: (N, 3, 3) each point's body axes in W (`body_axes_w`); normals: (N, 3) its
    plane's; r: (N,) its signed distance from it. A lever arm moved by dl moves every point of a sample by R_wb dl:
    one vector fixed to the body, which flips in W with the legs' direction, where a drift does not. A linear fit of two
    numbers, Cauchy-weighted at window_m (per point, or one for all), with a weak prior (prior_m, one point's weight at
    a window; None: none) that holds a component no plane sees at zero: legs flown along walls that are never seen
    ahead leave the forward one free. n_axes = 3 fits the down component too (`ground.self_calibration.
    lever_alternative`, beside a mount fit)."""
    a = np.einsum("nij,ni->nj", axes_w[:, :, :n_axes], normals)
    w = np.ones(len(r))
    dl = np.zeros(n_axes)
    if len(r) < n_axes + 1:
        return dl, robust_rms(r)
    ridge = np.zeros((0, n_axes)) if prior_m is None else np.eye(n_axes) * (float(np.median(window_m)) / prior_m)
    for _ in range(LEVER_ROUNDS):
        dl = np.linalg.lstsq(np.vstack([a * w[:, None], ridge]), np.r_[-r * w, np.zeros(len(ridge))], rcond=None)[0]
        u = (r + a @ dl) / window_m
        w = 1.0 / np.sqrt(1.0 + u * u)
    return dl, robust_rms(r + a @ dl)


def raised_floor_note(raised_m: float, left_m: float, z_m: np.ndarray, most_down_m: float = math.inf) -> str:
    """The pose line's note on a correction applied because it brought the floor onto z = 0 (`floor_brought_on`):
    by how much (raised_m, on the floor's points: up > 0, down < 0), how far off it they are left (left_m, robust
    RMS), and, when the height correction z_m (the knots') is about the same all flight (its spread under 1/MAX_MISFIT
    of its mean), the two errors that make a constant one. Down, within what (most_down_m): a floor above z = 0 may
    be material covering it, and is believed only within the logged reference's own error."""
    z = np.asarray(z_m, dtype=float)
    even = len(z) > 0 and float(np.std(z)) * MAX_MISFIT < abs(float(np.mean(z)))
    way = "down" if raised_m >= 0.0 else "up"
    cause = (f": a correction this even over the flight is what a lever arm's z entered too far {way}, or an "
             "altitude reference's offset, makes; check the lever arm against the drone") if even else ""
    if raised_m >= 0.0:
        return (f"the height corrected from the floor, which lay {raised_m:.2f} m below z = 0 where nothing but a "
                f"height error puts it (its points now {left_m * 100:.1f} cm off it){cause}")
    within = (f"within the {most_down_m:.2f} m the altitude reference may drift in the flight"
              if math.isfinite(most_down_m) else "the altitude from the downward rangefinder, which only a floor sets")
    return (f"the height corrected from the floor, which lay {-raised_m:.2f} m above z = 0, level and {within} (its "
            f"points now {left_m * 100:.1f} cm off it); were it material covering the floor, the volume would be low "
            f"by as much{cause}")


def level_sigma_m(walk_m_per_sqrt_s: float, duration_s: float) -> float:
    """The standard error of a drifting altitude reference's level over a flight of duration_s: the mean over the
    flight of a random walk (walk_m_per_sqrt_s) that starts at the log's start, whose variance is q^2 T / 3. What the
    height's level is off by when no floor the flight confirmed sets it (`PoseCorrection.level_sigma_m`)."""
    return walk_m_per_sqrt_s * math.sqrt(max(duration_s, 0.0) / 3.0)


def bend_sigmas(b: Beams, knots: np.ndarray, k: np.ndarray, opts: PoseCorrectionOptions) -> np.ndarray:
    """(K, 4) the drift's second difference at each knot, one sigma (inf: none; z: none, a rangefinder's
    height steps over a pile). A velocity error that changes slowly (`drift_correlation_s`) makes a smooth
    position error: between knots dt apart its second difference is dt x the velocity error's change, from
    the error's own change (drift_rel x speed x sqrt(2 dt / tau)) and from the turns (the error is a fraction
    of the velocity, so it turns with it: drift_rel x |the logged velocity's change|), plus the hover walk's
    sqrt(2 dt); the heading's is its walk's."""
    n_knots = len(knots)
    out = np.full((n_knots, 4), np.inf)
    if n_knots < 3:
        return out
    dt = np.diff(knots)
    vel = np.zeros((n_knots - 1, 2))
    for c in range(2):
        pos = np.bincount(k, weights=b.vehicle_w[:, c], minlength=n_knots - 1)
        cnt = np.bincount(k, minlength=n_knots - 1)
        mean_t = np.bincount(k, weights=b.t_s, minlength=n_knots - 1) / np.maximum(cnt, 1)
        mean_p = pos / np.maximum(cnt, 1)
        vel[:, c] = np.gradient(mean_p, mean_t) if (cnt > 0).all() else 0.0
    speed = np.linalg.norm(vel, axis=1)
    h = 0.5 * (dt[:-1] + dt[1:])
    dv = np.linalg.norm(np.diff(vel, axis=0), axis=1)
    v_mid = 0.5 * (speed[:-1] + speed[1:])
    sig = (h * opts.horizontal_drift_rel * (dv + v_mid * np.sqrt(2.0 * h / opts.drift_correlation_s))
           + opts.hover_walk_m_per_sqrt_s * np.sqrt(2.0 * h))
    out[1:-1, 0] = out[1:-1, 1] = sig
    out[1:-1, 3] = opts.heading_walk_rad_per_sqrt_s * np.sqrt(2.0 * h)
    return out


def _height_again(b: Beams, x: np.ndarray, k: np.ndarray, f: np.ndarray, knots: np.ndarray, wall: np.ndarray,
                  voted: np.ndarray, storage: Storage, cell_m: float, step_z_m: float, noise: float, sensor_m: float,
                  max_error_m: float, n_significant: float, max_vertical_error_m: float,
                  open_shift_m: float) -> tuple[np.ndarray, np.ndarray | None, str | None, float | None,
                                             np.ndarray | None, float | None]:
    """The height solved again once the registration has aligned the flight horizontally: the floor screen
    (`_screen`) and the height from the floor and the crossings (`vertical_from_crossings`), as the first
    time, from the logged reference, in the registered frame, with x, y and heading held at the registration's.

    Both were first done in the frame before the registration, which can misplace a stretch of the flight by a
    metre (measured: a `flow` flight over pile 2 whose level was set by 130 points on 0.86 m of pile). Nor is the
    registration's own height kept: it solves the height with the position, and on a pile with a flat top the
    two trade (measured: a `vio` flight over pile 2 at P_traj 5 %, a +0.26 m block of height over 97 s that
    the crossings' misfit prefers by 0.03 cm, 0.17 m RMS of height error; solved again 0.07 m). Returns the
    correction, the height's information, a note, the height's standard error (`height_rounds`; None when the solve
    gave none), the floor it was solved on and, when the walls' feet do not confirm that floor, what anchoring on it
    moved the height (`floor_unconfirmed_note`; None when confirmed); x as it was and None for the rest when the
    registration's height stands (no floor kept, nothing significant, or refused as the first height would be)."""
    x_h = x.copy()
    x_h[:, 2] = 0.0
    p, _ = corrected_points(b, x_h, k, f)
    kept, _, _, _, confirmed = _screen(p, b.t_s, knots, wall, voted, storage, cell_m, step_z_m, noise, sensor_m,
                                       max_error_m)
    if not kept.any():
        return x, None, None, None, None, None
    sigma: list[float] = []
    z, z_info = height_rounds(p, b.t_s, knots, wall, kept, storage, cell_m, step_z_m, noise, max_error_m,
                              n_significant, sigma)
    if (z is None or height_refused(z, knots, step_z_m, n_significant, max_vertical_error_m) is not None
            or floor_unconfirmed_note(z, confirmed, open_shift_m) is not None):
        return x, None, None, None, None, None
    change = rms(z - x[:, 2])
    x_h[:, 2] = z
    return x_h, z_info, (f"the height solved again on the floor once the pile seen at different times aligned the "
                         f"flight ({change:.2f} m RMS change)"), (sigma[-1] if sigma else None), kept, (
                             None if confirmed else float(np.mean(z)))


def height_rounds(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                  storage: Storage, cell_m: float, step_z_m: float, noise_m: float, max_error_m: float,
                  n_significant: float, sigma_out: list[float] | None = None) -> tuple[np.ndarray | None,
                                                                                     np.ndarray | None]:
    """`vertical_from_crossings` SLOPE_ROUNDS times, each with the cells' slopes from the heights corrected so
    far (module docstring); (None, None) when a round finds nothing significant. The last round appends its
    height's standard error to sigma_out (`vertical_from_crossings`). When a pile's toe shows among the floor
    candidates (`floor_from_below`), the level is then set where the floor's own candidates lie: the joint solve
    weighs the toe's cells as floor, and measured under Appendix A's noise put the vehicle 4-25 cm low."""
    z = z_info = None
    for i in range(SLOPE_ROUNDS):
        z, z_info = vertical_from_crossings(p, t, knots, wall, floor, storage, cell_m, step_z_m, noise_m,
                                            max_error_m, n_significant, z,
                                            sigma_out=sigma_out if i == SLOPE_ROUNDS - 1 else None)
        if z is None:
            return None, None
    kept = floor_from_below(p, t, knots, z, floor, n_significant)
    if kept is not floor:  # the toe showed: the level is the floor's own, read from the candidates kept
        idx = np.flatnonzero(kept)
        z = z - float(np.median(p[idx, 2] + np.interp(t[idx], knots, z)))
    return z, z_info


REVISIT_INTERVALS = 3
"""Knot intervals between two sightings of a cell for them to be two passes over it: a cell is what the vehicle flies
in a sweep period and a knot interval is two sweep periods, so one pass sees a cell within an interval and the
next; three apart, the vehicle has left and come back."""


def floor_anchored(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                   storage: Storage, cell_m: float, max_error_m: float = math.inf) -> np.ndarray:
    """(K - 1,) per knot interval, whether its height is tied to the floor: the floor seen in it, or a cell it saw
    seen again on another pass (`REVISIT_INTERVALS`) in an interval that is tied (and so on). Elsewhere the
    height rests on a chain, the pile seen from one interval to the next, whose links' errors add up: measured on
    the paper's pile 2 at P_traj 5 %, decimetres over 100 s even on the true horizontal pose (docs/design-notes.md).
    The cells, counts and points are `vertical_from_crossings`' (MIN_CELL_POINTS points in a cell and interval,
    `_in_building`)."""
    n_int = len(knots) - 1
    if n_int < 1:
        return np.zeros(0, dtype=bool)
    k, _ = knot_basis(t, knots)
    nx, ny, cid = _cells(p, storage, cell_m)
    n_cells = nx * ny
    inside = _in_building(p, wall, storage, max_error_m)
    key = k * n_cells + cid
    seen, count = np.unique(key[inside], return_counts=True)
    seen = seen[count >= MIN_CELL_POINTS]
    on_floor, floor_count = np.unique(key[inside & floor], return_counts=True)
    anchor = np.zeros(n_int, dtype=bool)
    anchor[on_floor[floor_count >= MIN_CELL_POINTS] // n_cells] = True
    cell, interval = seen % n_cells, seen // n_cells
    order = np.lexsort((interval, cell))  # by cell, then interval
    cell, interval = cell[order], interval[order]
    src, dst = [], []
    for d in range(1, len(cell)):
        same = cell[d:] == cell[:-d]
        if not same.any():
            break
        revisit = same & (interval[d:] - interval[:-d] >= REVISIT_INTERVALS)
        src.append(interval[:-d][revisit])
        dst.append(interval[d:][revisit])
    i = np.concatenate(src) if src else np.zeros(0, dtype=np.int64)
    j = np.concatenate(dst) if dst else np.zeros(0, dtype=np.int64)
    graph = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(n_int, n_int))
    _, label = connected_components(graph, directed=False)
    tied = np.zeros(label.max() + 1, dtype=bool)
    tied[label[anchor]] = True
    return tied[label]


def _untied_runs(tied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stretches of REVISIT_INTERVALS knot intervals or more not tied to the floor, as interval ranges [start,
    end): a shorter one lies within a pass's reach of tied intervals on both sides (one interval alone has both its
    knots tied by its neighbours)."""
    free = np.concatenate([[0], (~np.asarray(tied, dtype=bool)).astype(np.int8), [0]])
    edges = np.diff(free)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    long_enough = ends - starts >= REVISIT_INTERVALS
    return starts[long_enough], ends[long_enough]


def unanchored_stretches(knots: np.ndarray, tied: np.ndarray) -> tuple[float, float, float]:
    """(total s not tied to the floor, the longest such stretch's start and end s) from `floor_anchored`'s
    intervals, counting the stretches `_untied_runs` counts."""
    starts, ends = _untied_runs(tied)
    if len(starts) == 0:
        return 0.0, 0.0, 0.0
    lengths = knots[ends] - knots[starts]
    best = int(np.argmax(lengths))
    return float(lengths.sum()), float(knots[starts[best]]), float(knots[ends[best]])


def untied_sigma_m(knots: np.ndarray, tied: np.ndarray, walk_m_per_sqrt_s: float) -> float:
    """The standard error of the height's mean over the flight from its stretches no floor tied (`_untied_runs` of
    `floor_anchored`'s intervals): there the height rests on the pile seen from one moment to the next, whose links'
    errors add up (decimetres over 100 s, measured), so the data do not check the altitude reference's own drift. A
    stretch of T s between two tied moments is the walk pinned at both ends, a Brownian bridge, whose mean over the
    stretch has variance q^2 T / 12; one open at the flight's start or end is a walk from its tied end, q^2 T / 3 (as
    `level_sigma_m`). Each is weighted by its share of the flight (the legs sweep the floor at a steady rate, so the
    share of the surfaced area whose heights it set), and the stretches, apart in time, add in quadrature. 0 when
    tied throughout."""
    starts, ends = _untied_runs(tied)
    knots = np.asarray(knots, dtype=float)
    flown = float(knots[-1] - knots[0]) if len(knots) >= 2 else 0.0
    if len(starts) == 0 or not flown > 0:
        return 0.0
    n_int = len(knots) - 1
    total = 0.0
    for a, e in zip(starts, ends, strict=True):
        length = float(knots[e] - knots[a])
        pinned_both = a > 0 and e < n_int
        variance = walk_m_per_sqrt_s ** 2 * length / (12.0 if pinned_both else 3.0)
        total += variance * (length / flown) ** 2
    return math.sqrt(total)


def half_sample_mode(x: np.ndarray) -> float:
    """The half-sample mode (Bickel and Fruehwirth, 2006): the shortest half of the values, then the shortest half
    of that, down to two or three. Robust to a one-sided tail, where the median is not."""
    x = np.sort(np.asarray(x, dtype=float))
    if len(x) == 0:
        raise ValueError("the half-sample mode of no values")
    while len(x) > 3:
        h = (len(x) + 1) // 2
        i = int(np.argmin(x[h - 1:] - x[:len(x) - h + 1]))
        x = x[i:i + h]
    if len(x) == 3:
        gap_lo, gap_hi = x[1] - x[0], x[2] - x[1]
        return float(x[1] if gap_lo == gap_hi else np.mean(x[:2]) if gap_lo < gap_hi else np.mean(x[1:]))
    return float(np.mean(x))


def floor_from_below(p: np.ndarray, t: np.ndarray, knots: np.ndarray, z: np.ndarray, floor: np.ndarray,
                     n_significant: float) -> np.ndarray:
    """The floor candidates, with the pile's toe among them dropped when it shows: their heights under the height
    correction z, read from below.

    Nothing lies under the floor but noise, so the candidates below their level show the floor's own scatter; the
    level is their half-sample mode (the floor's peak, not lifted by a toe as a median is). When significantly
    more candidates lie beyond BAND of those sigmas above the level than below it, the excess is a pile's toe
    (under a degree of pointing noise the candidates' band is decimetres tall: measured, 255 of 858 candidates on
    pile 1's toe, 0.24 m up, and every corrected height 4-25 cm low) and only the candidates within BAND sigmas of
    the level are kept. Symmetric tails are left alone: without pointing noise the floor's spread about a solved
    height is the drift model's misfit, and dropping it lost anchors (docs/design-notes.md)."""
    idx = np.flatnonzero(floor)
    if len(idx) < MIN_VOTES:
        return floor
    u = p[idx, 2] + np.interp(t[idx], knots, z)
    level = half_sample_mode(u)
    below = level - u[u < level]
    if len(below) < MIN_CELL_POINTS:
        return floor
    half = BAND * float(np.median(below)) / 0.6745  # the median of a half-normal is 0.6745 sigma
    n_hi, n_lo = int(np.count_nonzero(u > level + half)), int(np.count_nonzero(u < level - half))
    if not n_hi - n_lo > n_significant * math.sqrt(max(n_hi + n_lo, 1)):
        return floor
    keep = np.abs(u - level) <= half
    if not keep.any():
        return floor
    out = floor.copy()
    out[idx[~keep]] = False
    return out


def height_refused(z: np.ndarray, knots: np.ndarray, step_z_m: float, n_significant: float,
                   max_vertical_error_m: float) -> str | None:
    """Why a height correction is not believed (None: it is): it moves the altitude reference further than
    an indoor estimator's is off, or jumps between two knots more than any indoor estimator's does (a flat
    pile top taken for the floor somewhere: the paper's pile 2 hides the floor almost everywhere)."""
    if np.abs(z).max() > max_vertical_error_m:
        return (f"the height was not corrected: the floor seen would put the altitude reference "
                f"{np.abs(z).max():.2f} m off, more than the {max_vertical_error_m:g} m an "
                "indoor estimator's is (a flat pile top taken for the floor?)")
    if len(z) > 1 and np.abs(np.diff(z)).max() > n_significant * step_z_m:
        return (f"the height was not corrected: the floor seen is not consistent (the correction "
                f"would jump {np.abs(np.diff(z)).max():.2f} m between knots {_spacing(knots):.1f} s apart; "
                "a flat pile top taken for the floor?)")
    return None


def _registered(b: Beams, x: np.ndarray, knots: np.ndarray, k: np.ndarray, f: np.ndarray, wall: np.ndarray,
                floor: np.ndarray, storage: Storage, cell_m: float, step: np.ndarray, noise: float, sensor_m: float,
                wall_info_total: np.ndarray, on: np.ndarray, z_free: bool, heading_held: bool,
                opts: PoseCorrectionOptions) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """The position (and, with `opts.crossings_heading`, the heading) registered on the pile seen at different
    times (`register_from_crossings`), each kept only when its gain beats fitting its knots to noise.

    The walls' fit anchors each knot where they see it, with one point's information per knot (the walls'
    points within a knot interval share its systematic part: millimetres on the walls bought degrees of
    heading when each point counted, docs/pose_error.md): their information (wall_info_total, from the
    points `on`) divided by the points' weight on the knot."""
    n_knots = len(knots)
    kk, ff = k[on], f[on]
    weight = (np.bincount(kk, weights=(1 - ff) ** 2, minlength=n_knots)
              + np.bincount(kk + 1, weights=ff ** 2, minlength=n_knots))
    wall_info = wall_info_total / np.maximum(weight, 1.0)[:, None]
    elapsed = knots - knots[0]
    abs_sigma = np.tile([opts.max_position_error_m] * 3 + [opts.max_heading_error_rad], (n_knots, 1))
    abs_sigma[:, 3] = np.minimum(abs_sigma[:, 3], step[3] + opts.heading_bias_rad_s * elapsed
                                 + opts.heading_walk_rad_per_sqrt_s * np.sqrt(elapsed))
    bend = bend_sigmas(b, knots, k, opts)
    z_c = (Component.Z.value,) if z_free else ()
    xy = (Component.X.value, Component.Y.value)
    notes: list[str] = []

    def needed(n_extra: int) -> float:
        return n_extra + opts.n_significant * math.sqrt(2.0 * max(n_extra, 1))

    def register(start: np.ndarray, comps: tuple[int, ...], fixed: tuple[int, ...],
                 what: str) -> tuple[np.ndarray, np.ndarray, float, int] | None:
        """register_from_crossings; None (with a note) when what it gives is no drift (`is_drift`)."""
        out = register_from_crossings(b, start, x, knots, k, f, wall, floor, storage, cell_m, step, noise,
                                      sensor_m, wall_info, abs_sigma, comps, fixed, opts.max_position_error_m, bend)
        free = tuple(c for c in comps if c != Component.Z.value)  # a stage re-solves its fixed ones too
        if is_drift(out[0], start, step, free):
            return out
        notes.append(f"the {what} from the pile seen at different times was not used: the trajectory it gave "
                     "jumps more than the drift model allows")
        return None
    reg = register(x, z_c + xy, z_c, "position")
    if reg is None:
        return x, None, notes
    x_xy, info, gain, n_extra = reg
    if not (n_extra > 0 and gain > needed(n_extra)):
        return x, None, notes
    x_out, info_out = x_xy, info
    if opts.crossings_heading and heading_held:
        reg_h = register(x_xy, z_c + xy + (Component.HEADING.value,), z_c + xy, "heading")
        x_h, info_h, gain_h, n_h = reg_h if reg_h is not None else (x_xy, info, 0.0, 0)
        if n_h > 0 and gain_h > needed(n_h):
            x_out, info_out = x_h, info_h
            notes.append(f"the heading from the pile seen at different times ({math.degrees(rms(x_h[:, 3])):.2f} deg "
                         "RMS)")
        elif reg_h is not None:  # said, so a surveyor knows an indoor heading's drift is still in the volume
            why = (f"does not show it off: fitting it gains {gain_h:.0f}, where fitting {n_h} knots to noise would "
                   f"gain up to {needed(n_h):.0f}" if n_h > 0 else "constrains no knot of it")
            notes.append(f"the heading was left as logged: the pile seen at different times {why}")
    return x_out, info_out, notes


MIN_PILE_SLOPE = 0.05
"""The gentlest surface slope a shift is registered on (3 deg): steeper than a floor's fall (drainage: up to 2 %) with
margin; below it a centimetre of height error (a drifting height within a pass, a range quantum) is a metre of shift."""
MAX_PILE_SLOPE = 1.0
"""The steepest surface slope registered on (tan 45 deg: above any granular material's angle of repose, ~30-40 deg)."""
SLOPE_ROUNDS = 3
"""Rounds of the height solution, each with the cells' slopes from the previous one's corrected heights (a
slope fitted to uncorrected heights takes up the difference between two passes over a cell)."""


def _flattened(p: np.ndarray, wall: np.ndarray, storage: Storage, cell_m: float, max_error_m: float,
               slope_z: np.ndarray | None = None) -> tuple[np.ndarray, int, int, np.ndarray, np.ndarray]:
    """What the crossings compare: the points they use (`_in_building`), the cells (nx, ny, each point's) and each
    point's height with its cell's slope taken out. The slope is fitted from all the cell's points, every time
    together (with heights slope_z, default p's own): the height a knot interval gives is then at the cell's
    centre, so two passes that hit a sloped cell in different places still agree. Returns (inside, nx, ny, cid,
    z_flat)."""
    inside = _in_building(p, wall, storage, max_error_m)
    nx, ny, cid = _cells(p, storage, cell_m)
    seen = p if slope_z is None else np.column_stack([p[:, :2], slope_z])
    return inside, nx, ny, cid, p[:, 2] - _cell_slopes(seen, cid, nx * ny, cell_m, ny, inside)


def vertical_from_crossings(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                            storage: Storage, cell_m: float, step_z_m: float, noise_m: float, max_error_m: float,
                            n_significant: float = 3.0, start: np.ndarray | None = None,
                            significant_only: bool = True,
                            sigma_out: list[float] | None = None,
                            cov_out: list[np.ndarray] | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The height correction at the knots (K,) from the floor and from the pile seen at different times.

    Each knot interval's points in a cell (cell_m: what the vehicle flies in a sweep period, so a cell holds
    both sweep directions' points) give one height, z + c(t); the surface's height there, m, is one unknown
    per cell, the same whenever it is seen; a cell whose points the vote took for the floor (`floor`) has
    m = 0. Solved with the knots' random-walk prior, robustly (Huber: a cell on a slope, whose height
    depends on where in it the points fell, scatters and counts little; a flat part of the pile the vote
    took for the floor is outvoted by the other times that saw it). Returns (None, None) when there is
    nothing to solve or the result is not significant; else the correction and the data's information on
    each knot (1 / m^2). Without floor cells the solution is relative (its level: the prior's zero);
    `significant_only=False` returns it whatever its gain (`screen_floor` needs it). With sigma_out (a list), the
    standard error of the correction's mean over the samples is appended to it when floor cells set the level
    (`mean_sigma_m`)."""
    n_knots = len(knots)
    k, f_t = knot_basis(t, knots)
    seen_z = None if start is None else p[:, 2] + np.interp(t, knots, start)  # slopes from the corrected
    inside, nx, ny, cid, z_flat = _flattened(p, wall, storage, cell_m, max_error_m, seen_z)
    key, med, mad, tm, cnt = group_median((k * (nx * ny) + cid)[inside], z_flat[inside], t[inside])
    fkey, _, _, _, fcnt = group_median((k * (nx * ny) + cid)[inside & floor], z_flat[inside & floor],
                                        t[inside & floor])
    is_floor = np.zeros(len(key), dtype=bool)
    pos = np.searchsorted(key, fkey)
    is_floor[pos[fcnt * 2 >= cnt[pos]]] = True  # most of the interval's points in the cell are floor
    keep = cnt >= MIN_CELL_POINTS
    key, med, mad, tm, cnt, is_floor = key[keep], med[keep], mad[keep], tm[keep], cnt[keep], is_floor[keep]
    cell = key % (nx * ny)
    _, inv, times_seen = np.unique(cell, return_inverse=True, return_counts=True)
    floor_cells = np.zeros(times_seen.shape, dtype=bool)
    floor_cells[inv[is_floor]] = True
    use = (times_seen[inv] >= 2) | floor_cells[inv]  # seen once and not floor: says nothing about c
    key, med, mad, tm, cnt, inv = key[use], med[use], mad[use], tm[use], cnt[use], inv[use]
    if len(key) == 0:
        return None, None
    uniq_cells, cell_idx = np.unique(inv, return_inverse=True)
    n_cells = len(uniq_cells)
    fc = np.flatnonzero(floor_cells[uniq_cells])
    rows_s = median_sd_m(mad, cnt, noise_m)
    n_par = n_knots + n_cells
    kk, ff = knot_basis(tm, knots)
    m_obs, m_floor = len(med), len(fc)
    rows = np.concatenate([np.repeat(np.arange(m_obs), 3), m_obs + np.arange(m_floor)])
    cols = np.concatenate([np.column_stack([kk, kk + 1, n_knots + cell_idx]).ravel(), n_knots + fc])
    data = np.concatenate([np.column_stack([(1 - ff) / rows_s, ff / rows_s, -1.0 / rows_s]).ravel(),
                           np.full(m_floor, 1.0 / noise_m)])
    a_obs = sparse.csr_matrix((data, (rows, cols)), shape=(m_obs + m_floor, n_par))
    b_obs = np.concatenate([-med / rows_s, np.zeros(m_floor)])
    # the prior: knot-to-knot steps, a weak pull to zero (the knots) and to the floor (the cells)
    r = n_knots - 1
    steps = np.arange(r)
    pr = np.concatenate([np.repeat(steps, 2), r + np.arange(n_par)])
    pc_ = np.concatenate([np.column_stack([steps, steps + 1]).ravel(), np.arange(n_par)])
    pd = np.concatenate([np.tile([-1.0 / step_z_m, 1.0 / step_z_m], r),
                         np.where(np.arange(n_par) < n_knots, 1.0 / max_error_m, 1.0 / storage.height_m)])
    a_pr = sparse.csr_matrix((pd, (pr, pc_)), shape=(r + n_par, n_par))
    a = sparse.vstack([a_obs, a_pr], format="csr")
    rhs = np.concatenate([b_obs, np.zeros(r + n_par)])
    x = irls_huber(a, rhs)
    info = np.asarray(a_obs[:, :n_knots].multiply(a_obs[:, :n_knots]).sum(axis=0)).ravel()
    # Significance: the heights' misfit with the correction and without it (the cells' heights fitted
    # alone), in the residuals' own spread (a cell on a slope scatters more than its points say), against
    # what fitting the knots to noise would explain.
    r_full = a_obs @ x - b_obs
    a_cells = sparse.vstack([a_obs[:, n_knots:], a_pr[r + n_knots:, n_knots:]], format="csr")
    x_cells = irls_huber(a_cells, np.concatenate([b_obs, np.zeros(n_cells)]))
    r_none = a_obs[:, n_knots:] @ x_cells - b_obs
    spread = max(1.0, robust_rms(r_full))
    gain = 2.0 * float(np.sum(huber_loss(r_none / spread)) - np.sum(huber_loss(r_full / spread)))
    if significant_only and not gain > n_knots + n_significant * math.sqrt(2.0 * n_knots):
        return None, None
    if cov_out is not None:
        cov = knot_covariance(a, x, rhs, n_knots)
        if cov is not None:
            cov_out.append(cov * spread ** 2)
    if sigma_out is not None and m_floor > 0:
        sigma_out.append(mean_sigma_m(a, x, rhs, (k, f_t), n_knots) * spread)
    z = x[:n_knots]
    if m_floor == 0:  # no floor: the level is not observed (the cells' weak pull to 0 would set it): keep the
        z = z - np.mean(z)  # logged reference's on average
    return z, info / spread ** 2


def crossings_misfit_m(p: np.ndarray, t: np.ndarray, knots: np.ndarray, z: np.ndarray, wall: np.ndarray,
                       storage: Storage, cell_m: float, max_error_m: float, noise_m: float) -> tuple[float, float]:
    """How far the pile seen at different times disagrees with itself with the height correction z (K,) at the
    knots: each knot interval's median height in a cell (its slope taken out, as `vertical_from_crossings` does)
    against the cell's median over the intervals that saw it, robust RMS over the cells seen at least twice, m; and
    the noise of those medians (a median's sd, 1.25 of its points' spread, at least noise_m, over the root of their
    count, as `vertical_from_crossings` weighs them): (misfit, noise), (0, 0) when no cell is seen twice."""
    k, _ = knot_basis(t, knots)
    q = np.column_stack([p[:, :2], p[:, 2] + np.interp(t, knots, z)])
    inside, nx, ny, cid, z_flat = _flattened(q, wall, storage, cell_m, max_error_m)
    key, med, mad, _, cnt = group_median((k * (nx * ny) + cid)[inside], z_flat[inside], t[inside])
    keep = cnt >= MIN_CELL_POINTS
    cell, med, sd = key[keep] % (nx * ny), med[keep], median_sd_m(mad[keep], cnt[keep], noise_m)
    _, inv, seen = np.unique(cell, return_inverse=True, return_counts=True)
    again = seen[inv] >= 2
    if not again.any():
        return 0.0, 0.0
    _, cmed, _, _, _ = group_median(inv[again], med[again], med[again])
    _, back = np.unique(inv[again], return_inverse=True)
    return robust_rms(med[again] - cmed[back]), float(np.median(sd[again]))


def screen_floor(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                 storage: Storage, cell_m: float, step_z_m: float, noise_m: float, sensor_m: float,
                 max_error_m: float) -> tuple[np.ndarray, np.ndarray | None, str | None, bool]:
    """The floor candidates that are the floor: (the mask kept, the height from the crossings at the floor's
    level when most were dropped, a note when some were, whether the walls' feet confirm it); `_screen` without
    its tolerance."""
    kept, shift, note, _, confirmed = _screen(p, t, knots, wall, floor, storage, cell_m, step_z_m, noise_m, sensor_m,
                                              max_error_m)
    return kept, shift, note, confirmed


def _screen(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
            storage: Storage, cell_m: float, step_z_m: float, noise_m: float, sensor_m: float,
            max_error_m: float) -> tuple[np.ndarray, np.ndarray | None, str | None, float, bool]:
    """The floor candidates that are the floor: (the mask kept, ..., a note when some were dropped, the
    tolerance: how far from the floor's level a candidate is still floor, inf where no level was found; whether
    what is seen at the walls comes down to the level, `floor_unconfirmed_note`).

    A flat pile top can pass the per-interval vote (nothing below it in that interval) and then anchors the
    height on itself. Across the flight it cannot hide: the crossings alone (no floor) put every time's
    points in one frame up to a constant, and in that frame the floor is one level, the lowest flat one,
    and no wall is seen below it (walls stand on the floor). So, in that frame: the candidates' heights per
    knot interval and cell; the floor's level is their lowest peak (as the vote's outermost peak), read in a
    window as tall as a flat floor's heights scatter (`level_window`), not the frame's spread on slopes; it must
    not lie above the walls' lowest points (beyond stray returns); the
    candidates within BAND noise levels of it are kept, the rest dropped, each judged within the frame's own
    uncertainty between its time and the level's (`knot_covariance`: where the crossings tie two stretches of the
    flight only loosely, the frame's stretches float apart). None kept: the height comes from the crossings alone.

    A floor meets the walls it runs to, so where the level is the floor, what is seen at a wall comes down to it
    unless the pile covers every wall's foot. There the level may still be the floor, seen in a gap between heaps
    (the paper's pile 2), or the bottom of a hollow in a pile that hides the floor wall to wall: the same shape,
    one flat at the floor and one curving at 0.7 m, and nothing else in the data tells them apart: the caller
    decides (`floor_unconfirmed_note`)."""
    if not floor.any():
        return floor, None, None, math.inf, False
    cov: list[np.ndarray] = []
    z_rel, _ = vertical_from_crossings(p, t, knots, wall, np.zeros_like(floor), storage, cell_m, step_z_m, noise_m,
                                       max_error_m, significant_only=False, cov_out=cov)
    if z_rel is None:
        return floor, None, None, math.inf, False
    zc = p[:, 2] + np.interp(t, knots, z_rel)
    k, _ = knot_basis(t, knots)
    nx, ny, cid = _cells(p, storage, cell_m)
    key = k * (nx * ny) + cid
    # the frame's noise: how far one interval's height of a cell is from the cell's height at other times
    inside = ~wall & (p[:, 2] < storage.height_m)
    gk, gmed, _, _, gcnt = group_median(key[inside], zc[inside], t[inside])
    many = gcnt >= MIN_CELL_POINTS
    gcell, gmed = gk[many] % (nx * ny), gmed[many]
    spread = between_times_scatter_m(gcell, gmed)
    tol = BAND * max(spread, sensor_m, noise_m)
    # the same with each cell's slope taken out (two passes that hit a sloped cell in different places): the
    # frame's own misalignment between times, which a flat floor's heights carry too
    zs = zc - _cell_slopes(np.column_stack([p[:, :2], zc]), cid, nx * ny, cell_m, ny, inside)
    _, smed, _, _, _ = group_median(key[inside], zs[inside], t[inside])
    frame_m = between_times_scatter_m(gcell, smed[many])
    fk, fmed, _, _, fcnt = group_median(key[floor], zc[floor], t[floor])
    # the lowest level that holds more than stray points (nothing but noise is below the floor); not the
    # highest peak: a broad flat top can out-number the floor seen (measured: 350 against 100 points)
    order = np.argsort(fmed)
    fmed, fcnt, fk = fmed[order], fcnt[order], fk[order]
    stray_f = max(MIN_VOTES, STRAY_FRACTION * float(np.sum(fcnt)))
    if lowest_window(fmed, fcnt, tol, stray_f) is None:
        return np.zeros_like(floor), None, ("no floor seen: too few floor points agree on one level once the "
                                            "crossings align the flight; the height is corrected from the crossings "
                                            "alone"), math.inf, False
    # The level within the floor's own scatter, not the frame's: under a degree of pointing noise the frame's
    # spread (on slopes) reached 0.7 m, and a window that wide over a pile that hides most of the floor took in
    # the toe's ramp above the few floor cells seen (its median 0.6-0.9 m up the toe: Appendix A, pile 2).
    width = level_window(fk % (nx * ny), fmed, fcnt, noise_m, frame_m, tol)
    i0, i1 = lowest_window(fmed, fcnt, width, stray_f) or lowest_window(fmed, fcnt, tol, stray_f)
    level = float(np.median(fmed[i0:i1]))
    # everything seen at a wall (its face or the floor or pile against it), the horizontal correction applied:
    # nothing there is below the floor
    band = BAND * max(sensor_m, noise_m)
    at_wall = ((p[:, 0] < band) | (p[:, 0] > storage.length_m - band) | (p[:, 1] < band)
               | (p[:, 1] > storage.width_m - band))
    walls_z = np.sort(zc[at_wall])
    stray = int(max(MIN_VOTES, STRAY_FRACTION * len(walls_z)))
    wall_low = float(walls_z[stray]) if len(walls_z) > stray else math.inf
    if level > wall_low + tol:
        return np.zeros_like(floor), None, (f"no floor seen: what the vote took for it lies {level - wall_low:.2f} m "
                                            "above the walls' lowest points once the crossings align the flight (a "
                                            "flat pile top); the height is corrected from the crossings alone"), \
            tol, False
    confirmed = int(np.count_nonzero(np.abs(walls_z - level) <= tol)) >= MIN_VOTES
    # A candidate is judged against the level within the frame's own uncertainty between its time and the level's:
    # where the crossings tie two stretches of the flight loosely (a loop whose long legs see the pile's flanks once),
    # the frame's halves float apart, and a floor seen in one lies above the other's level (measured: 0.10 m on a
    # flight's true pose, 0.33 m with a barometer's walk; the far end's floor dropped as a flat pile top).
    reach = np.full(len(fk), tol)
    if cov:
        c = cov[0]
        lk = fk[i0:i1] // (nx * ny)
        var = np.diag(c) + float(np.mean(c[np.ix_(lk, lk)])) - 2.0 * np.mean(c[:, lk], axis=1)
        reach = np.hypot(tol, BAND * np.sqrt(np.maximum(var, 0.0)))[np.minimum(fk // (nx * ny), len(knots) - 1)]
    good_keys = fk[np.abs(fmed - level) <= reach]
    kept = floor & np.isin(key, good_keys)
    dropped = int(np.count_nonzero(floor & ~kept))
    if not 2 * dropped > np.count_nonzero(floor):
        # Most of it is one level: the vote's floor stands as it is. Dropping the few off it cost more than it
        # gave (measured on pile 1, which has no flat top: the crossings' frame misaligns some true floor by
        # a few decimetres on a `flow` flight; Ve 0.16 % -> 2.0 %); the joint solve's Huber loss outvotes them.
        return floor, None, None, tol, confirmed
    # The floor kept is the level's own cluster: a floor is flat, so its heights scatter by their own noise, not by
    # the crossings' spread on slopes, which under a degree of pointing noise reached 0.7 m and kept a pile's toe
    # as floor (the joint solve on it then put the level 0.6 m off: Appendix A, `vio`, pile 2)
    half = floor_half_width(fmed[i0:i1], level, tol, noise_m, fcnt)
    kept = floor & np.isin(key, fk[np.abs(fmed - level) <= half])
    note = (f"{dropped} of {int(np.count_nonzero(floor))} floor points dropped: more than {tol:.2f} m above the "
            "floor's level once the crossings align the flight (a flat pile top)")
    # Most of what the vote called floor was a flat top: the remaining floor is too sparse to anchor each
    # interval (measured: the joint solve over it kept a 0.19 m bias on a pile-2 flight); the crossings'
    # own solution, put at the floor's level, is used instead.
    return kept, z_rel - level, note, tol, confirmed


def floor_unconfirmed_note(z: np.ndarray, confirmed: bool, open_shift_m: float) -> str | None:
    """Why a height anchored on a floor the walls' feet do not confirm (`_screen`) is not kept (None: it is): it moves
    the height (z, the knots', against the crossings alone, whose mean is the logged reference's) by more than
    open_shift_m on average, the most the logged height is believed to be off. Within it, were the floor a hollow,
    it could do no more harm than the logged height's own error."""
    shift = abs(float(np.mean(z)))
    if confirmed or shift <= open_shift_m:
        return None
    return (f"no floor confirmed: what the vote took for it was seen only away from the walls (the pile covers their "
            f"feet), so it may be a hollow in the pile, and it would move the height by {shift:.2f} m, more than the "
            f"barometer is believed to drift in the flight ({open_shift_m:.2f} m); the height is corrected from the "
            "crossings alone, at the logged height's level")


def open_floor_note(how: str, shift_m: float) -> str:
    """The pose line's note on a height anchored (how: "anchored", "solved again") on a floor the walls' feet do not
    confirm, which moved it shift_m on average."""
    return (f"the floor the height was {how} on was seen only away from the walls (the pile covers their feet): were "
            f"it a hollow in the pile, the height would be off by up to {abs(shift_m):.2f} m, what anchoring on it "
            "moved it")


def lowest_window(med_m: np.ndarray, counts: np.ndarray, width_m: float, stray: float) -> tuple[int, int] | None:
    """The lowest window width_m tall of the sorted heights med_m (counts points each) that holds more than stray
    points, as the index range [i, j) of its heights (None: none does). Nothing but noise is below the floor."""
    cum = np.concatenate([[0], np.cumsum(counts)])
    upto = np.searchsorted(med_m, med_m + width_m, side="right")
    dense = np.flatnonzero(cum[upto] - cum[:-1] > stray)
    return (int(dense[0]), int(upto[dense[0]])) if len(dense) else None


def level_window(cell: np.ndarray, med_m: np.ndarray, counts: np.ndarray, noise_m: float, frame_m: float,
                 tol_m: float) -> float:
    """How tall a window of floor heights (one knot interval's median in a cell each) the floor's level is read in:
    BAND times the larger of the candidates' own scatter (in the cells seen at more than one time, about each
    cell's median), a typical height median's noise, and the crossings frame's misalignment between times
    (frame_m: measured with the cells' slopes taken out); never over tol (the frame's spread over the whole
    surface, slopes and all: under a degree of pointing error a point on a slope moves up or down by the slope
    times 0.2 m, which a flat floor's heights do not)."""
    typical = noise_m / math.sqrt(max(float(np.median(counts)), 1.0)) if len(counts) else noise_m
    return min(tol_m, BAND * max(between_times_scatter_m(cell, med_m), typical, frame_m))


def between_times_scatter_m(cell: np.ndarray, med_m: np.ndarray) -> float:
    """How far one knot interval's height of a cell (med_m, the cells' ids in cell) is from the cell's median
    height over the times it was seen: the robust RMS over the cells seen more than once (0: none was)."""
    _, inv, seen = np.unique(cell, return_inverse=True, return_counts=True)
    again = seen[inv] >= 2
    if not again.any():
        return 0.0
    _, cell_med, _, _, _ = group_median(inv, med_m, med_m)  # per cell (inv: 0 .. cells - 1)
    return robust_rms((med_m - cell_med[inv])[again])


def floor_half_width(lowest_m: np.ndarray, level_m: float, tol_m: float, noise_m: float, counts: np.ndarray) -> float:
    """How far from the floor's level a floor height (one knot interval's median in a cell) is still floor, once
    most of the vote's floor was a flat top: BAND times the scatter of the lowest window's heights about the level
    (a floor is flat, so that is their own noise), never under BAND sd's of a typical height's median, never over
    tol (the crossings' spread, which on a pile's slopes under pointing noise reaches its toe)."""
    typical = noise_m / math.sqrt(max(float(np.median(counts)), 1.0)) if len(counts) else noise_m
    scatter = robust_rms(np.asarray(lowest_m) - level_m) if len(lowest_m) else 0.0
    return min(tol_m, BAND * max(scatter, typical))


def _in_building(p: np.ndarray, wall: np.ndarray, storage: Storage, max_error_m: float) -> np.ndarray:
    """The points the crossings use: inside the building's walls and under its roof, not a wall's, and no deeper
    below the floor than the largest position error looked for (max_error_m)."""
    return (~wall & (p[:, 0] > 0) & (p[:, 0] < storage.length_m) & (p[:, 1] > 0) & (p[:, 1] < storage.width_m)
            & (p[:, 2] > -max_error_m) & (p[:, 2] < storage.height_m))


def _cells(p: np.ndarray, storage: Storage, cell_m: float) -> tuple[int, int, np.ndarray]:
    nx = max(1, math.ceil(storage.length_m / cell_m))
    ny = max(1, math.ceil(storage.width_m / cell_m))
    cid = (np.clip((p[:, 0] / cell_m).astype(np.int64), 0, nx - 1) * ny
           + np.clip((p[:, 1] / cell_m).astype(np.int64), 0, ny - 1))
    return nx, ny, cid


def register_from_crossings(b: Beams, x: np.ndarray, x_wall: np.ndarray, knots: np.ndarray, k: np.ndarray,
                            f: np.ndarray, wall: np.ndarray, floor: np.ndarray, storage: Storage, cell_m: float,
                            step: np.ndarray, noise_m: float, sensor_m: float, wall_info: np.ndarray,
                            abs_sigma: np.ndarray,
                            comps: tuple[int, ...], fixed: tuple[int, ...], max_error_m: float,
                            bend: np.ndarray | None = None, n_sigma: float = 3.0,
                            rounds: int = 3) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The pile seen at different times registered in position (and heading) too, not only in height.

    Each knot interval's points in a cell give one height at the cell's centre (`vertical_from_crossings`);
    on a slope a horizontal shift s of that interval's points changes it by g . s (g: the cell's gradient,
    fitted from all its points), and a heading change dpsi by g . J v dpsi (v: the interval's mean beam vector
    there, horizontal; J: a quarter turn): a heading error turns the sweep about the vehicle, moving a point
    at lateral distance D by D dpsi along the track, which the walls beside the track do not see and the
    pile's slope along the track does. So the along-track position between turns, which the walls leave to
    interpolation, is observed wherever a cell on a slope is seen twice. Linearised about x (K, 4), solved
    for the components `comps` (Component values) with the cells' heights, robustly (Huber, IRLS), with the
    knots' random-walk prior (step (4,)), the walls' information on each knot (wall_info (K, 4): the wall fit
    x_wall is kept where the walls see it) and an absolute prior (abs_sigma (K, 4)); `rounds` re-fits of the
    cells' gradients with the correction so far.

    Returns the correction (K, 4), the crossings' information on each knot (K, 4; 1/m^2, 1/rad^2), the
    Huber gain of the components `comps` not in `fixed` over holding them at x's values (in the residuals'
    own spread: a chi-square-like gain) and the number of knot values the crossings constrain among them."""
    n_knots = len(knots)
    comps = tuple(comps)
    nc = len(comps)
    x = x.copy()
    x_start = x.copy()
    info = np.zeros((n_knots, 4))
    gain, n_extra = 0.0, 0
    for rnd in range(rounds):
        p, vr = corrected_points(b, x, k, f)
        inside = _in_building(p, wall, storage, max_error_m)
        nx, ny, cid = _cells(p, storage, cell_m)
        flat, gx, gy = _significant_gradients(p, cid, nx * ny, cell_m, ny, inside, n_sigma)
        z_flat = p[:, 2] - flat
        key_all = k * (nx * ny) + cid
        key, med, mad, tm, cnt = group_median(key_all[inside], z_flat[inside], b.t_s[inside])
        gi = np.searchsorted(key, key_all[inside])
        vx = np.bincount(gi, weights=vr[inside, 0], minlength=len(key)) / cnt
        vy = np.bincount(gi, weights=vr[inside, 1], minlength=len(key)) / cnt
        fl = np.bincount(gi, weights=floor[inside].astype(float), minlength=len(key))
        is_floor = fl * 2 >= cnt
        # a surface steeper than a granular pile's angle of repose is a wall or a pile's toe against one (a
        # cell across a step): not linear in a shift, it is left out
        # nor is a cell whose points in one interval scatter about its plane beyond the sensor's noise: a step
        # (a block's edge, a wall's foot) is not a plane either
        # and a cell on the building's edge holds a wall's foot, a step, whatever the wall's points assigned
        cx_i, cy_i = (key % (nx * ny)) // ny, (key % (nx * ny)) % ny
        edge = (cx_i == 0) | (cx_i == nx - 1) | (cy_i == 0) | (cy_i == ny - 1)
        keep = ((cnt >= MIN_CELL_POINTS) & (np.hypot(gx, gy)[key % (nx * ny)] <= MAX_PILE_SLOPE)
                & (mad <= BAND * max(sensor_m, noise_m)) & ~edge)
        key, med, mad, tm, cnt, vx, vy, is_floor = (a[keep] for a in (key, med, mad, tm, cnt, vx, vy, is_floor))
        cell = key % (nx * ny)
        seen, inv, times_seen = np.unique(cell, return_inverse=True, return_counts=True)
        floor_cells = pinned_to_floor(seen, inv, is_floor, gx, gy)
        use = (times_seen[inv] >= 2) | floor_cells[inv]
        key, med, mad, tm, cnt, vx, vy, cell, inv = (a[use] for a in (key, med, mad, tm, cnt, vx, vy, cell, inv))
        if len(key) == 0:
            return x_start, info, 0.0, 0
        uniq_cells, cell_idx = np.unique(inv, return_inverse=True)
        n_cells = len(uniq_cells)
        fc = np.flatnonzero(floor_cells[uniq_cells])
        g_x, g_y = gx[cell], gy[cell]
        # d(height at the cell's centre)/d(component): z 1, x -gx, y -gy, heading -g . J v
        coef = {Component.Z.value: np.ones(len(key)), Component.X.value: -g_x, Component.Y.value: -g_y,
                Component.HEADING.value: -(g_x * -vy + g_y * vx)}
        rows_s = median_sd_m(mad, cnt, noise_m)
        kk, ff = knot_basis(tm, knots)
        m_obs, m_floor = len(med), len(fc)
        n_par = nc * n_knots + n_cells
        r_i, c_i, d_i = [], [], []
        obs = np.arange(m_obs)
        for ci, c in enumerate(comps):
            r_i += [obs, obs]
            c_i += [ci * n_knots + kk, ci * n_knots + kk + 1]
            d_i += [coef[c] * (1 - ff) / rows_s, coef[c] * ff / rows_s]
        r_i += [obs, m_obs + np.arange(m_floor)]
        c_i += [nc * n_knots + cell_idx, nc * n_knots + fc]
        d_i += [-1.0 / rows_s, np.full(m_floor, 1.0 / noise_m)]
        a_obs = sparse.csr_matrix((np.concatenate(d_i), (np.concatenate(r_i), np.concatenate(c_i))),
                                  shape=(m_obs + m_floor, n_par))
        # the cells' heights relative to the current points: delta solves a_obs delta = b_obs
        b_obs = np.concatenate([-med / rows_s, np.zeros(m_floor)])
        # priors on the totals x + delta: steps, the walls' fit where they see it, absolute
        pr, pc, pd, pb = [], [], [], []
        r = 0
        for ci, c in enumerate(comps):
            for i in range(n_knots - 1):
                pr += [r, r]
                pc += [ci * n_knots + i, ci * n_knots + i + 1]
                pd += [-1.0 / step[c], 1.0 / step[c]]
                pb.append(-(x[i + 1, c] - x[i, c]) / step[c])
                r += 1
            if bend is not None and np.isfinite(bend[:, c]).any():
                for i in range(1, n_knots - 1):
                    if not np.isfinite(bend[i, c]):
                        continue
                    pr += [r, r, r]
                    pc += [ci * n_knots + i - 1, ci * n_knots + i, ci * n_knots + i + 1]
                    pd += [1.0 / bend[i, c], -2.0 / bend[i, c], 1.0 / bend[i, c]]
                    pb.append(-(x[i - 1, c] - 2.0 * x[i, c] + x[i + 1, c]) / bend[i, c])
                    r += 1
            for i in range(n_knots):
                w = math.sqrt(wall_info[i, c]) if c != Component.Z.value else 0.0
                if w > 0:
                    pr.append(r)
                    pc.append(ci * n_knots + i)
                    pd.append(w)
                    pb.append(-w * (x[i, c] - x_wall[i, c]))
                    r += 1
                pr.append(r)
                pc.append(ci * n_knots + i)
                pd.append(1.0 / abs_sigma[i, c])
                pb.append(-x[i, c] / abs_sigma[i, c])
                r += 1
        for i in range(n_cells):
            pr.append(r)
            pc.append(nc * n_knots + i)
            pd.append(1.0 / storage.height_m)
            pb.append(0.0)
            r += 1
        a_pr = sparse.csr_matrix((pd, (pr, pc)), shape=(r, n_par))
        # The heights scatter about the model by more than their points' spread says (a cell's plane is an
        # approximation, the footprints differ between passes): the rows in their residuals' own spread, so
        # the data weigh against the prior as much as they are worth.
        a = sparse.vstack([a_obs, a_pr], format="csr")
        rhs = np.concatenate([b_obs, np.asarray(pb)])
        sol = irls_huber(a, rhs)
        spread = max(1.0, robust_rms(a_obs @ sol - b_obs))
        if spread > 1.0:
            a_obs, b_obs = a_obs / spread, b_obs / spread
            a = sparse.vstack([a_obs, a_pr], format="csr")
            rhs = np.concatenate([b_obs, np.asarray(pb)])
            sol = irls_huber(a, rhs)
        delta = sol[:nc * n_knots].reshape(nc, n_knots).T
        a_k = a_obs[:, :nc * n_knots]
        col_info = np.asarray(a_k.multiply(a_k).sum(axis=0)).ravel().reshape(nc, n_knots).T
        if rnd == rounds - 1:
            # the gain of the components not fixed: the same rows with them held at x_start's values
            spread = 1.0  # the rows are in their own spread already
            free = [ci for ci, c in enumerate(comps) if c not in fixed]
            if free:
                held_cols = np.concatenate([np.arange(ci * n_knots, (ci + 1) * n_knots) for ci in free])
                rest = np.setdiff1d(np.arange(n_par), held_cols)
                held_val = np.concatenate([(x_start[:, comps[ci]] - x[:, comps[ci]]) for ci in free])
                rhs_h = rhs - a[:, held_cols] @ held_val
                sol_h = irls_huber(a[:, rest], rhs_h)
                r_held = a_obs[:, rest] @ sol_h - (b_obs - a_obs[:, held_cols] @ held_val)
                r_full = a_obs @ sol - b_obs
                gain = 2.0 * float(np.sum(huber_loss(r_held / spread)) - np.sum(huber_loss(r_full / spread)))
                n_extra = int(sum(np.count_nonzero(col_info[:, ci] * step[comps[ci]] ** 2 / spread ** 2 >= 1.0)
                                  for ci in free))
            for ci, c in enumerate(comps):
                info[:, c] = col_info[:, ci] / spread ** 2
        for ci, c in enumerate(comps):
            x[:, c] += delta[:, ci]
    if m_floor == 0 and Component.Z.value in comps:
        # No floor cell: the height's level is not observed (one constant added to every knot and cell fits the
        # same), and the cells' weak pull towards the floor set it: thousands of cells against a few dozen knots put
        # the pile's mean height into the vehicle's (1.0-2.0 m: pile 2, Ve 44-52 %). It goes back where the height
        # solved before put it. (At the end, not in each round: the rounds stay as they were, and holding the level
        # in them changed which registration was kept on a `flow` flight over pile 1, Ve 0.23 -> 7.1 %.)
        x[:, Component.Z.value] += float(np.mean(x_start[:, Component.Z.value]) - np.mean(x[:, Component.Z.value]))
    return x, info, gain, n_extra


def pinned_to_floor(cells: np.ndarray, inv: np.ndarray, is_floor: np.ndarray, gx: np.ndarray,
                    gy: np.ndarray) -> np.ndarray:
    """Per distinct cell (`cells`, the grid's cell ids; `inv`: each row's index into them), whether the registration
    holds its height at the floor's 0: a knot interval saw mostly floor points in it (`is_floor`, per row), and the
    cell is flat (no significant gradient: gx, gy per grid cell, `_significant_gradients`).

    A pile's toe holds both: the floor beside it and the flank's lowest decimetres, which the floor's band takes for
    the floor. Pinned to 0 with its fitted slope, such a cell had every pass seeing it pay for the kink with a shift
    up the slope, and the pile came out pulled in: on the true pose of 38 flights over our own cone and ridge, the
    forced registration moved their volume by -0.15 % on average (up to -0.8 %), by -0.05 % once sloped cells were
    left free (docs/design-notes.md). Free, a sloped cell counts as any cell seen twice: its passes must agree with
    one another, not with a floor."""
    pinned = np.zeros(len(cells), dtype=bool)
    pinned[inv[is_floor]] = True
    return pinned & (np.hypot(gx, gy)[cells] == 0)


def _cell_slopes(p: np.ndarray, cid: np.ndarray, n_cells: int, cell_m: float, ny: int,
                 use: np.ndarray) -> np.ndarray:
    """Per point, its cell's least-squares plane's height above the cell's centre at the point (0 where the
    cell's points do not span both directions)."""
    return _cell_gradients(p, cid, n_cells, cell_m, ny, use)[0]


def _cell_gradients(p: np.ndarray, cid: np.ndarray, n_cells: int, cell_m: float, ny: int,
                    use: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_cell_slopes`, and each cell's gradient (gx, gy) (n_cells,) each (0 where not fitted)."""
    cx = (cid // ny + 0.5) * cell_m
    cy = (cid % ny + 0.5) * cell_m
    dx, dy, z = p[:, 0] - cx, p[:, 1] - cy, p[:, 2]
    w = use.astype(float)

    def s(v: np.ndarray) -> np.ndarray:
        return np.bincount(cid, weights=v * w, minlength=n_cells)
    n, sx, sy, sz = s(np.ones(len(p))), s(dx), s(dy), s(z)
    sxx, sxy, syy, sxz, syz = s(dx * dx), s(dx * dy), s(dy * dy), s(dx * z), s(dy * z)
    safe = np.maximum(n, 1.0)
    # centred moments
    cxx, cxy, cyy = sxx - sx * sx / safe, sxy - sx * sy / safe, syy - sy * sy / safe
    cxz, cyz = sxz - sx * sz / safe, syz - sy * sz / safe
    det = cxx * cyy - cxy * cxy
    ok = (n >= 6) & (det > 1e-3 * np.maximum(cxx * cyy, 1e-12))
    gx = np.where(ok, (cyy * cxz - cxy * cyz) / np.where(ok, det, 1.0), 0.0)
    gy = np.where(ok, (cxx * cyz - cxy * cxz) / np.where(ok, det, 1.0), 0.0)
    return gx[cid] * dx + gy[cid] * dy, gx, gy


def _significant_gradients(p: np.ndarray, cid: np.ndarray, n_cells: int, cell_m: float, ny: int, use: np.ndarray,
                           n_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_cell_gradients`, with the gradient set to 0 where the plane does not explain more than n_sigma^2 (per
    degree of freedom) of its points' scatter: a flat cell's fitted slope is its noise's, and a shift would be
    bought from it."""
    flat, gx, gy = _cell_gradients(p, cid, n_cells, cell_m, ny, use)
    w = use.astype(float)
    cx = (cid // ny + 0.5) * cell_m
    cy = (cid % ny + 0.5) * cell_m
    dx, dy = p[:, 0] - cx, p[:, 1] - cy
    n = np.bincount(cid, weights=w, minlength=n_cells)
    res = p[:, 2] - flat
    mean_res = np.bincount(cid, weights=res * w, minlength=n_cells) / np.maximum(n, 1.0)
    ssr = np.bincount(cid, weights=(res - mean_res[cid]) ** 2 * w, minlength=n_cells)
    s2 = ssr / np.maximum(n - 3.0, 1.0)
    mx = np.bincount(cid, weights=dx * w, minlength=n_cells) / np.maximum(n, 1.0)
    my = np.bincount(cid, weights=dy * w, minlength=n_cells) / np.maximum(n, 1.0)
    ex, ey = dx - mx[cid], dy - my[cid]
    # the part of the scatter the slope explains: sum (g . (p - mean))^2
    explained = np.bincount(cid, weights=(gx[cid] * ex + gy[cid] * ey) ** 2 * w, minlength=n_cells)
    sig = (explained > 2.0 * n_sigma ** 2 * np.maximum(s2, 1e-12)) & (np.hypot(gx, gy) >= MIN_PILE_SLOPE)
    # and only where the slope continues up or down it: one cell across a block's edge, at a 0.93 slope, was a
    # registration's only sloped cell and moved a synthetic flight's along-track position by a metre, or not,
    # as a 2 % change of the cell size put the grid's cut across the edge
    sig &= _slope_continues(sig, gx, gy, n_cells, ny)
    gx, gy = np.where(sig, gx, 0.0), np.where(sig, gy, 0.0)
    return gx[cid] * dx + gy[cid] * dy, gx, gy


def _slope_continues(sloped: np.ndarray, gx: np.ndarray, gy: np.ndarray, n_cells: int, ny: int) -> np.ndarray:
    """Per cell (x-major, ny cells a column): whether its slope continues into a neighbour up or down it (the
    neighbour the gradient points to, or the one opposite, is sloped too, the same way). A pile's flank spans
    several cells; a step (a block's edge, a wall's foot) has flat cells on both sides, and the slope fitted
    across it is wherever the grid happened to cut it."""
    nx = n_cells // ny
    ix, iy = np.divmod(np.arange(n_cells), ny)
    g = np.hypot(gx, gy)
    sx = np.rint(np.divide(gx, g, out=np.zeros_like(gx), where=g > 0)).astype(np.int64)
    sy = np.rint(np.divide(gy, g, out=np.zeros_like(gy), where=g > 0)).astype(np.int64)
    out = np.zeros(n_cells, dtype=bool)
    for sign in (1, -1):
        jx, jy = ix + sign * sx, iy + sign * sy
        inside = (jx >= 0) & (jx < nx) & (jy >= 0) & (jy < ny) & ((sx != 0) | (sy != 0))
        j = np.where(inside, jx * ny + jy, 0)
        out |= inside & sloped[j] & (gx * gx[j] + gy * gy[j] > 0)
    return out


def apply_pose_correction(samples: np.ndarray, corr: PoseCorrection, frame: StorageFrame) -> np.ndarray:
    """A copy of the samples with the pose re-stated: position += the correction (W to NED), yaw -= dtheta
    (a turn about W's up axis is one about NED's down axis the other way)."""
    if not corr.applied:
        return samples
    out = samples.copy()
    c = corr.at(samples["t_s"].astype(float))
    d_ned = c[:, :3] @ frame.rot_w_from_ned  # R is symmetric: W -> NED of a vector
    if corr.lever_change_m is not None:
        # the lever arm moved in the body: every point moves by R_nb dl, as the vehicle's position moved by as much
        # would move it (the logged path moves with it, by the change: decimetres)
        dl = np.array([*corr.lever_change_m, 0.0])
        d_ned = d_ned + rot_body_to_ned(samples["roll_rad"], samples["pitch_rad"], samples["yaw_rad"]) @ dl
    for i, name in enumerate(("x_m", "y_m", "z_m")):
        out[name] = samples[name] + d_ned[:, i]
    out["yaw_rad"] = np.angle(np.exp(1j * (samples["yaw_rad"].astype(float) - c[:, 3])))
    return out


def with_closest_wall(corr: PoseCorrection, corrected: np.ndarray, frame: StorageFrame,
                      storage: Storage) -> PoseCorrection:
    """The correction with its corrected path's nearest approach to the walls and roof (`closest_wall`): the
    logged estimate keeps the plan's distance from the walls, the corrected path is where the vehicle was."""
    if not corr.applied or len(corrected) == 0:
        return corr
    path = frame.ned_to_w(np.column_stack([corrected["x_m"], corrected["y_m"], corrected["z_m"]]).astype(float))
    near = storage.nearest_surface(path)
    if near is None:
        return corr
    i, distance, surface = near
    t = corrected["t_s"]
    return replace(corr, closest_wall=(distance, surface, float(t[i]), float(t[i] - np.nanmin(t))))
