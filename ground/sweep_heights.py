"""The corrected height refined sweep by sweep from the floor each sweep sees.

The pose correction (`ground.pose_correction`) is piecewise linear between knots two sweep periods apart: a random
walk of the altitude reference between two knots is not in it. Measured on the own piles' 38 corrected flights (a
40 x 25 m building, piles of 136 and 384 m³): the corrected height is 10-20 mm RMS off the truth, and the floor's
cells, about 900 m², carry that as up to 1.2 % of the pile's volume. A sweep crosses the building from wall to wall:
where it sees the floor, its floor points say the height at that sweep's time, four times as often as the knots. So
after the correction each sweep's floor points give an offset (their median height), which is added to the height
between sweeps (linear in time), and only as much of it as the sweep's own errors leave believable: each offset is
shrunk by the empirical-Bayes factor tau^2 / (tau^2 + sigma_i^2), where sigma_i is the offset's standard error (its
points' scatter, and the position error drawn per pose message) and tau^2 the offsets' spread beyond those errors.
A clean survey keeps it all; under Appendix A's noise 2-61 % of it was kept. Where no sweep sees the floor for more
than two sweeps, the offset fades to zero over one: the knots, which the crossings of the pile tie, stand there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.frames import Boresight, StorageFrame
from firmware_py.core.storage import Storage
from ground.group_stats import rms, sorted_groups
from ground.plane_stretches import placed_beams, stretch_floor_m, sweep_ids

MIN_FLOOR_POINTS = 10
"""A sweep's floor gives an offset when it holds at least this many points (as a plane's peak in the pose vote)."""
N_SIGMA = 3.0
"""The floor's points are looked for within this many sigmas of the height's reach between two knots."""
MEDIAN_EFFICIENCY = math.sqrt(math.pi / 2.0)
"""A median's standard error over the mean's, for Gaussian scatter."""


@dataclass(frozen=True)
class SweepHeights:
    """The height offsets the sweeps' floor gives, to add to the corrected height (W's z, m), linear in time
    between anchors (zero anchors taper it where no sweep saw the floor).

    Attributes:
        t_s: (N,) anchor times (the log's clock).
        dz_m: (N,) the height added there (W z, m).
        sweeps_used: sweeps whose floor gave an offset; sweeps: all sweeps.
        shrink: the mean factor the offsets were shrunk by (1: kept whole, 0: all noise).
    """

    t_s: np.ndarray
    dz_m: np.ndarray
    sweeps_used: int
    sweeps: int
    shrink: float

    def at(self, t_s: np.ndarray) -> np.ndarray:
        """(N,) the height added at times t_s (zero beyond the anchors)."""
        t = np.asarray(t_s, dtype=float)
        if len(self.t_s) == 0:
            return np.zeros(len(t))
        return np.interp(t, self.t_s, self.dz_m, left=0.0, right=0.0)

    def rms_m(self) -> float:
        return rms(self.dz_m)

    def as_dict(self) -> dict:
        return {"sweeps_used": self.sweeps_used, "sweeps": self.sweeps, "shrink": self.shrink,
                "rms_m": self.rms_m(), "max_m": float(np.abs(self.dz_m).max(initial=0.0)),
                "t_s": [float(v) for v in self.t_s], "dz_m": [float(v) for v in self.dz_m]}


def _robust_sigma(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else 0.0


def floor_points(z_m: np.ndarray, along_floor: np.ndarray, reach_m: float) -> np.ndarray:
    """(N,) which points are the floor's: their stretch runs along the floor (`ground.plane_stretches`; a pile's toe
    climbs) and they lie within reach_m of z = 0. Not narrowed to the points' own spread: each sweep's floor is off by
    its own offset, and a window the size of the whole floor's scatter cut the sweeps most off (measured: an own-pile
    flight's offsets 12 -> 9 mm RMS, its volume's gain halved)."""
    return along_floor & (np.abs(z_m) <= reach_m)


def sweep_offsets(z_m: np.ndarray, t_s: np.ndarray, sweep: np.ndarray, floor: np.ndarray, quantum_m: float,
                  pose_draw_sigma_m: float = 0.0,
                  pose_stream_hz: float = 50.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per sweep whose floor holds MIN_FLOOR_POINTS: the floor points' median time, their median height (the
    offset) and its standard error: their robust scatter (never under the range's quantisation) over their number,
    and the position error drawn per pose message (pose_draw_sigma_m, the header's) over the messages they were
    placed from. Why the second: the samples between two pose messages share its draw, so they are not independent
    in it, and a white draw is not the slow wander the offsets are to follow (Appendix A's 0.11 m a message: offsets
    of 5-15 cm RMS kept at 0.76-0.99 without it)."""
    ids, zs, ts = sweep[floor], z_m[floor], t_s[floor]
    order = np.argsort(ids, kind="stable")
    ids, zs, ts = ids[order], zs[order], ts[order]
    _, starts, counts = sorted_groups(ids)
    t_out, off, se = [], [], []
    for a, n in zip(starts, counts, strict=True):
        if n < MIN_FLOOR_POINTS:
            continue
        b = a + n
        z = zs[a:b]
        messages = len(np.unique(np.floor(ts[a:b] * pose_stream_hz)))
        t_out.append(float(np.median(ts[a:b])))
        off.append(float(np.median(z)))
        se.append(math.hypot(MEDIAN_EFFICIENCY * max(_robust_sigma(z), quantum_m) / math.sqrt(n),
                             pose_draw_sigma_m / math.sqrt(messages)))
    return np.array(t_out), np.array(off), np.array(se)


def shrunk(off: np.ndarray, se: np.ndarray) -> tuple[np.ndarray, float]:
    """The offsets shrunk towards zero by how much of their spread their own errors explain (empirical Bayes:
    offset = true + error, true ~ N(0, tau^2)); and the mean factor."""
    if len(off) == 0:
        return off, 0.0
    tau2 = max(0.0, float(np.mean(off ** 2) - np.mean(se ** 2)))
    k = tau2 / (tau2 + se ** 2) if tau2 > 0 else np.zeros(len(off))
    return off * k, float(np.mean(k))


def tapered(t: np.ndarray, dz: np.ndarray, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The anchors with zeros put one sweep period beyond each end and inside each gap longer than two periods, so
    the offset fades to zero where no sweep saw the floor instead of being carried across the gap."""
    if len(t) == 0:
        return t, dz
    ts, zs = [t[0] - period_s], [0.0]
    for i in range(len(t)):
        if i and t[i] - t[i - 1] > 2.0 * period_s:
            ts += [t[i - 1] + period_s, t[i] - period_s]
            zs += [0.0, 0.0]
        ts.append(float(t[i]))
        zs.append(float(dz[i]))
    ts.append(t[-1] + period_s)
    zs.append(0.0)
    return np.array(ts), np.array(zs)


def sweep_heights(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, storage: Storage,
                  boresight: Boresight, range_sigma_m: float, range_sigma_rel: float, angle_sigma_rad: float,
                  resolution_m: float, position_sigma_m: float, period_s: float,
                  reach_m: float, pose_draw_sigma_m: float = 0.0,
                  pose_stream_hz: float = 50.0) -> SweepHeights | None:
    """The offsets (module docstring) of samples already corrected; None when no sweep's floor gives one.
    period_s: a sweep's duration (half the servo's period); reach_m: how far from z = 0 a floor point may lie
    (the height correction's own reach); pose_draw_sigma_m, pose_stream_hz: the header's position error drawn per
    pose message, and the messages a second (`sweep_offsets`)."""
    floor_m = stretch_floor_m(resolution_m)
    b, sweep_dir = placed_beams(samples, lever_arm_body_m, frame, boresight, storage, range_sigma_m, range_sigma_rel,
                                angle_sigma_rad, floor_m, position_sigma_m)
    if len(b.t_s) < 2 or b.parallel is None:
        return None
    p = b.vehicle_w + b.to_point_w
    dt = float(np.median(np.diff(b.t_s)))
    sweep = sweep_ids(b.t_s, sweep_dir, dt)
    on = floor_points(p[:, 2], b.parallel[:, 0], reach_m)
    t, off, se = sweep_offsets(p[:, 2], b.t_s, sweep, on, resolution_m / math.sqrt(12.0), pose_draw_sigma_m,
                               pose_stream_hz)
    if len(t) == 0:
        return None
    r, k = shrunk(off, se)
    ts, zs = tapered(t, -r, period_s)
    return SweepHeights(ts, zs, len(t), int(sweep.max() - sweep.min() + 1), k)

