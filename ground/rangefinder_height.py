"""The share of the logged height that followed the pile, when the autopilot's height came from a downward rangefinder.

An EKF that takes its height from a downward rangefinder (the header's EKF sources say so:
`firmware_py.core.pose_source`) logs the height above whatever is below the vehicle. Over a stockpile that is
the pile's top, so the logged height is low by a share w of the ground's height below the vehicle (w = 1 for the
rangefinder alone; less where the EKF blends it with the barometer or switches between them), and every point
of a sweep is placed that much low. The building cannot always take it out: where the pile hides the floor, the
pose correction has no floor to tie the height to, and measured it as "too small to matter" on a flight 28 % low.

The crossings measure w without any floor: a cell seen at two times, with different ground heights below the
vehicle, comes out at heights that differ by -w times the difference of those ground heights. So w is the
least-squares slope of the cells' height differences on the ground-height differences, over every pair of times
a cell was seen (`estimate_share`), the ground below the vehicle read from the survey's own points (a grid of
cell medians, a cell without points taking its nearest's), and the crossings from points away from the nadir, so the
two do not share their noise. The height reference's own slow drift (the barometer's) is fitted beside w, so that a
drift that happens to follow the pile is not taken for a share of it. Those points are themselves placed low by the
error, so the ground below is read again from the points re-placed with the share found, until the lift settles. The
samples' logged heights are then raised by w times the ground below (`apply_share`), before the mount and the pose are
estimated, which then correct what is left (the barometer's walk, the horizontal drift).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame
from firmware_py.core.storage import Storage
from ground.group_stats import JACKKNIFE_BLOCKS, group_median, jackknife_sd
from ground.pointcloud import cloud_from_samples

CELL_M = 1.0
"""The cell of the crossings and of the ground below: small against a pile (a cell seen twice is one surface), large
enough that its median is not one beam's noise (0.5 m cells halved the share under Appendix A's pointing noise: the
ground below's noise dilutes a slope fitted on it)."""
N_SIGMA = 3.0
"""The share is applied when it is this many standard errors above zero."""
MAX_ROUNDS = 12
"""The ground below converges geometrically, by the share per round (points placed low read the ground low)."""
SETTLED_M = 0.01
"""The rounds stop when the lift moves by less than this (m)."""
DRIFT_KNOT_S = 30.0
"""The height reference's drift is linear between knots this far apart: the shortest correlation time the pose
correction believes of a drift (`PoseCorrectionOptions.drift_correlation_s`)."""
NADIR_M = 2.0 * CELL_M
"""Points this close to the vehicle's nadir read the ground below and are not crossings."""
LAGS_S = (0.0, 0.5, 1.0, 2.0, 4.0)
"""Trial time constants of the EKF's smoothing of the rangefinder height: the crossings' misfit picks one."""
MIN_POINTS = 3
"""Points of one interval in a cell for its height (a median)."""
STEP_S = 0.1
"""The time grid of the EKF's lag (`_lowpass`) and of the lift over time in the report: on it the reported lift is
the lift the samples got, linear between (a lag of 0 s leaves the ground below's steps, which it rounds off)."""


@dataclass(frozen=True)
class RangefinderShare:
    """What the crossings said of the rangefinder's share of the logged height.

    Attributes:
        share: w, the logged height's error per metre of ground below the vehicle (taken out with a minus sign).
        sigma: its standard error (the larger of the cells' and the flight's stretches': `_Crossings.fit`,
            `_Crossings.block_sigma`).
        pairs: the pairs of times a cell was seen that measured it.
        applied: whether the samples were re-placed with it.
        reason: one line when it was not applied.
        lift_m: (mean, largest) height it added to the samples, m.
        lift_t_s: times (the log's clock) at which the lift is reported, STEP_S apart.
        lift_at_t_m: the height added to the samples at those times, m (linear between): what a reader needs to
            put the vehicle's reported trajectory where the survey placed it.
        source_stated: whether the log header said the height came from the rangefinder (False: it did not say
            where the height came from, and the share was measured in case it did).
    """

    share: float
    sigma: float
    pairs: int
    applied: bool
    reason: str | None = None
    lift_m: tuple[float, float] = (0.0, 0.0)
    lift_t_s: tuple[float, ...] = ()
    lift_at_t_m: tuple[float, ...] = ()
    source_stated: bool = True

    def lift_at(self, t_s: np.ndarray) -> np.ndarray:
        """The height (m, up) the samples were raised by at times t_s: 0 when not applied."""
        t = np.asarray(t_s, dtype=float)
        if not self.applied or not self.lift_t_s:
            return np.zeros(t.shape)
        return np.interp(t, self.lift_t_s, self.lift_at_t_m)

    def as_dict(self) -> dict:
        return {"share": self.share, "sigma": self.sigma if math.isfinite(self.sigma) else None,  # strict JSON
                "pairs": self.pairs, "applied": self.applied,
                "reason": self.reason, "lift_mean_m": self.lift_m[0], "lift_max_m": self.lift_m[1],
                "lift_t_s": [round(v, 3) for v in self.lift_t_s],
                "lift_at_t_m": [round(v, 4) for v in self.lift_at_t_m], "source_stated": self.source_stated}

    def describe(self) -> str:
        said = ("" if self.source_stated else
                "the log does not say where the autopilot's height came from (no EKF source parameters in its "
                "header), and ")
        return (f"{said}the autopilot's height followed the pile (its downward rangefinder): the crossings measured a "
                f"share of {self.share:.2f} ± {self.sigma:.2f} of the ground's height below the vehicle in the "
                f"logged height, and it was taken out before the pose correction (the samples raised by "
                f"{self.lift_m[0]:.2f} m on average, {self.lift_m[1]:.2f} m at most)")


def _vehicle_w(samples: np.ndarray, frame: StorageFrame) -> np.ndarray:
    return frame.ned_to_w(np.column_stack([samples["x_m"], samples["y_m"], samples["z_m"]]).astype(float))


def _ground_grid(points_w: np.ndarray, storage: Storage) -> np.ndarray:
    """Median height of the points per CELL_M cell (a cell no point fell in: its nearest that holds points)."""
    nx, ny = math.ceil(storage.length_m / CELL_M), math.ceil(storage.width_m / CELL_M)
    i = np.clip((points_w[:, 0] / CELL_M).astype(int), 0, nx - 1)
    j = np.clip((points_w[:, 1] / CELL_M).astype(int), 0, ny - 1)
    keys, med, _, _, _ = group_median(i * ny + j, points_w[:, 2], points_w[:, 2])
    grid = np.full(nx * ny, np.nan)
    grid[keys] = med
    grid = grid.reshape(nx, ny)
    empty = np.isnan(grid)
    if empty.all():
        return np.zeros((nx, ny))
    if empty.any():  # between two sweep lines: the nearest cell that holds points
        _, (ii, jj) = distance_transform_edt(empty, return_indices=True)
        grid = grid[ii, jj]
    return np.clip(grid, 0.0, storage.height_m)


def ground_below_m(vehicle_w: np.ndarray, t_s: np.ndarray, points_w: np.ndarray, storage: Storage) -> np.ndarray:
    """The height of the ground below the vehicle (W, one row a sample at t_s) at each sample, from the points' cell
    medians."""
    grid = _ground_grid(points_w, storage)
    v = vehicle_w
    posed = np.isfinite(v[:, 0]) & np.isfinite(v[:, 1])  # a sample logged without a pose: from its neighbours
    out = np.zeros(len(v))
    if not posed.any():
        return out
    i = np.clip((v[posed, 0] / CELL_M).astype(int), 0, grid.shape[0] - 1)
    j = np.clip((v[posed, 1] / CELL_M).astype(int), 0, grid.shape[1] - 1)
    out[posed] = grid[i, j]
    if not posed.all():
        out[~posed] = np.interp(t_s[~posed], t_s[posed], out[posed])
    return out


def apply_share(samples: np.ndarray, share: float, below_m: np.ndarray, frame: StorageFrame) -> np.ndarray:
    """The samples with their logged height raised by share times the ground below (NED: down is +z; the frame's
    z axis is up, so a rise in W is a fall in down)."""
    out = samples.copy()
    up_ned = frame.rot_w_from_ned.T @ np.array([0.0, 0.0, 1.0])  # W's up in NED
    lift = share * below_m
    out["x_m"] = samples["x_m"] + lift * up_ned[0]
    out["y_m"] = samples["y_m"] + lift * up_ned[1]
    out["z_m"] = samples["z_m"] + lift * up_ned[2]
    return out


@dataclass(frozen=True)
class _Crossings:
    """The cells seen in two intervals at least one apart: each (cell, interval) group's median height, and the
    pairs of groups of one cell. The ground below enters per group (`below`), so one grouping serves every trial."""

    group: np.ndarray  # (N,) each point's group
    count: np.ndarray  # (G,) points per group
    z: np.ndarray  # (G,) median height
    a: np.ndarray  # (P,) pairs: first group
    c: np.ndarray  # (P,) second group
    cell: np.ndarray  # (P,) the pair's cell
    t: np.ndarray  # (G,) each group's mean time

    @classmethod
    def of(cls, points_w: np.ndarray, t_s: np.ndarray, interval_s: float) -> _Crossings:
        k = ((t_s - t_s.min()) // interval_s).astype(np.int64)
        cell = (points_w[:, 0] // CELL_M).astype(np.int64) * 100_000 + (points_w[:, 1] // CELL_M).astype(np.int64)
        key = cell * 1_000_000 + k
        keys, z, _, t, count = group_median(key, points_w[:, 2], t_s)
        group = np.searchsorted(keys, key)
        gcell, gk = keys // 1_000_000, keys % 1_000_000
        ok = count >= MIN_POINTS
        a, c = [], []
        for part in np.split(np.arange(len(keys)), np.flatnonzero(np.diff(gcell)) + 1):
            part = part[ok[part]]
            if len(part) < 2:
                continue
            i, j = np.triu_indices(len(part), 1)
            far = np.abs(gk[part][i] - gk[part][j]) >= 2  # another pass, not the next sweep of the same one
            a.append(part[i][far])
            c.append(part[j][far])
        a = np.concatenate(a) if a else np.zeros(0, dtype=np.int64)
        c = np.concatenate(c) if c else np.zeros(0, dtype=np.int64)
        return cls(group, count, z, a, c, gcell[a], t)

    def differences(self, below_at_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per pair: the cell's height difference and the ground-below difference."""
        b = np.bincount(self.group, weights=below_at_points, minlength=len(self.count)) / self.count
        return self.z[self.a] - self.z[self.c], b[self.a] - b[self.c]

    def _design(self, db: np.ndarray) -> np.ndarray:
        """The least-squares design of dz = -w db + b(t1) - b(t2): w's column, then the drift's knots DRIFT_KNOT_S
        apart (linear between; the first knot is 0, the drift being relative)."""
        t0, t1 = float(self.t.min()), float(self.t.max())
        k = max(2, math.ceil((t1 - t0) / DRIFT_KNOT_S) + 1)
        step = max((t1 - t0) / (k - 1), 1e-9)
        rows = np.arange(len(db))
        design = np.zeros((len(db), 1 + k))
        design[:, 0] = -db
        for g, sign in ((self.a, 1.0), (self.c, -1.0)):
            x = (self.t[g] - t0) / step
            i = np.clip(np.floor(x).astype(int), 0, k - 2)
            np.add.at(design, (rows, 1 + i), sign * (1.0 - (x - i)))
            np.add.at(design, (rows, 2 + i), sign * (x - i))
        return np.delete(design, 1, axis=1)

    def fit(self, below_at_points: np.ndarray) -> tuple[float, float, float]:
        """(w, its standard error, the misfit) with this ground below: dz = -w db + b(t1) - b(t2) over the pairs,
        b the height reference's slow drift (the barometer's), linear between knots DRIFT_KNOT_S apart, fitted
        with w so that a drift that happens to follow the pile is not taken for a share of it. The error takes a
        cell's pairs as one draw (their errors are shared); `block_sigma` adds what is shared over time."""
        dz, db = self.differences(below_at_points)
        if len(dz) == 0:
            return 0.0, math.inf, 0.0
        design = self._design(db)
        x = np.linalg.lstsq(design, dz, rcond=None)[0]
        r = dz - design @ x
        w = float(x[0])
        info = np.linalg.pinv(design.T @ design)
        _, inv = np.unique(self.cell, return_inverse=True)
        score = np.zeros((inv.max() + 1, design.shape[1]))
        np.add.at(score, inv, design * r[:, None])
        cov = info @ (score.T @ score) @ info
        return w, float(math.sqrt(max(cov[0, 0], 0.0))), float(r @ r)

    def block_sigma(self, below_at_points: np.ndarray) -> float:
        """w's standard error from a delete-one-block jackknife over time: the cells' sightings cut into
        JACKKNIFE_BLOCKS blocks in time order, w fitted again without the pairs that touch each block. Errors
        shared over a stretch of the flight (a drift the knots do not follow, a misplaced pass over the pile) move
        every pair of that stretch together, which a cell-by-cell error does not see: on 44 SITL `flow` flights the
        cells' error put the profile's true share 4 of them away (median), up to 15; this one 0.6, and no small
        share of the 56 `vio` flights (0.01-0.07: a barometer walk that happened to follow the ground) stays
        significant, against 19 (docs/design-notes.md)."""
        dz, db = self.differences(below_at_points)
        if len(dz) == 0:
            return math.inf
        edges = np.quantile(self.t, np.linspace(0.0, 1.0, JACKKNIFE_BLOCKS + 1))
        block_a = np.clip(np.searchsorted(edges, self.t[self.a], side="right") - 1, 0, JACKKNIFE_BLOCKS - 1)
        block_c = np.clip(np.searchsorted(edges, self.t[self.c], side="right") - 1, 0, JACKKNIFE_BLOCKS - 1)
        design = self._design(db)
        ws = []
        for b in range(JACKKNIFE_BLOCKS):
            keep = (block_a != b) & (block_c != b)
            if np.count_nonzero(keep) < design.shape[1] + 2:
                continue
            ws.append(float(np.linalg.lstsq(design[keep], dz[keep], rcond=None)[0][0]))
        if len(ws) < 3:  # too few blocks left to say anything: no share is believed
            return math.inf
        return jackknife_sd(np.asarray(ws))


def _lowpass(x: np.ndarray, t_s: np.ndarray, tau_s: float) -> np.ndarray:
    """A first-order low-pass of x(t) with time constant tau_s (0: x itself), on the STEP_S grid."""
    if tau_s <= 0 or len(x) < 2:
        return x
    from scipy.signal import lfilter  # here: scipy.signal imports scipy.stats, a quarter second of every start-up
    tg = np.arange(t_s[0], t_s[-1] + STEP_S, STEP_S)
    a = 1.0 - math.exp(-STEP_S / tau_s)
    y = lfilter([a], [1.0, a - 1.0], np.interp(tg, t_s, x), zi=[(1.0 - a) * x[0]])[0]
    return np.interp(t_s, tg, y)


def estimate_share(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, storage: Storage,
                   interval_s: float, boresight: Boresight = SQUARE) -> tuple[RangefinderShare, np.ndarray]:
    """The rangefinder's share of the logged height (module docstring), and the samples re-placed with it (the
    samples as they were when it is not applied)."""
    base = cloud_from_samples(samples, lever_arm_body_m, frame, boresight=boresight)
    if len(base.points_w) < 100:
        return RangefinderShare(0.0, math.inf, 0, False, "too few points to measure it"), samples
    inside = ((base.points_w[:, 0] > CELL_M) & (base.points_w[:, 0] < storage.length_m - CELL_M)
              & (base.points_w[:, 1] > CELL_M) & (base.points_w[:, 1] < storage.width_m - CELL_M)
              & (base.points_w[:, 2] < storage.height_m - 1.0))
    p0, t0 = base.points_w[inside], base.t_s[inside]
    t_all = samples["t_s"].astype(float)
    # The crossings from points away from the vehicle's nadir: the ground below is read from the nadir cells, and a
    # cell's height and the ground below read from the same points share their noise (on a flat floor, a share of 1).
    v = _vehicle_w(samples, frame)
    off_nadir = np.hypot(p0[:, 0] - np.interp(t0, t_all, v[:, 0]), p0[:, 1] - np.interp(t0, t_all, v[:, 1])) \
        > NADIR_M
    if np.count_nonzero(off_nadir) < 100:
        return RangefinderShare(0.0, math.inf, 0, False, "too few points away from the nadir to measure it"), samples
    crossings = _Crossings.of(p0[off_nadir], t0[off_nadir], interval_s)
    n = len(crossings.a)
    if n < 10:
        return RangefinderShare(0.0, math.inf, n, False, "no cell seen again at another ground height"), samples
    w, sigma, tau = 0.0, math.inf, 0.0
    placed, lift_p = p0, np.zeros(len(p0))
    for _ in range(MAX_ROUNDS):
        below_s = ground_below_m(v, t_all, placed, storage)
        lagged = {tau_s: _lowpass(below_s, t_all, tau_s) for tau_s in LAGS_S}
        trials = [(*crossings.fit(np.interp(t0[off_nadir], t_all, lagged[tau_s])), tau_s) for tau_s in LAGS_S]
        w, sigma, _, tau = min(trials, key=lambda r: r[2])  # the EKF's lag: the one the crossings fit best
        new_lift = w * np.interp(t0, t_all, lagged[tau])
        moved = float(np.max(np.abs(new_lift - lift_p)))
        lift_p = new_lift
        placed = p0 + np.column_stack([np.zeros(len(p0)), np.zeros(len(p0)), lift_p])
        if moved < SETTLED_M:  # the ground below read from points re-placed with the lift it gives: a fixed point
            break
    below_pairs = np.interp(t0[off_nadir], t_all, lagged[tau])
    dz, db = crossings.differences(below_pairs)
    sigma = max(sigma, crossings.block_sigma(below_pairs))  # what the flight's stretches share, beside the cells'
    spread, noise = float(np.sqrt(np.mean(db * db))), float(1.4826 * np.median(np.abs(dz + w * db)))
    if not spread > N_SIGMA * noise:  # a ground below as flat as the cells' own noise measures no share
        return RangefinderShare(w, sigma, n, False, f"the ground below the vehicle varied by {spread:.2f} m, "
                                f"within the cells' noise ({noise:.2f} m): nothing to measure a share on"), samples
    if not (w > N_SIGMA * sigma) or w > 1.0 + N_SIGMA * sigma:
        why = (f"not significant ({w:.2f} ± {sigma:.2f})" if not w > N_SIGMA * sigma
               else f"a share of {w:.2f} is more than the whole ground below: not a rangefinder height")
        return RangefinderShare(w, sigma, n, False, why), samples
    below_s = _lowpass(ground_below_m(v, t_all, placed, storage), t_all, tau)
    lift = w * below_s
    grid_t = np.arange(t_all[0], t_all[-1] + STEP_S, STEP_S)
    return (RangefinderShare(w, sigma, n, True, None, (float(np.mean(lift)), float(np.max(lift))),
                             tuple(float(v) for v in grid_t), tuple(float(v) for v in np.interp(grid_t, t_all, lift))),
            apply_share(samples, w, below_s, frame))
