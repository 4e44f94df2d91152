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
what the drift fit left; the height is solved again after it (`height_again`).

The pieces this module builds on: its planes, options and knots (`ground.pose_knots`), the height and the floor's
screen of step (3) (`ground.pose_height`), the registration of step (5) (`ground.pose_registration`), the cells both
compare the pile in (`ground.crossing_cells`), the no-harm decisions above (`ground.pose_decisions`), the robust
sparse least squares of its linear fits (`ground.huber_lsq`); the report's words for what it did are
`ground.pose_warnings`. This module keeps the vote, the fit to the planes and the order of the steps
(`estimate_pose_correction`).

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
from scipy.spatial import cKDTree

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame, rot_body_to_ned
from firmware_py.core.sensor_noise import POSE_STREAM_HZ
from firmware_py.core.storage import Storage
from ground.base import FloorFall
from ground.crossing_cells import grid_cells, in_building, not_the_pile
from ground.floor_check import floor_fall
from ground.group_stats import rms, robust_rms
from ground.plane_stretches import (
    INSIDE_SIGN,
    Beams,
    TimingSplit,
    beams,
    beside_a_servo_delay,
    body_axes_w,
    by_angle,
    nearest_plane,
    neighbour_noise_m,
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
    matters,
)
from ground.pose_height import (
    crossings_misfit_m,
    floor_anchored,
    floor_from_below,
    floor_unconfirmed_note,
    height_again,
    height_refused,
    height_rounds,
    level_sigma_m,
    open_floor_note,
    raised_floor_note,
    screen_floor,
    unanchored_stretches,
    untied_sigma_m,
)
from ground.pose_knots import (
    BAND,
    HELD,
    KNOT_SWEEPS,
    MAX_MISFIT,
    MIN_VOTES,
    PLANE_NAMES,
    STRAY_FRACTION,
    Component,
    PoseCorrectionOptions,
    corrected_points,
    knot_basis,
    knot_times,
    median_spacing_s,
    path_speed_m_s,
    prior_sigmas,
    sweep_period_from_samples,
)
from ground.pose_registration import registered
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
    cell_m: float | None = None
    """The side of the cells the pile seen at different times is compared in (what the vehicle flies in a sweep
    period), when the fit got that far: a caller comparing two corrections' crossings (`ground.report`) uses the
    same cells."""
    step_sigma: np.ndarray | None = None
    """(4,) the knots' random-walk prior (`prior_sigmas`: x, y, z in m, heading in rad), when the fit got that far: the
    prior a mount fitted with a drift beside it uses (`ground.report`, when `unexplained` or applied)."""
    drift_rms_m: float | None = None
    """The floor and walls' robust RMS off their planes after the drift model's fit to them, before the registration
    on the pile seen twice traded some of it (`rms_after_m` is after; with a lever arm applied in place of the knots,
    the lever arm's), when the fit got that far: how well a mount and a drift explain the building, which a caller
    comparing two mounts reads (`ground.report`)."""
    drift_fit: np.ndarray | None = None
    """(knots, 4) what the drift model's fit found (to the floor and walls, and the pile seen twice), when
    `unexplained` (not applied: `values` stay zero). A start for the mount fitted with a drift: bent by the mount, it
    is still nearer the drift than none is where the structure pins it only loosely."""
    servo_delay: TimingSplit | None = None
    """A servo timing offset fitted beside the drift model's fit to the floor and walls (`ground.plane_stretches.
    beside_a_servo_delay`), when the fit got that far: the report re-times the servo when it is significant and
    matters (`TimingSplit.significant`), which the pile seen on opposite sweeps, its usual trigger, shows only for
    large offsets."""
    servo_delay_raw: TimingSplit | None = None
    """The same offset fitted on the floor's and walls' points as logged, each knot interval's points on a plane at one
    logged angle about their own mean (`beside_a_servo_delay` with groups, `by_angle`), when the fit got that far: a
    lag of several milliseconds puts the walls decimetres off, beyond the windows the drift's fit gives its points
    planes in, where `servo_delay` no longer sees it."""
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
        return {"applied": self.applied, "reason": self.reason, "knot_spacing_s": median_spacing_s(self.knot_t_s),
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
                "sweep_heights": None if self.sweep_heights is None else self.sweep_heights.as_dict(),
                "servo_delay": None if self.servo_delay is None else self.servo_delay.as_dict(),
                "servo_delay_raw": None if self.servo_delay_raw is None else self.servo_delay_raw.as_dict()}


FINAL_WINDOW_NOISE = 3.0
"""The drift's fit narrows its windows down to this many noise levels (its last window; a point within BAND of them is
on its plane)."""


def timing_as_logged(pose: PoseCorrection) -> TimingSplit | None:
    """The servo timing offset on the floor and walls as logged (`PoseCorrection.servo_delay_raw`) where the one beside
    the drift's fit cannot see it: that fit was not made (too few points near their planes), or the offset moves the
    points further than its last windows reach. Else None: as logged, a knot interval's drift between the two sweep
    directions' sightings of one angle reads as a few tenths of a millisecond (measured on the pose campaigns' 76
    drifting flights without a lag: up to 0.73 ms at 8.6 standard errors, moving the points 0.8 cm; the drift's fit
    there read 0.00-0.03 ms)."""
    raw = pose.servo_delay_raw
    if raw is None:
        return None
    if pose.servo_delay is None or raw.shift_m > BAND * FINAL_WINDOW_NOISE * pose.noise_m:
        return raw
    return None


TIMING_SHARE = 0.5
"""A servo timing offset fitted beside the drift (`ground.plane_stretches.beside_a_servo_delay`) excuses what the drift
leaves on the floor and walls only when it explains at least this share of it (of its square): most of it. One more
free parameter always takes a little; measured (docs/design-notes.md, 2026-12-07): an injected 0.5 ms delay 71 %, the
networked SITL's bridge 52 %, an 11.5 deg boresight tilt the header did not state 17 % and 2 %."""


def not_applied(reason: str, knots: np.ndarray | None = None, **kw) -> PoseCorrection:
    """No correction, and why."""
    k = np.zeros(0) if knots is None else knots
    return PoseCorrection(k, np.zeros((len(k), 4)), np.zeros((len(k), 4), dtype=bool), False, reason, **kw)



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
    noise_m = neighbour_noise_m(j, r)
    return floor_m if noise_m is None else max(noise_m, floor_m)


def heading_step_at_walls_m(b: Beams, plane: np.ndarray, step_rad: float) -> float:
    """What the heading's prior lets it wander between two knots (a random walk's bridge: its RMS between knots is a
    step over sqrt 6), seen at the walls' median horizontal range: how far off their planes a heading set within
    that wander leaves the walls' points. plane: each point's plane (`PLANE_NAMES` order, -1: none); 0 without
    wall points."""
    wall = plane >= 1
    if not wall.any() or not step_rad > 0:
        return 0.0
    reach_m = float(np.median(np.hypot(b.to_point_w[wall, 0], b.to_point_w[wall, 1])))
    return reach_m * step_rad / math.sqrt(6.0)


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
    j0, r0 = nearest_plane(p0, n, d, opts.max_position_error_m, b.parallel)
    # The data's noise comes from neighbouring samples, which share a pose message: a position error drawn per
    # message (the header's; Appendix A's 0.11 m) is not in it, yet it scatters the points about their planes
    # and no knot seconds apart can fit it (an error-free flight: 0.32 m of "correction" on 1 of 648 runs).
    noise = math.hypot(_noise_m(np.where(np.abs(r0) <= sensor_m, j0, -1), r0, floor_m), position_sigma_m)
    speed = path_speed_m_s(b.t_s, b.vehicle_w, period or spacing / KNOT_SWEEPS)
    if not speed > 0:  # a log of one instant, or one sweep longer than it, or a vehicle that never moved
        return not_applied(f"the logged path does not move over the sweeps ({t1 - t0:.1f} s of samples): nothing "
                           "along a path to correct the pose from")
    step = prior_sigmas(spacing, speed, opts)
    cell_m = speed * (period or spacing / KNOT_SWEEPS)  # what the vehicle flies in a sweep period
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
    # The servo's timing offset on the points as logged, on the planes the start found them near (the vote's reach),
    # each knot interval's points on a plane at one logged angle (`angle_bins`) about their own mean: that takes the
    # drift out without its fit, so a lag that puts the walls beyond the fit's windows, or leaves too few points in
    # them for a fit at all, is found (`beside_a_servo_delay`). The angle's part: a mount's error is the same at one
    # angle both ways, a lag opposite (within a knot interval and plane alone a servo 3 deg off read as 4 ms of lag).
    j_raw, r_raw = nearest_plane(p0, n, d, opts.max_position_error_m, b.parallel)
    servo = samples["servo_rad"][usable(samples)][::stride]
    timed_raw = (beside_a_servo_delay(b.t_s, b.to_point_w, r_raw, j_raw, n, groups=by_angle(k * len(d) + j_raw, servo))
                 if len(servo) == len(b.t_s) and len(servo) else None)  # (placed elsewhere: not these samples')
    final = FINAL_WINDOW_NOISE * noise
    j_fit, _ = nearest_plane(corrected_points(b, x, k, f)[0], n, d, BAND * sensor_m, b.parallel)
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
            _, r = nearest_plane(corrected_points(b, x, k, f)[0], n, d, BAND * window, b.parallel)
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
                           "the pose", points=counts, noise_m=noise, servo_delay_raw=timed_raw)
    z_info = None
    tied: np.ndarray | None = None  # per knot interval, whether the height is tied to the floor (`floor_anchored`)
    first_refused: str | None = None  # why the height solved before the registration was refused
    z_sigma: list[float] = []  # the standard errors of the height's mean, the last solve's last
    notes: list[str] = []
    open_floor_shift: float | None = None  # what a floor the walls' feet do not confirm moved the height, when used
    height_floor: np.ndarray | None = None  # the floor the applied height rests on, when the walls' feet confirm it
    voted_floor: np.ndarray | None = None  # the vote's floor, before the screen drops what it takes for a pile's top
    # whether the height's level rests on a floor the walls' feet confirm (else on the logged reference): without
    # the crossings the walls' fit solves the height from the floor plane, when it saw one
    level_on_floor = opts.vertical and not opts.crossings and counts[0] > 0
    if opts.vertical and opts.crossings:
        # how far a floor seen only away from the walls may move the height (`_screen`): anywhere when the height
        # came from the rangefinder, else the barometer's walk over the flight (`PoseCorrectionOptions.open_floor`)
        open_shift = math.inf if opts.open_floor else opts.vertical_walk_m_per_sqrt_s * math.sqrt(t1 - t0)
        # the floor: points along it, in intervals where the vote found it, near the height it found
        z_at = np.interp(b.t_s, knots, z_vote)
        voted = voted_floor = b.parallel[:, 0] & (np.abs(p1[:, 2] + z_at) <= BAND * sensor_m)
        # what the crossings leave out: the walls' points, and what a beam pointing up beyond its own pointing
        # noise hit (a position error moves the vehicle and its points together: not the beam's direction)
        wall = not_the_pile((j1 >= 1) | (j_fit >= 1), b.to_point_w, angle_sigma_rad, opts.n_significant)

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
    j_pre, _ = nearest_plane(p0, n, d, BAND * sensor_m, b.parallel)
    pre = (j_pre >= 0) | on
    jj_pre = np.where(j_pre >= 0, j_pre, j1)[pre]
    to_matter = matters(np.einsum("ij,ij->i", p0[pre], n[jj_pre]) - d[jj_pre], r1[on],
                        np.einsum("ij,ij->i", p1[pre], n[jj_pre]) - d[jj_pre], jj_pre, noise)

    def misfit(v: np.ndarray) -> float:
        _, _, r, j = on_fit_planes(v)
        return robust_rms(r[j >= 0])
    # What the drift model, fitted to the floor and walls, leaves on them: the measure of whether a drift
    # explains them at all (MAX_MISFIT was measured on it: a drift leaves 1.1-1.5 noise levels, a mount fault ~6)
    _, drift_beam, drift_r, drift_j = on_fit_planes(x)  # kept: the registration below may replace x
    drift_misfit = robust_rms(drift_r[drift_j >= 0])
    # A servo timing offset moves the points of the two sweep directions opposite ways, which no drift does: fitted
    # beside the drift's fit, it excuses a misfit (below) and tells the report to re-time the servo (`ground.report`).
    timed = beside_a_servo_delay(b.t_s, drift_beam, drift_r, j_fit, n, BAND * final)
    if opts.vertical and opts.crossings and opts.crossings_horizontal and to_matter:
        # the height joins the registration when it was solved, or refused only in the frame before it
        z_free = z_info is not None or first_refused is not None
        x_reg, cross_info, cross_notes = registered(b, x, knots, k, f, wall, floor, storage, cell_m, step, noise,
                                                    sensor_m, info, sel, z_free, held[3], opts)
        if cross_info is not None:
            # No harm to the walls: the registration trades some of their fit for the pile seen twice, but one that
            # leaves them more than MAX_MISFIT times as far off as the drift fit did (or the noise, if more) is
            # dropped. (Against the noise alone, an ideal sensor's 0.3 cm range quantum, this refused registrations
            # that took two `flow` flights from 1.15 and 0.84 m of trajectory error to 0.09 m: docs/design-notes.md.)
            # Nor against less than what the heading's prior lets it wander between two knots, seen at the walls'
            # range: the registration sets the heading from the pile seen twice, which the walls see that much of
            # (a LiDAR tilted 2 deg under a `flow` drift, the mount fitted beside the drift: the walls 0.6 cm off
            # after the drift's fit, 1.9 cm after the registration that took the trajectory from 0.36 to 0.11 m).
            reg_misfit = misfit(x_reg)
            bound = MAX_MISFIT * max(noise, drift_misfit, heading_step_at_walls_m(b, j1, step[3]))
            if reg_misfit > bound:
                notes.append(f"the position from the pile seen at different times was not used: it left the floor "
                             f"and walls {reg_misfit * 100:.1f} cm off their planes, more than the "
                             f"{bound * 100:.1f} cm allowed ({drift_misfit * 100:.1f} cm without it)")
                cross_info, cross_notes = None, []
            else:
                x = x_reg
                if (z_info is not None and floor_note is not None) or first_refused is not None:
                    # The first height was solved in the frame before the registration (`height_again`); refused
                    # there, it is tried again in the registered frame: on slopes the horizontal error before it
                    # shows as height (measured: a two-knot zigzag of +0.95 / -0.88 m on our own ridge, refused
                    # as a jump, and the flight's volume 32 % off without any height correction).
                    x, z_again, again_note, sigma_again, floor_again, shift_again = height_again(
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
    j_before, _ = nearest_plane(p0, n, d, BAND * sensor_m, b.parallel)
    both = (j_before >= 0) | on
    jj = np.where(j_before >= 0, j_before, j1)[both]
    r_before = np.einsum("ij,ij->i", p0[both], n[jj]) - d[jj]
    r_after = np.einsum("ij,ij->i", p1[both], n[jj]) - d[jj]
    cap = (BAND * sensor_m / noise) ** 2
    gain = capped_gain(r_before, r_after, noise, cap)
    n_free = int(constrained.sum())
    needed = n_free + opts.n_significant * math.sqrt(2.0 * max(n_free, 1))
    common = dict(notes=tuple(notes), points=counts, rms_before_m=robust_rms(r_before),
                  rms_after_m=robust_rms(r1[on]), noise_m=noise, gain=gain, gain_needed=needed, cell_m=cell_m,
                  step_sigma=step, drift_rms_m=drift_misfit, servo_delay=timed, servo_delay_raw=timed_raw)
    if drift_misfit > MAX_MISFIT * noise:
        # No drift explains a servo timing offset, nor is it a mounting error; a fraction of a millisecond held
        # flights at this bound (docs/design-notes.md, 2026-12-07). Judged beside it, and said, it is no reason to
        # refuse the drift's correction.
        if timed.misfit_m <= MAX_MISFIT * noise and timed.misfit_m ** 2 <= (1.0 - TIMING_SHARE) * drift_misfit ** 2:
            notes.append(f"the floor and walls stayed {drift_misfit * 100:.1f} cm off their planes after the drift's "
                         f"fit, {timed.misfit_m * 100:.1f} cm beside a servo timing offset of "
                         f"{timed.delay_s * 1e3:+.2f} ms (the beam reaching each logged angle that much after the log "
                         "says), which moves the two sweep directions' points opposite ways: the drift is corrected, "
                         "the offset is not")
            drift_misfit = timed.misfit_m
            common["notes"] = tuple(notes)
    if drift_misfit > MAX_MISFIT * noise:
        return not_applied(f"not applied: the floor and walls stay {drift_misfit * 100:.1f} cm off their "
                           f"planes "
                           f"after it, against {noise * 100:.1f} cm of noise: a drifting pose does not explain them "
                           "(a mounting error the self-calibration did not fit?)", knots, unexplained=True,
                           drift_fit=x.copy(), **common)
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
        p_z = corrected_points(b, x_z, k, f)[0]
        z_before, z_after = p0[height_floor, 2], p_z[height_floor, 2]
        on_floor = p0[height_floor]
        _, _, cid = grid_cells(on_floor, storage, cell_m)
        wall_distance = to_nearest_wall_m(on_floor, storage.length_m, storage.width_m)
        material = (in_building(p0, wall, storage, opts.max_position_error_m) & ~height_floor
                    & (p0[:, 2] > float(np.median(z_before)) + MAX_MISFIT * noise))
        material_distance = (cKDTree(p0[material, :2]).query(on_floor[:, :2])[0] if material.any() else None)
        draws = shared_draws(b.t_s[height_floor], pose_draw_sigma_m, pose_stream_hz)
        brought = floor_brought_on(z_before, z_after, cid * len(knots) + k[height_floor], noise, open_shift,
                                   wall_distance, material_distance, draws, opts.n_significant, resolution_m)
        fall = (down_onto_a_fall(p_z, voted_floor, in_building(p_z, wall, storage, opts.max_position_error_m), noise)
                if brought and float(np.median(z_after - z_before)) < 0.0 and voted_floor is not None else None)
        if fall is not None:
            common.update(notes=(*common["notes"], f"the height was not brought down onto z = 0 from the floor: so "
                                                   f"placed it would still fall {fall.fall_pct:.1f} % towards "
                                                   f"{round(fall.rise_azimuth_deg):d} deg from x (a floor laid to a "
                                                   "fall, which no height error makes)"))
        elif brought:
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
                                  **{**common, "notes": (*common["notes"], note), "rms_after_m": lever_rms,
                                     "drift_rms_m": lever_rms})  # no drift applied: the lever arm is what explains
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


def down_onto_a_fall(p_w: np.ndarray, floor: np.ndarray, inside: np.ndarray, noise_m: float) -> FloorFall | None:
    """The fall of the vote's floor (floor: a mask over p_w, the points placed with the height the floor's route would
    apply) when it falls as much as a floor is laid to (`FloorFall.laid`, 1 %), fitted away from the material above it
    (`floor_fall`; inside: the points in the building off its walls; material: those more than MAX_MISFIT noise levels
    above the floor's median). None when it falls less.

    Why: a height error moves a level floor up or down as a whole, so a floor that would still fall once brought onto
    z = 0 was not moved by one. The floor's route brings a floor seen above z = 0 down only when it is level, but it
    judges the floor the screen kept, and on a floor laid to a fall the screen keeps its lower part and drops the rest
    as a flat pile top: the four cones on a 1.5 % floor, flown without pose error, had every point lowered 0.12 m
    (docs/design-notes.md). The vote's floor, before the screen, still holds the whole fall. Only down: nothing lies
    below the floor, so a floor below z = 0 is a height error whatever its slope (and the storage frame's z = 0 is the
    floor's lowest corner, so a fall alone never puts it there). Why the least fall a floor is laid to, not the 0.5 %
    the report names: the vote's floor holds a pile's toe within its band, and on level floors it read up to 0.94 %
    (of the evaluation runs reported with the lever arm's z 0.1 m off, one in ten: the route brought the floor onto
    z = 0 181 times, and at 0.5 % this would have refused 3, a wall pile's among them, whose lever arm then stayed
    off: docs/design-notes.md)."""
    v = p_w[floor]
    if not len(v):
        return None
    material = inside & ~floor & (p_w[:, 2] > float(np.median(v[:, 2])) + MAX_MISFIT * noise_m)
    fall = floor_fall(v, p_w[material, :2])
    return fall if fall is not None and fall.laid else None


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
