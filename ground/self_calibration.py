"""Self-calibration from the building: the servo's zero and scale and the LiDAR's boresight, estimated
from the planes every survey sees.

A real servo is never where its calibration says, and a LiDAR is never glued on square: the true beam
is at gamma' = offset + (1 + scale) gamma (gamma the logged, modelled angle) and leans out of the
sweep plane by the boresight (`firmware_py.core.frames.Boresight`: a tilt out of the plane and a yaw of
the servo axis). The floor (z = 0) and the four walls are known planes (the log header's storage), so
the four parameters are those that put the structure points back on their planes.

What each plane constrains (measured per plane set by `plane_set_errors`): a wall beside the track,
seen at the sweep's end, and the floor pin the offset and the scale through the beam's elevation (a
wall point moves by its drop below the LiDAR times the angle error, a floor point by its horizontal
distance); a tilt or a yaw moves a point along the track, which only a plane facing the track sees:
the walls seen while the vehicle turns at the corners (the floor and the walls beside it see a tilt
only through the vehicle's roll and pitch, an order of magnitude more weakly). So the floor is not
needed: where a pile hides it (the paper's pile 2 leaves ~30 floor points) the walls carry the fit, and on a steady
pose the fit takes the walls alone unless they tell nothing (`estimate_mount`: under noise the floor's band takes in
the pile's toe).

How: first a vote over the whole plausible range (`_search`, a Hough transform over the servo's
offset and scale): every point says which offset would put it on each plane at each trial scale, and
the mount most structure points agree on wins, so the fit starts in the right basin however much of
the structure the pile hides (a local fit started square was dragged off by pile points near the
walls). Then robust least squares (arctan loss, bounded influence) over the points near a plane, the
window shrinking from the sensor's datasheet error to what the data achieve.

Observability, from the data: each parameter's covariance from the fit's tangent and residuals, the
points of a sweep taken as one draw (a cluster-robust sandwich). A parameter the structure seen does
not pin well enough that a deviation that matters would stand 3 standard errors out is held square
(reported as not observable) and the rest fitted again; none observable: nothing is estimated.

How sure: the samples are split into eight interleaved groups of whole sweeps (every eighth sweep),
each group fitted on its own; the spread of the eight estimates gives each parameter's standard
error. A parameter is applied only when it is both significant (beyond 3 standard errors) and large
enough to matter: it moves a structure point at the survey's median range by more than the sensor's
range sigma there. So a fault-free survey gets no correction, and the report says what was found.

Under sensor noise that is not enough: the pile's points just inside the floor and walls, which the
noise-widened bands take in from one side only, bias the fit, and a bias is as significant as a real
error. So a correction is applied only if the data say the planes' own points come back
(`_misfit_gain`: it brings the points closer to their planes than the noise; `_inside_excess`: it does
not hold the planes with points from the inside, where a plane's own noise is symmetric; `lever_alternative`: the
lever arm moved by one vector in the body does not explain them as well, which is what a lever arm entered off
does and no mount parameter can); else `MountEstimate.refused` says why.

On top of the configured mounting: the log header's ``boresight`` (the payload's --boresight, square when
absent) is where the fit starts; the tilt and yaw it estimates, reports and applies are deviations from it.

Why this does not fight the servo re-timing (`ground.servo_timing`): a late or slow servo shows as a
disagreement between the two sweep directions, an offset, a scale error and a boresight do not (they
move both directions alike), so the timing is fixed first and this fit sees the re-timed angles.
"""

from __future__ import annotations

import hashlib
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.optimize import least_squares

from firmware_py.core.frames import (
    SQUARE,
    Boresight,
    StorageFrame,
    beam_dir_body,
    beam_dot_body,
    beam_dot_body_partials,
    premultiply,
    rot_body_to_ned,
)
from firmware_py.core.servo_model import command_angles, servo_angles
from firmware_py.core.storage import Storage
from ground.blas_threads import one_blas_thread
from ground.group_stats import robust_rms
from ground.plane_stretches import INSIDE_SIGN, beams, nearest_plane, neighbour_noise_m, planes, stretches_along
from ground.pose_correction import lever_shift
from ground.pose_knots import knot_basis
from ground.remembered import Remembered
from ground.servo_timing import Resimulated

N_GROUPS = 8
"""Interleaved groups of sweeps for the standard errors."""
MAX_MISFIT = 3.0
"""A fit whose structure points stay more than this many noise levels off their planes is not applied."""
N_SIGNIFICANT = 3.0
"""A parameter is applied when beyond this many standard errors (and large enough to matter)."""
MAX_POINTS = 20_000
"""Points used in the fit (evenly spaced in time); the planes need far fewer."""
SEARCH_RESOLUTION_RAD = math.radians(0.1)
"""The start search's offset bin: fine enough that pile points rarely share a bin with the structure,
coarse against the angle noise of a structure point (a few mm at metres: hundredths of a degree)."""
SEARCH_SCALE_NODE = 0.025
"""Scales at which the search re-runs the servo model, interpolated linearly between: at most 0.23 deg
off the exact model (95th percentile, paper's sweep), inside the fit's first window."""
PARAMS = ("servo_offset_rad", "servo_scale", "boresight_tilt_rad", "sweep_yaw_rad")
LIN_STEP = 1e-3
"""Scale step of the servo model's tangent (`ServoAngles.linearize`)."""
BOUNDS = (np.array([-math.radians(20.0), -0.3, -math.radians(20.0), -math.radians(20.0)]),
          np.array([math.radians(20.0), 0.3, math.radians(20.0), math.radians(20.0)]))
"""What a mounting can plausibly be off by (the SITL's fault limits); an estimate at a bound is a
failed fit (data the planes cannot explain), never applied."""
REMEMBERED_SIMS_BYTES = 64 * 2**20
"""Servo re-simulations kept across `ServoAngles` instances, by their drive and scale (`ServoAngles._sim`), up to this
many bytes, the least recently used let go first: a report's fits on 20,000 samples re-run about 110 scales (18 MB);
a long flight's full log keeps fewer."""
_sims: Remembered[np.ndarray] = Remembered(REMEMBERED_SIMS_BYTES, lambda a: a.nbytes)


def forget_sims() -> None:
    """Forget the remembered re-simulations: a benchmark that reports one flight again and again times a fresh report
    only when it forgets them (and the covariance fits, `ground.gp_slopes.forget_fits`) before each run."""
    _sims.clear()


@dataclass(frozen=True)
class MountEstimate:
    """What the fit found, and what is applied.

    Attributes:
        values: the four parameters (PARAMS order), as estimated.
        std_errors: their standard errors (from the spread over sweep groups); NaN when nothing was
            large enough to matter (then they are not computed).
        applied: which of them are applied (significant and large enough to matter).
        points: structure points in the final fit, per plane (floor, x=0, x=L, y=0, y=W).
        rms_before_m, rms_after_m: robust RMS distance of those points from their planes.
        reason: one line when nothing could be estimated (too few structure points).
        observable: which parameters the structure seen pins down (module docstring); the others are
            held square (value 0, not applied).
        refused: one line when significant parameters were not applied because the correction does not
            bring the structure closer to its planes by more than the noise (`_misfit_gain`).
        unexplained: nothing estimated because the structure stays off its planes whatever the mount (as
            `PoseCorrection.unexplained` says of the drift).
        lever_change_m: the change of the lever arm (body forward, right, down) that puts the structure back on its
            planes as well as the correction did, when that is why the correction was not applied
            (`lever_alternative`); None otherwise.
        with_drift: fitted together with a drift of the trajectory (`DriftNuisance`): a proposal, made where neither
            the mount nor the pose explained the building alone, and said so in the report (a tilt traded against an
            along-track drift is less certain than one seen on a steady pose).
        held: which parameters the caller held as configured (`estimate_mount`'s `held`), not estimated: beside a
            drift, the report holds the boresight when the flight is explained as well without it
            (`ground.report`).
        given: not estimated at all: the user's measured mount (`KnownMount`, `--mount`), applied as given; its
            standard errors and structure RMS are NaN (nothing was fitted).
    """

    values: tuple[float, float, float, float]
    std_errors: tuple[float, float, float, float]
    applied: tuple[bool, bool, bool, bool]
    points: tuple[int, int, int, int, int]
    rms_before_m: float
    rms_after_m: float
    reason: str | None = None
    observable: tuple[bool, bool, bool, bool] = (True, True, True, True)
    refused: str | None = None
    unexplained: bool = False
    lever_change_m: tuple[float, float, float] | None = None
    with_drift: bool = False
    held: tuple[bool, bool, bool, bool] = (False, False, False, False)
    given: bool = False

    @property
    def any_applied(self) -> bool:
        return any(self.applied)

    def correction(self, base: Boresight = SQUARE) -> tuple[float, float, Boresight]:
        """(offset rad, scale, boresight) to apply: the applied parameters, zero for the rest; the
        boresight is the configured one (base) plus the applied deviations."""
        v = [x if a else 0.0 for x, a in zip(self.values, self.applied, strict=True)]
        return v[0], v[1], mounted(base, v[2], v[3])

    def as_dict(self) -> dict:
        deg = (True, False, True, True)
        out = {}
        for name, v, e, a, o, h, is_angle in zip(PARAMS, self.values, self.std_errors, self.applied, self.observable,
                                                 self.held, deg, strict=True):
            key = name.replace("_rad", "_deg") if is_angle else name
            f = math.degrees if is_angle else (lambda x: x)
            out[key] = {"estimate": f(v), "std_error": None if math.isnan(e) else f(e), "applied": a,
                        "observable": o, "held_as_configured": h}
        out.update(points_per_plane=dict(zip(("floor", "x0", "xL", "y0", "yW"), self.points, strict=True)),
                   rms_before_m=_finite_or_none(self.rms_before_m), rms_after_m=_finite_or_none(self.rms_after_m),
                   reason=self.reason, refused=self.refused,
                   lever_change_m=None if self.lever_change_m is None else list(self.lever_change_m),
                   fitted_with_drift=self.with_drift, given=self.given)
        return out


def _finite_or_none(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None  # NaN is no JSON: a given mount fitted nothing


@dataclass(frozen=True)
class KnownMount:
    """The mount's errors against the log header's calibration as the user measured them (`pilescan-ground report
    --mount`), applied in place of the self-calibration: the servo's zero offset (rad) and its travel's scale error (a
    fraction: +0.05 turns 5 % further per pulse than calibrated), the LiDAR's tilt out of the sweep plane and the
    sweep plane's yaw (rad) on top of the header's boresight; the conventions `MountEstimate` reports in, so a mount the
    building found can be given back as it was reported. Why: a servo or a mounting measured on the bench after the
    flight is known better than a building that shows little structure lets the self-calibration find it, and a
    simulated flight's true mount tells what of its error the calibration leaves (tools.pose_mount_check). Held to
    BOUNDS, what a mounting can plausibly be off by."""

    servo_offset_rad: float = 0.0
    servo_scale: float = 0.0
    tilt_rad: float = 0.0
    sweep_yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        names = ("servo offset", "servo scale", "tilt", "sweep yaw")
        for name, v, lo, hi, pct in zip(names, self.values, BOUNDS[0], BOUNDS[1], (False, True, False, False),
                                        strict=True):
            if not (math.isfinite(v) and lo <= v <= hi):
                shown, unit, limit = (v * 100, " %", hi * 100) if pct else (math.degrees(v), " deg", math.degrees(hi))
                raise ValueError(f"the {name} must be within +/-{limit:g}{unit} (what a mounting can plausibly be off "
                                 f"by), got {shown:g}{unit}")

    @property
    def values(self) -> tuple[float, float, float, float]:
        return (self.servo_offset_rad, self.servo_scale, self.tilt_rad, self.sweep_yaw_rad)

    def estimate(self) -> MountEstimate:
        """The mount as an estimate the report applies: every parameter that is not zero applied, nothing fitted."""
        nan = math.nan
        return MountEstimate(self.values, (nan, nan, nan, nan), tuple(v != 0.0 for v in self.values),
                             (0, 0, 0, 0, 0), nan, nan, given=True)


MAX_MOUNT_RAD = math.pi / 4
"""`Boresight`'s own limit on each angle."""


def mounted(base: Boresight, d_tilt_rad: float, d_yaw_rad: float) -> Boresight:
    """The configured boresight turned by the deviations (each angle kept within `Boresight`'s limits)."""
    return Boresight(float(np.clip(base.tilt_rad + d_tilt_rad, -MAX_MOUNT_RAD, MAX_MOUNT_RAD)),
                     float(np.clip(base.sweep_yaw_rad + d_yaw_rad, -MAX_MOUNT_RAD, MAX_MOUNT_RAD)))


def not_estimated(reason: str, points: tuple[int, int, int, int, int] = (0,) * 5,
                  unexplained: bool = False) -> MountEstimate:
    """No estimate, and why (nothing is applied)."""
    return MountEstimate((0.0,) * 4, (0.0,) * 4, (False,) * 4, points, 0.0, 0.0, reason, unexplained=unexplained)


class ServoAngles:
    """The shaft angle of a servo whose zero and scale differ from its calibration by (offset, scale).

    With the header's drive (`Resimulated`: waveform, calibration, sweep start) the firmware's own
    servo model is run again on the pulses it sent, read by the true servo as (1 + scale) times the
    commanded angle plus the offset, slewing at its rated speed: a servo that turns 5 % more per
    pulse also hits its slew limit sooner, which a plain scale of the logged angles misses (up to
    4 deg on the paper's sweep). The logged angle plus the difference true minus nominal is used, so
    the re-simulation's own small differences from the payload's model cancel (`Resimulated.apply`).
    Without the drive: offset + (1 + scale) times the logged angle. The offset adds exactly either
    way (the model's slew and lag act on the error between target and shaft, which a common offset
    leaves alone), so only a new scale costs a re-simulation.
    """

    def __init__(self, samples: np.ndarray, resim: Resimulated | None) -> None:
        self.logged = samples["servo_rad"].astype(float)
        self.resim = resim
        self._cache: dict[float, np.ndarray] = {}
        if resim is not None:
            self.t = samples["t_s"].astype(float) - resim.t0_s
            end = float(self.t.max()) if len(self.t) else 0.0
            self.cmd_t = np.arange(0.0, end + resim.frame_s, resim.frame_s)
            self.cmd = command_angles(resim.waveform, resim.cal, self.cmd_t, resim.frame_s)
            self.angle0 = float(resim.waveform.angle(0.0))
            digest = hashlib.blake2b(repr((resim.cal, self.angle0)).encode(), digest_size=20)
            for a in (self.t, self.cmd_t, self.cmd):
                digest.update(repr(np.shape(a)).encode())
                digest.update(np.ascontiguousarray(a, dtype=float).tobytes())
            self._drive = digest.digest()
            self.nominal = self._sim(0.0)

    def _sim(self, scale: float) -> np.ndarray:
        """The re-simulated angles at a scale (read-only), remembered by the drive and the scale: a report fits the
        mount several times on the same samples (alone, beside a drift, with its boresight held), and each fit's search
        re-ran the same scales (a `vio` flight's pose-corrected report: 144 re-simulations, 110 of them distinct, 5 ms
        each on the estimates' thread). What is remembered is what would be computed: the same arrays to the bit."""
        key = self._drive + struct.pack("<d", float(scale))
        got = _sims.get(key)
        if got is not None:
            return got
        r = self.resim
        got = servo_angles(self.t, self.cmd_t, (1.0 + scale) * self.cmd, r.cal, (1.0 + scale) * self.angle0)
        got.setflags(write=False)
        _sims.put(key, got)
        return got

    def exact(self, scale: float) -> np.ndarray:
        """The angles for a scale, re-simulated (offset 0)."""
        if self.resim is None:
            return (1.0 + scale) * self.logged
        got = self._cache.get(scale)
        if got is None:
            if len(self._cache) > 8:
                self._cache.clear()
            got = self._cache[scale] = self.logged + self._sim(scale) - self.nominal
        return got

    def linearize(self, scale: float) -> None:
        """Use the angles' tangent at `scale` until the next call: a fit stage moves the scale by a
        little, and one re-simulation a stage instead of one per trial scale cuts the cost tenfold
        (each stage re-linearizes where the last one ended, so the final fit is exact to second order)."""
        base = self.exact(scale)
        self._lin = (scale, base, (self.exact(scale + LIN_STEP) - base) / LIN_STEP)

    def scale_slope(self, idx: np.ndarray | slice = slice(None)) -> np.ndarray | None:
        """d(angle)/d(scale) of the samples idx as `__call__` computes them: the logged angles without the drive,
        the tangent's slope once linearized; None for the exact re-simulation (no closed form)."""
        if self.resim is None:
            return self.logged[idx]
        lin = getattr(self, "_lin", None)
        return None if lin is None else lin[2][idx]

    def __call__(self, offset: float, scale: float, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        """The angles of the samples idx (all by default): a fit over some points computes only theirs."""
        lin = getattr(self, "_lin", None)
        if self.resim is None:
            return (1.0 + scale) * self.logged[idx] + offset
        if lin is None:
            return self.exact(scale)[idx] + offset
        s0, base, slope = lin
        return base[idx] + (scale - s0) * slope[idx] + offset


class _Problem:
    """The samples' geometry, fixed, and the points as a function of the four parameters."""

    def __init__(self, s: np.ndarray, lever, frame: StorageFrame, resim: Resimulated | None,
                 base: Boresight = SQUARE) -> None:
        self.base = base
        self.gamma, self.range_m = s["servo_rad"].astype(float), s["range_m"].astype(float)
        self.angles = ServoAngles(s, resim)
        # What the parameters cannot change, once: each beam's origin and its body-to-W rotation
        # (eqs. 3-6 as `beam_rays_w` computes them; only the beam's direction in the body varies).
        r_nb = rot_body_to_ned(s["roll_rad"], s["pitch_rad"], s["yaw_rad"])
        self.r_wb = premultiply(frame.rot_w_from_ned, r_nb)
        pos = np.stack([s["x_m"], s["y_m"], s["z_m"]], axis=1).astype(float)
        self.origins = frame.ned_to_w(pos) + np.einsum("nij,j->ni", self.r_wb, np.asarray(lever, dtype=float))
        self._level = (s, frame)
        self.along: np.ndarray | None = None
        """(N, 5) whether each point's stretch of sweep runs along each plane (`along_planes`); None: not known,
        every point may lie on every plane."""

    def allowed(self, idx: np.ndarray | slice = slice(None)) -> np.ndarray | None:
        return None if self.along is None else self.along[idx]

    def level(self) -> _Problem:
        """The same beams from a level vehicle (roll and pitch zero, heading kept): the survey's
        geometry without the vehicle's wobble (`estimate_mount`'s observability)."""
        s, frame = self._level
        out = object.__new__(_Problem)
        out.__dict__.update(self.__dict__)
        r_nb = rot_body_to_ned(np.zeros(len(s)), np.zeros(len(s)), s["yaw_rad"])
        out.r_wb = premultiply(frame.rot_w_from_ned, r_nb)
        return out

    def points(self, q: np.ndarray, idx: np.ndarray | slice = slice(None)) -> np.ndarray:
        g = self.angles(float(q[0]), float(q[1]), idx)
        d_b = beam_dir_body(g, mounted(self.base, float(q[2]), float(q[3])))
        return self.origins[idx] + np.einsum("nij,nj->ni", self.r_wb[idx], d_b) * self.range_m[idx, None]

    def plane_distances(self, idx: np.ndarray, n: np.ndarray, d: np.ndarray
                        ) -> tuple[Callable[[np.ndarray], np.ndarray], Callable[[np.ndarray], np.ndarray] | None]:
        """The signed distances of the points `idx` from their planes (normals n, offsets d, one per point) as a
        function of the parameters: n . p - d = (n . origin - d) + range (R_wb^T n) . beam_body; and their Jacobian
        (len(idx), 4) in the parameters (offset, scale, tilt, sweep yaw), in closed form (`beam_dot_body_partials`),
        None where the angles' scale has none (the exact re-simulation). The parts the parameters cannot change are
        taken once, so a fit's many trial evaluations cost a dot product per point instead of a rotation."""
        c = np.einsum("ij,ij->i", self.origins[idx], n) - d
        m = np.ascontiguousarray((np.einsum("nij,ni->nj", self.r_wb[idx], n) * self.range_m[idx, None]).T)
        slope = self.angles.scale_slope(idx)

        def at(q: np.ndarray) -> np.ndarray:
            g = self.angles(float(q[0]), float(q[1]), idx)
            return c + beam_dot_body(m, g, mounted(self.base, float(q[2]), float(q[3])))

        def jac(q: np.ndarray) -> np.ndarray:
            g = self.angles(float(q[0]), float(q[1]), idx)
            d_servo, d_tilt, d_yaw = beam_dot_body_partials(m, g, mounted(self.base, float(q[2]), float(q[3])))
            # an angle `mounted` holds at its limit does not move with the parameter
            tilt_free = abs(self.base.tilt_rad + float(q[2])) < MAX_MOUNT_RAD
            yaw_free = abs(self.base.sweep_yaw_rad + float(q[3])) < MAX_MOUNT_RAD
            return np.column_stack([d_servo, d_servo * slope, d_tilt * tilt_free, d_yaw * yaw_free])
        return at, (None if slope is None else jac)



def _trim_inside(j: np.ndarray, r: np.ndarray, window: np.ndarray) -> np.ndarray:
    """j with each plane's band holding no more points inside the building than outside it: the inside's
    farthest (in windows) are dropped. Why: a plane's own points scatter symmetrically about it, and nothing
    but noise lies outside the building, so the outside's count is what the inside holds of the plane's own;
    the excess is the pile's, which lies inside and, on a toe, farther than the noise."""
    out = j.copy()
    for k, sign in enumerate(INSIDE_SIGN):
        m = np.flatnonzero(j == k)
        u = sign * r[m] / window[m]
        inside = m[u > 0]
        n_out = len(m) - len(inside)
        if len(inside) > n_out:
            far = inside[np.argsort(u[u > 0])[n_out:]]
            out[far] = -1
    return out


BAND = 3.0
"""A fit round takes the points within this many windows of their nearest plane."""


def _fit(prob: _Problem, idx: np.ndarray, n: np.ndarray, d: np.ndarray, q0: np.ndarray,
         windows: list[np.ndarray], free: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit the points `idx` over a shrinking window (per-point arrays, m); returns (q, plane index,
    residual m) of the last round, for the points `idx`. Only the `free` parameters move (all by default).
    Each round fits the bands trimmed to no more points inside than outside (`_trim_inside`); the plane index
    returned is the untrimmed assignment, so that the inside-excess guard can still see what a fit holds.

    Each round takes the points within BAND windows of their nearest plane and a bounded-influence
    loss (arctan) of their distance in windows: a point more than about a window off counts for
    little whatever its distance, so the pile surface near a wall or the floor cannot drag the fit,
    and shrinking the window walks the fit from the search's basin into the exact one.
    """
    q = q0.copy()
    free = np.ones(4, dtype=bool) if free is None else free
    lo, hi = BOUNDS[0][free], BOUNDS[1][free]
    for window in windows:
        prob.angles.linearize(float(q[1]))
        w_idx = window[idx]
        j, r_in = nearest_plane(prob.points(q, idx), n, d, BAND * w_idx, prob.allowed(idx))
        j = _trim_inside(j, r_in, w_idx)
        keep = j >= 0
        sel = idx[keep]
        if len(sel) < 50 or not free.any():
            break
        distance, jacobian = prob.plane_distances(sel, n[j[keep]], d[j[keep]])
        wj = w_idx[keep]

        def resid(qf, distance=distance, wj=wj, q=q):
            qq = q.copy()
            qq[free] = qf
            return distance(qq) / wj

        def jac(qf, jacobian=jacobian, wj=wj, q=q):
            qq = q.copy()
            qq[free] = qf
            return jacobian(qq)[:, free] / wj[:, None]

        q = q.copy()
        # One BLAS thread: the solver's products with a tall, four-column Jacobian are too small to share, and a
        # threaded OpenBLAS on a busy two-core machine spent more time handing them off than computing them.
        with one_blas_thread():
            q[free] = least_squares(resid, np.clip(q[free], lo, hi), jac="2-point" if jacobian is None else jac,
                                    loss="arctan", f_scale=1.0, bounds=(lo, hi),
                                    x_scale=np.full(int(free.sum()), 0.01), diff_step=1e-6, max_nfev=80).x
    j, r = nearest_plane(prob.points(q, idx), n, d, BAND * windows[-1][idx], prob.allowed(idx))
    return q, j, r


@dataclass(frozen=True)
class DriftNuisance:
    """A smooth drift of the trajectory's position fitted with the mount, and thrown away: a drifting pose (an indoor
    estimate) moves every point of a stretch of flight alike, which a fit of the mount alone cannot explain (it
    refused: the structure stayed decimetres off its planes), while a mount error moves the points of one sweep
    differently by their angle, which a translation cannot take up. Piecewise linear in time with a random-walk
    prior between knots, as `ground.pose_correction`'s. (A heading drift as well was measured and not kept: it took
    up the walls' systematic millimetres, as the pose correction's heading did; docs/design-notes.md.)"""

    knots_s: np.ndarray
    """Knot times (s, the samples' clock), increasing, at least two."""
    step_sigma_m: np.ndarray
    """(3,) the prior's sigma of one knot-to-knot change of x, y, z (m)."""
    abs_sigma_m: np.ndarray
    """(3,) the prior's sigma of each knot's value (m): the largest drift believed."""
    start_m: np.ndarray | None = None
    """(len(knots_s), 3) a second start for the drift (m), beside none: the pose correction's own fit of it, which
    the mount bent but which lies nearer the drift than none does where the structure pins it only loosely (a pile
    that hides the floor). None: the fit starts from no drift only."""

    def __post_init__(self) -> None:
        if self.start_m is not None and np.shape(self.start_m) != (len(self.knots_s), 3):
            raise ValueError(f"the drift's start has shape {np.shape(self.start_m)}, not ({len(self.knots_s)}, 3)")


DRIFT_ROUNDS = 15
"""Gauss-Newton rounds of the mount and the drift together (`_DriftFit.rounds`), each with the points' planes and
weights assigned again; they stop earlier once a round moves nothing by a millimetre."""

HELD_ROUNDS = 60
"""At most this many reweighted rounds of the mount and the drift on planes held (`_DriftFit.held`); they stop once
a round moves the drift by less than a tenth of a millimetre and the mount by less than a microradian."""

HELD_ASSIGNMENTS = 5
"""At most this many times the joint fit is made on planes held (`_fit_with_drift`), each time with the planes
assigned again where it ended; it stops once that moves neither the drift nor the mount (at the structure's median
range) by more than the points' noise. Points at a window's edge change planes, so it does not settle exactly: on a
`vio` flight over pile 2, after the first fit 36, 14, 3, 4, 3 mm of drift at a knot the structure pins loosely and
0.016, 0.002, 0.004 deg of the mount's largest angle."""


class _DriftFit:
    """The mount and a drift of the beams' origins (`DriftNuisance`) fitted together, on the points `idx` of `prob`.
    The drift is piecewise linear on the knots with its random-walk prior; it enters each point's plane distance
    linearly (n . the drift at the point's time), beside the mount's four closed-form columns."""

    def __init__(self, prob: _Problem, idx: np.ndarray, n: np.ndarray, d: np.ndarray, t_s: np.ndarray,
                 drift: DriftNuisance) -> None:
        self.prob, self.idx, self.n, self.d = prob, idx, n, d
        knots = np.asarray(drift.knots_s, dtype=float)
        self.kk, self.ff = knot_basis(t_s, knots)
        self.n_k = n_k = len(knots)
        self.origins = prob.origins.copy()
        diff = sparse.diags([-np.ones(n_k - 1), np.ones(n_k - 1)], [0, 1], shape=(n_k - 1, n_k))
        self.prior = sparse.block_diag([diff.T @ diff / st ** 2 + sparse.eye(n_k) / ab ** 2
                                        for st, ab in zip(drift.step_sigma_m, drift.abs_sigma_m, strict=True)]
                                       ).toarray()
        # the mount's step damped (its bounds); dense, as the normal equations are (`_step`)
        self.p_all = sparse.block_diag([self.prior, sparse.diags(1.0 / BOUNDS[1] ** 2)]).toarray()

    def shift(self, dd: np.ndarray) -> None:
        kk, ff = self.kk, self.ff
        self.prob.origins = self.origins + dd[kk] * (1 - ff)[:, None] + dd[kk + 1] * ff[:, None]

    def place(self, qq: np.ndarray, dd: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        self.shift(dd)
        return self.prob.points(qq, self.idx if idx is None else idx)

    def _prior_loss(self, dd: np.ndarray) -> float:
        x = dd.T.ravel()
        return float(x @ (self.prior @ x))

    def _drift_columns(self, keep: np.ndarray, j: np.ndarray) -> sparse.csr_matrix:
        """(len(keep), 3 n_k) how the points `keep` (indices into self.idx) move off their planes j per metre of the
        drift at each knot and axis (the drift as `delta.T.ravel()`): n . the drift at the point's time."""
        n_k = self.n_k
        k_pt, f_pt, nrm = self.kk[self.idx[keep]], self.ff[self.idx[keep]], self.n[j]
        cols = np.stack([c * n_k + k_pt + e for c in range(3) for e in (0, 1)], axis=1)
        vals = np.stack([nrm[:, c] * (f_pt if e else 1 - f_pt) for c in range(3) for e in (0, 1)], axis=1)
        return sparse.csr_matrix((vals.ravel(), (np.repeat(np.arange(len(keep)), 6), cols.ravel())),
                                 shape=(len(keep), 3 * n_k))

    def _step(self, keep: np.ndarray, j: np.ndarray, r: np.ndarray, w_m: np.ndarray, q: np.ndarray,
              delta: np.ndarray, jacobian: Callable[[np.ndarray], np.ndarray], free: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """One Gauss-Newton step of the arctan loss (its weights at r / w_m) and the prior, for the points `keep`
        (indices into self.idx) on the planes j; the mount's parameters not `free` do not move.

        The normal equations are summed knot interval by knot interval, dense: a point moves with the drift at its
        interval's two knots only, so each interval adds one small block (its six drift columns, the mount's four,
        the residual) where the interval's columns are. The system has three unknowns a knot and the mount's four
        (under a hundred on a survey): solved dense, a step costs half what the sparse products it replaced did,
        which spent most of their time building matrices (docs/design-notes.md)."""
        n_k = self.n_k
        u = r / w_m
        w = 1.0 / (1.0 + u ** 4) / w_m ** 2  # the arctan loss's weight, in m^-2
        pts = self.idx[keep]
        k_pt, f_pt, nrm = self.kk[pts], self.ff[pts], self.n[j]
        y = np.empty((len(keep), 11))
        y[:, 0:6:2] = nrm * (1 - f_pt)[:, None]  # column c * 2 + e: axis c at the interval's knot k + e
        y[:, 1:6:2] = nrm * f_pt[:, None]
        y[:, 6:10] = jacobian(q) * free
        y[:, 10] = r
        order = np.argsort(k_pt, kind="stable")
        k_pt, y, w = k_pt[order], y[order], w[order]
        yw = y * w[:, None]
        m = 3 * n_k + 4
        normal, grad = np.zeros((m, m)), np.zeros(m)
        ends = np.searchsorted(k_pt, np.arange(n_k), side="right")
        start = 0
        base = np.array([c * n_k + e for c in range(3) for e in (0, 1)] + [3 * n_k + i for i in range(4)])
        for k in np.flatnonzero(np.diff(np.r_[0, ends]) > 0):
            end = ends[k]
            block = yw[start:end].T @ y[start:end]
            ix = base + np.r_[np.full(6, k), np.zeros(4, dtype=int)]
            normal[np.ix_(ix, ix)] += block[:10, :10]
            grad[ix] += block[:10, 10]
            start = end
        normal += self.p_all
        normal[3 * n_k:, 3 * n_k:][np.diag_indices(4)] += ~free  # a held parameter's step is 0
        rhs = -grad - self.p_all[:, :3 * n_k] @ delta.T.ravel()
        try:
            step = np.linalg.solve(normal, rhs)
        except np.linalg.LinAlgError:  # singular: no step (the caller stops on a step not finite)
            step = np.full(m, np.nan)
        return step[:3 * n_k].reshape(3, n_k).T, step[3 * n_k:] * free

    def rounds(self, q: np.ndarray, delta: np.ndarray, sigma: np.ndarray, final: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rounds with the planes assigned again each time and the window shrinking to what the data achieve:
        the way from a start into the basin. Returns (q, drift, final window)."""
        prob, idx, n, d = self.prob, self.idx, self.n, self.d
        lo, hi = BOUNDS
        window = np.maximum(sigma, final)

        def loss(qq: np.ndarray, dd: np.ndarray, w_idx: np.ndarray) -> float:
            # the arctan loss over every point (one beyond BAND windows of any plane counts as at BAND), the prior
            u = nearest_plane(self.place(qq, dd), n, d, np.full(len(idx), np.inf), prob.allowed(idx))[1] / w_idx
            return float(np.sum(np.arctan(np.minimum(u * u, BAND ** 2)))) + self._prior_loss(dd)

        for _ in range(DRIFT_ROUNDS):
            prob.angles.linearize(float(q[1]))
            w_idx = window[idx]
            j, r = nearest_plane(self.place(q, delta), n, d, BAND * w_idx, prob.allowed(idx))
            j = _trim_inside(j, r, w_idx)
            keep = np.flatnonzero(j >= 0)
            if len(keep) < 50:
                break
            _, jacobian = prob.plane_distances(idx[keep], n[j[keep]], d[j[keep]])
            d_delta, d_q = self._step(keep, j[keep], r[keep], w_idx[keep], q, delta, jacobian, np.ones(4, bool))
            if not (np.all(np.isfinite(d_delta)) and np.all(np.isfinite(d_q))):
                break
            before, scale = loss(q, delta, w_idx), 1.0
            while scale > 1.0 / 64 and loss(np.clip(q + scale * d_q, lo, hi), delta + scale * d_delta, w_idx) > before:
                scale /= 2.0
            q, delta = np.clip(q + scale * d_q, lo, hi), delta + scale * d_delta
            jj, r_all = nearest_plane(self.place(q, delta), n, d, BAND * w_idx, prob.allowed(idx))
            kappa = robust_rms(r_all[jj >= 0] / np.maximum(sigma[idx][jj >= 0], 1e-9))
            final = np.maximum(kappa * sigma, 0.002)
            window = np.maximum(sigma, np.minimum(window, final))
            if scale * np.abs(d_delta).max() < 1e-3 and np.all(scale * np.abs(d_q) < 1e-5):
                break
        return q, delta, final

    def held(self, q: np.ndarray, delta: np.ndarray, window: np.ndarray, sub: np.ndarray | None = None,
             free: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The mount and the drift at the minimum of the arctan loss with each point's plane held as assigned at
        the start (in `window`; trimmed as `_fit` trims), by reweighted Gauss-Newton with a line search: without
        the planes changing, it converges. Why: the rounds assign the planes again each time, and where a pile
        hides the floor a tilt and an along-track drift trade places between rounds (a `flow` flight over pile 2:
        the tilt still moving 0.1-0.2 deg a round after 15, the drift 0.2-0.5 m), and the mount fitted alone on
        the drift where they stopped moved the tilt 0.5 deg further (2.2 -> 2.7 deg, true 2.0) and the volume by
        4 pp. sub: only these of the points (indices into self.idx; the standard errors' groups); free: the
        mount's parameters that move (all by default)."""
        prob, n, d = self.prob, self.n, self.d
        idx = self.idx if sub is None else self.idx[sub]
        free = np.ones(4, dtype=bool) if free is None else free
        lo, hi = BOUNDS
        prob.angles.linearize(float(q[1]))
        w_idx = window[idx]
        j, r = nearest_plane(self.place(q, delta, idx), n, d, BAND * w_idx, prob.allowed(idx))
        j = _trim_inside(j, r, w_idx)
        on = np.flatnonzero(j >= 0)
        if len(on) < 50:
            return q, delta
        keep = on if sub is None else sub[on]
        jk, wk = j[on], w_idx[on]
        # With the planes held, the drift moves each point off its plane linearly (its drift columns): both it and
        # the undrifted distances are made once, not at every trial step.
        a_d = self._drift_columns(keep, jk)
        self.shift(np.zeros_like(delta))
        dist, jacobian = prob.plane_distances(idx[on], n[jk], d[jk])
        if jacobian is None:
            self.shift(delta)
            return q, delta

        def at(qq: np.ndarray, dd: np.ndarray) -> np.ndarray:
            return dist(qq) + a_d @ dd.T.ravel()

        def loss(qq: np.ndarray, dd: np.ndarray) -> float:
            u = at(qq, dd) / wk
            return float(np.sum(np.arctan(u * u))) + self._prior_loss(dd)

        for _ in range(HELD_ROUNDS):
            d_delta, d_q = self._step(keep, jk, at(q, delta), wk, q, delta, jacobian, free)
            if not (np.all(np.isfinite(d_delta)) and np.all(np.isfinite(d_q))):
                break
            before, scale = loss(q, delta), 1.0
            while scale > 1.0 / 1024 and loss(np.clip(q + scale * d_q, lo, hi), delta + scale * d_delta) > before:
                scale /= 2.0
            q, delta = np.clip(q + scale * d_q, lo, hi), delta + scale * d_delta
            if scale * np.abs(d_delta).max() < 1e-4 and np.all(scale * np.abs(d_q) < 1e-6):
                break
        self.shift(delta)
        return q, delta


def _fit_with_drift(prob: _Problem, idx: np.ndarray, n: np.ndarray, d: np.ndarray, q: np.ndarray, sigma: np.ndarray,
                    final: np.ndarray, t_s: np.ndarray, drift: DriftNuisance
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, _DriftFit, np.ndarray]:
    """The mount and the drift (`DriftNuisance`) fitted together: Gauss-Newton rounds on the points near a plane,
    weighted by the arctan loss as `_fit` is, the window shrinking to what the data achieve (`_DriftFit.rounds`), then
    the two together on the planes held to convergence (`_DriftFit.held`). A round whose full step makes the loss
    worse (a point changed planes, the model bent) takes a shorter one. The rounds start from no drift and, when the
    nuisance has one, from its start too; the fit that puts more points within the smaller of their final windows of a
    plane is kept (measured: from no drift alone, a flight over a pile that hides the floor ended in a minimum 2.8 cm
    off the planes, from the pose correction's drift within 0.5 cm). Leaves `prob`'s beam origins drifted by the
    fitted drift. Returns (q, plane index, residual, final window) as `estimate_mount`'s own fit does, the fit and
    the drift."""
    fit = _DriftFit(prob, idx, n, d, t_s, drift)
    starts = [np.zeros((fit.n_k, 3))]
    if drift.start_m is not None and np.all(np.isfinite(drift.start_m)):  # a start is a hint: a broken one is skipped
        starts.append(np.asarray(drift.start_m, dtype=float))
    fits = [fit.rounds(q.copy(), start.copy(), sigma, final) for start in starts]
    common = np.minimum.reduce([f for _, _, f in fits])
    agree = []
    for qq, dd, _ in fits:
        fit.shift(dd)
        agree.append(_agreeing(prob, qq, n, d, common, idx))
    q, delta, final = fits[int(np.argmax(agree))]
    # moved: by more than the points' noise, the drift itself or the mount at the structure's median range
    noise_m, reach_m = float(np.median(final[idx])), float(np.median(prob.range_m[idx]))
    for _ in range(HELD_ASSIGNMENTS):
        q_held, delta_held = fit.held(q, delta, final)
        moved = max(np.abs(delta_held - delta).max(), np.abs(q_held - q).max() * reach_m) > noise_m
        q, delta = q_held, delta_held
        if not moved:
            break
    j, r = nearest_plane(fit.place(q, delta), n, d, BAND * final[idx], prob.allowed(idx))
    return q, j, r, final, fit, delta


def _implied_shifts(prob: _Problem, n: np.ndarray, d: np.ndarray,
                    max_shift_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """How far each beam must turn in its sweep plane (square mount) for its range to end on each
    plane, the turn nearest the logged angle: (shift rad, solvable), both (N, 5).

    With the beam [0, sin g, cos g] in the body, a point's signed distance from plane k is
    c + r (a sin g + b cos g) (c: the beam origin's distance, a and b: the body's y and z axes
    along the plane's normal), zero at g = asin(-c / (r hypot(a, b))) - atan2(b, a) or pi minus that.
    """
    a = np.einsum("nj,kj->nk", prob.r_wb[:, :, 1], n)
    b = np.einsum("nj,kj->nk", prob.r_wb[:, :, 2], n)
    c = prob.origins @ n.T - d
    x = -c / (prob.range_m[:, None] * np.maximum(np.hypot(a, b), 1e-12))
    root = np.arcsin(np.clip(x, -1.0, 1.0))
    phi = np.arctan2(b, a)
    g = prob.gamma[:, None]
    s1 = (root - phi - g + math.pi) % (2 * math.pi) - math.pi
    s2 = (math.pi - root - phi - g + math.pi) % (2 * math.pi) - math.pi
    shift = np.where(np.abs(s1) <= np.abs(s2), s1, s2)
    return shift, (np.abs(x) <= 1.0) & (np.abs(shift) <= max_shift_rad)


def _search(prob: _Problem, n: np.ndarray, d: np.ndarray) -> tuple[float, float] | None:
    """The servo (offset, scale) most structure points agree on, the boresight taken square: a vote
    (a Hough transform) over the whole plausible range, so the fit starts in the right basin wherever
    the mount is, whatever the pile hides.

    Each point and plane give the beam angle that would put the point on that plane; a point truly
    on it says offset = that angle minus the servo's angle at the trial scale. For every trial scale
    the offsets are histogrammed (SEARCH_RESOLUTION_RAD bins, two merged so a peak on a bin edge is
    whole): the structure points of the true mount pile into one bin, pile points and wrong planes
    spread. The scale step moves the angles across the sweep by two bins at most, so the true peak
    is never stepped over. Returns None when no point could lie on any plane.
    """
    lo, hi = BOUNDS
    max_shift = hi[0] + hi[1] * float(np.max(np.abs(prob.gamma))) + SEARCH_RESOLUTION_RAD
    shift, ok = _implied_shifts(prob, n, d, max_shift)
    rows, cols = np.nonzero(ok)
    if len(rows) == 0:
        return None
    votes = shift[rows, cols]
    nodes = np.arange(lo[1], hi[1] + 1e-9, SEARCH_SCALE_NODE)
    moved = np.stack([prob.angles.exact(float(x))[rows] - prob.gamma[rows] for x in nodes])
    span = float(np.ptp(prob.gamma))
    step = 2.0 * SEARCH_RESOLUTION_RAD / max(span, SEARCH_RESOLUTION_RAD)
    n_bins = math.ceil(2.0 * hi[0] / SEARCH_RESOLUTION_RAD) + 1
    top = 2.0 * hi[0] / SEARCH_RESOLUTION_RAD  # |offset| < hi[0]: a bin coordinate in (0, top)
    scales = np.arange(lo[1], hi[1] + 1e-9, step)
    ks = np.clip(((scales - lo[1]) // SEARCH_SCALE_NODE).astype(np.int64), 0, len(nodes) - 2)
    best = (0, 0.0, 0.0)
    # Node interval by node interval: each vote's bin coordinate at the interval's first node and its change to the
    # next, made once for the interval's scales; a vote in range at neither end nor between is left out of them all.
    for k in np.unique(ks):
        at = (votes - moved[k] - lo[0]) / SEARCH_RESOLUTION_RAD
        per = (moved[k + 1] - moved[k]) / SEARCH_RESOLUTION_RAD
        reach = (np.minimum(at, at - per) < top) & (np.maximum(at, at - per) > 0)
        at, per = at[reach], per[reach]
        for scale in scales[ks == k]:
            t = at - (scale - nodes[k]) / SEARCH_SCALE_NODE * per
            h = np.bincount(t[(t > 0) & (t < top)].astype(np.int64), minlength=n_bins)
            h2 = h[:-1] + h[1:]
            j = int(np.argmax(h2))
            if h2[j] > best[0]:
                best = (int(h2[j]), float(scale), lo[0] + (j + 1) * SEARCH_RESOLUTION_RAD)
    return best[2], best[1]


def _cluster_cov(jac: np.ndarray, u: np.ndarray, cluster: np.ndarray) -> np.ndarray:
    """The parameters' covariance as the fit sees them: residuals u in windows and their tangent jac
    (N, p, per window), the arctan loss's weights (a point a few windows off counts for little, as
    in the fit), and the points of one sweep taken as one draw (a cluster-robust sandwich): a
    sweep's points share its errors, so counting them as independent would overstate how well the
    planes pin the mount. inf on the diagonal for a parameter the points do not move at all."""
    p = jac.shape[1]
    z = u * u
    weight = 1.0 / (1.0 + z * z)  # d arctan(z) / dz: the loss's weight on a squared residual
    info = (jac * weight[:, None]).T @ jac
    bread = np.linalg.pinv(info, rcond=1e-12, hermitian=True)
    _, inv = np.unique(cluster, return_inverse=True)
    score = np.zeros((inv.max() + 1, p))
    np.add.at(score, inv, jac * (weight * u)[:, None])
    cov = bread @ (score.T @ score) @ bread
    dead = np.diag(info) <= 1e-18 * max(float(np.max(np.diag(info))), 1e-300)
    cov[dead, dead] = math.inf
    return cov


def _agreeing(prob: _Problem, q: np.ndarray, n: np.ndarray, d: np.ndarray, window: np.ndarray,
              idx: np.ndarray | slice = slice(None)) -> int:
    """How many points (of idx) lie within their window of a plane with the mount q."""
    prob.angles.linearize(float(q[1]))
    return int(np.count_nonzero(nearest_plane(prob.points(q, idx), n, d, window[idx], prob.allowed(idx))[0] >= 0))


def _jacobian(prob: _Problem, q: np.ndarray, idx: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """d(signed plane distance)/d(parameter) of the points idx (N, 4), central differences."""
    jac = np.empty((len(idx), 4))
    for k in range(4):
        dq = np.zeros(4)
        dq[k] = 1e-5
        moved = prob.points(q + dq, idx) - prob.points(q - dq, idx)
        jac[:, k] = np.einsum("ij,ij->i", moved, normals) / 2e-5
    return jac


def _along(s: np.ndarray, lever_arm_body_m, frame: StorageFrame, boresight: Boresight, n: np.ndarray,
           range_sigma_m: float, range_sigma_rel: float, angle_sigma_rad: float,
           position_sigma_m: float = 0.0) -> np.ndarray | None:
    """(N, 5) whether each sample's stretch of sweep runs along each plane (`ground.plane_stretches`), placed
    with the configured mount. Why: under a degree of pointing noise a plane's window reaches tens of centimetres
    up a pile's toe, and where a pile hides the floor (the paper's pile 2) most points in the floor's were the
    toe's; with them in the fit, 10 of 48 square-mounted Appendix A flights got a false servo offset and scale (up
    to 6 pp of volume). None: the samples' times are not usable (every point may then lie on every plane)."""
    b, sweep_dir = beams(s, lever_arm_body_m, frame, boresight)
    if len(b.t_s) != len(s) or len(s) < 2:
        return None
    return stretches_along(b, sweep_dir, n, range_sigma_m, range_sigma_rel, angle_sigma_rad, 1e-3, position_sigma_m)


def _off_planes(r: np.ndarray, j: np.ndarray, noise: float) -> str | None:
    """Whether the fitted mount leaves the structure (the points with a plane, j >= 0) off its planes, and by how
    much (words); None if it does not. Its residual spread against the data's own noise, read off consecutive samples
    on the same plane (`neighbour_noise_m`): a fit that leaves much more than the noise has explained a pile as a
    wall or a floor. Nor may they stay farther off than the sensor's own datasheet error (`noise`): scattered points
    (no structure in the cloud at all) have neighbours as far apart as anything, so only this tells."""
    noise_m = neighbour_noise_m(j, r)
    floor_m = noise if noise_m is None else min(max(noise_m, 0.001), noise)
    spread_m = robust_rms(r[j >= 0])
    if spread_m > MAX_MISFIT * floor_m:
        return f"their points stay {spread_m * 100:.1f} cm off their planes against {floor_m * 100:.1f} cm of noise"
    return None


def estimate_mount(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, storage: Storage,
                   range_sigma_m: float, range_sigma_rel: float, resim: Resimulated | None = None,
                   boresight: Boresight = SQUARE, angle_sigma_rad: float = 0.0,
                   position_sigma_m: float = 0.0, drift: DriftNuisance | None = None,
                   stretches: np.ndarray | None = None,
                   held: tuple[bool, bool, bool, bool] | None = None) -> MountEstimate:
    """Estimate the servo offset and scale and the boresight from the building (module docstring).

    Args:
        samples: the survey's usable samples (SAMPLE_DTYPE, flags already filtered), in time order.
        lever_arm_body_m, frame, storage: the log header's geometry.
        range_sigma_m, range_sigma_rel: the header's sensor model (1 sigma, short range / relative).
        resim: how the servo was driven (`Resimulated.from_header`), for the exact servo model; None:
            the logged angles scaled and offset.
        boresight: the configured mounting (the header's); the tilt and yaw estimated are deviations from it.
        angle_sigma_rad: the header's pointing error (1 sigma), which a stretch of sweep along a plane may bend by.
        position_sigma_m: the header's position error drawn per pose message (1 sigma), which may bend it too.
        drift: fit the mount jointly with a smooth translation of the trajectory (`DriftNuisance`), for a pose that
            drifts; None: the logged positions are taken as they are. With a drift the estimate is a proposal: the
            checks that judge a correction by the structure's own points (`_misfit_gain`, `_inside_excess`, the
            planes' points' RMS) are not made, since a drift still bends them; the caller keeps the mount only if
            the pose correction on it is then applied, with its own checks (`ground.report`).
        stretches: (N, 5) whether each usable sample's stretch of sweep runs along each plane, placed with this
            boresight and this noise, if the caller has it (the pose correction asks the same: computed once, a
            tenth of each estimate's time); used only when it covers exactly the samples kept here.
        held: the parameters (PARAMS order) to hold as configured rather than estimate (None: none); the rest are
            fitted again without them, beside the drift if there is one.

    Why the walls first: without a drift the mount is fitted on the walls alone, and on the floor too only when the
    walls give no estimate (too few of their points, no parameter pinned, a fit run to a limit) and do not leave the
    structure unexplained. Under a degree of pointing noise, where a pile hides the floor (the paper's pile 2), the
    floor's band still takes in the pile's toe (its stretches of sweep run along the floor within that noise): those
    points pulled an Appendix A flight with the servo 3 deg off to +4.81 deg and a scale of -3.4 %, its volume 4.0
    pp under its square twin's (+3.37 deg on the walls alone, +0.2 pp). The walls pin the offset and the scale through
    the beam's elevation, the tilt and the yaw at the corners (module docstring), so the floor adds little where they
    are seen (docs/design-notes.md, "The mount's plain fit on the walls"). Beside a drift the floor stays: it pins
    the drift's height, which no wall sees.
    """
    finite = np.logical_and.reduce([np.isfinite(samples[f]) for f in
                                    ("range_m", "servo_rad", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad")])
    s = samples[finite & (samples["range_m"] > 0)]
    if len(s) < 1000:
        return not_estimated(f"too few usable samples ({len(s)}) to calibrate from the building")
    n, d = planes(storage)
    along = (stretches if stretches is not None and len(stretches) == len(s) else
             _along(s, lever_arm_body_m, frame, boresight, n, range_sigma_m, range_sigma_rel, angle_sigma_rad,
                    position_sigma_m))
    args = (s, lever_arm_body_m, frame, n, d, range_sigma_m, range_sigma_rel, resim, boresight, drift, held)
    if drift is None and along is not None:
        # The walls alone first; the floor too only where they tell nothing (the docstring's "Why the walls").
        walls = _estimate(*args, along & ~FLOOR_COLUMN)
        if walls.reason is None or walls.unexplained:
            return walls
    return _estimate(*args, along)


FLOOR_COLUMN = np.array([True, False, False, False, False])
"""The floor's column in `stretches_along`'s (N, 5) (`ground.plane_stretches.planes` order)."""


def _estimate(s: np.ndarray, lever_arm_body_m, frame: StorageFrame, n: np.ndarray, d: np.ndarray,
              range_sigma_m: float, range_sigma_rel: float, resim: Resimulated | None, boresight: Boresight,
              drift: DriftNuisance | None, held: tuple[bool, bool, bool, bool] | None,
              along: np.ndarray | None) -> MountEstimate:
    """`estimate_mount` on the usable samples s, each point allowed on the planes along says (None: on any)."""
    stride = max(1, len(s) // MAX_POINTS)
    s = s[::stride]
    prob = _Problem(s, np.asarray(lever_arm_body_m, dtype=float), frame, resim, boresight)
    prob.along = None if along is None else along[::stride]
    rng_m = prob.range_m
    sigma = np.maximum(range_sigma_m, range_sigma_rel * rng_m)  # the header's 1-sigma range error
    idx_all = np.arange(len(s))
    sweep = np.concatenate([[0], np.cumsum(np.diff(s["sweep_dir"].astype(np.int64)) != 0)])
    q0 = np.zeros(4)
    found = _search(prob, n, d)
    start = q0 if found is None else np.array([found[0], found[1], 0.0, 0.0])
    # The search's reach (two bins of offset, interpolation) or the sensor's noise, whichever is more.
    first = np.maximum(sigma, 4.0 * SEARCH_RESOLUTION_RAD * rng_m)
    q, j, r = _fit(prob, idx_all, n, d, start, [first])
    # The last window is what the data achieve, not the datasheet: the structure points' robust spread
    # in sensor sigmas (a simulated or a good sensor beats its datasheet), never under 2 mm.
    kappa = robust_rms(r[j >= 0] / np.maximum(sigma[j >= 0], 1e-9))
    final = np.maximum(kappa * sigma, 0.002)
    windows = [np.maximum(sigma, final), final]
    q, j, r = _fit(prob, idx_all, n, d, q, windows)
    if found is not None and _agreeing(prob, start, n, d, final) > _agreeing(prob, q, n, d, final):
        # The wide first window let the pile drag the fit off what most structure points agree on
        # (seen with a coarser search on pile 2): fit again from the search's mount, narrow at once.
        q, j, r = _fit(prob, idx_all, n, d, start, [final, final])
    joint, delta = None, None
    if drift is not None:
        q, j, r, final, joint, delta = _fit_with_drift(prob, idx_all, n, d, q, sigma, final, s["t_s"].astype(float),
                                                       drift)
        windows = [np.maximum(sigma, final), final]

    def refit(q: np.ndarray, delta: np.ndarray | None, free: np.ndarray):
        """(mount, drift, plane, residual) fitted again with only the free parameters moving, the rest square; beside
        the drift, when there is one."""
        q = np.where(free, q, 0.0)
        if joint is None:
            return delta, *_fit(prob, idx_all, n, d, q, windows, free)
        q, delta = joint.held(q, delta, final, free=free)
        return delta, q, *nearest_plane(joint.place(q, delta), n, d, BAND * final, prob.allowed())

    held = (False,) * 4 if held is None else tuple(bool(h) for h in held)
    free = ~np.array(held)
    if not free.all():
        delta, q, j, r = refit(q, delta, free)
    on = j >= 0
    if np.count_nonzero(on) < 50:
        return not_estimated("the building's floor and walls were not found in the cloud",
                             tuple(int(np.count_nonzero(j == k)) for k in range(5)))
    # Large enough to matter: the point displacement at the median structure range vs the sensor sigma.
    r_med = float(np.median(rng_m[on]))
    g_med = float(np.median(np.abs(prob.gamma[on])))
    reach = np.array([r_med, r_med * g_med, r_med, r_med * math.sin(g_med)])
    noise = max(range_sigma_m, range_sigma_rel * r_med, 0.005)
    # Observability: which parameters the structure seen pins down well enough that a deviation that
    # matters would stand N_SIGNIFICANT standard errors out (their covariance from the fit's tangent
    # and residuals, sweeps as draws). The tangent is taken at a square boresight and a level vehicle:
    # a tilt or yaw seen only at second order (through its cosine, on the floor and the walls beside
    # the track) is seen in size but neither in sign nor apart from the other, and one seen only
    # through the vehicle's roll and pitch rests on a few degrees of wobble whose own errors are alike.
    # Every parameter that fails is held square at once (one at a time, the tilt and yaw that were
    # weak together each looked fine alone, and a yaw took up a tilt's cosine), then the rest is
    # fitted again and checked again.
    level = prob.level()
    while True:
        k_on = idx_all[on]
        jac = _jacobian(level, np.array([q[0], q[1], 0.0, 0.0]), k_on, n[j[on]]) / final[on, None]
        cov = np.full((4, 4), math.inf)
        cov[np.ix_(free, free)] = _cluster_cov(jac[:, free], r[on] / final[on], sweep[on])
        pinned = np.sqrt(np.maximum(np.diag(cov), 0.0)) * reach * N_SIGNIFICANT
        weak = free & ~(pinned < noise)
        if not weak.any():
            break
        free &= ~weak
        if not free.any():
            # Weak because the structure stays off its planes (the spread the covariance is read from is a drift's
            # bending, not the noise) is the unexplained case, not a building that shows the mount too little: a
            # LiDAR tilted 2 deg under a `vio` drift over pile 2 was refused so and never fitted beside the drift.
            off = None if drift is not None else _off_planes(r, j, noise)
            counts = tuple(int(np.count_nonzero(j == k)) for k in range(5))
            return not_estimated("the floor and walls seen constrain none of the mounting's parameters well "
                                 "enough to tell a deviation that matters" + ("" if off is None else f" ({off})"),
                                 counts, unexplained=off is not None)
        delta, q, j, r = refit(q, delta, free)  # the drift still fitted beside the mount, if there is one
        on = j >= 0
    counts = tuple(int(np.count_nonzero(j == k)) for k in range(5))
    at_bound = free & (np.isclose(q, BOUNDS[0], rtol=0, atol=1e-6) | np.isclose(q, BOUNDS[1], rtol=0, atol=1e-6))
    if at_bound.any():
        return not_estimated("the floor and walls in the cloud fit no plausible mounting (the estimate ran to "
                             f"its limit on {', '.join(n for n, b in zip(PARAMS, at_bound, strict=True) if b)})",
                             counts)
    # Does the mounting model explain the structure (`_off_planes`)? Not with a drift beside the mount: its nuisance
    # is a translation on the knots, and what it cannot follow (a heading's drift, the part of a downward
    # rangefinder's height that follows the pile within a knot) leaves the planes' points off them however right the
    # mount; the pose correction on the mount proposed judges them, with a heading of its own (a `flow` flight with
    # the servo 3 deg off: the joint fit found +2.99 deg and left the walls 0.9 cm off against 0.3 cm of noise;
    # refused here, the report kept neither and read 13.9 % low).
    off = None if drift is not None else _off_planes(r, j, noise)
    if off is not None:
        return not_estimated(f"the mounting model does not explain the floor and walls seen ({off})", counts,
                             unexplained=True)
    matters = free & (np.abs(q) * reach > noise)
    # Standard errors: the same fit on every 8th sweep (whole sweeps share their errors); only needed
    # when something is large enough to matter (a square mount, the usual case, skips them).
    se = np.full(4, math.nan)
    if matters.any():
        group = sweep % N_GROUPS
        if joint is None:
            ests = [_fit(prob, idx_all[group == k], n, d, q, windows[-1:], free)[0] for k in range(N_GROUPS)]
        else:
            # each group's mount with the drift fitted beside it too: held at the whole fit's, the drift's share of
            # a parameter it trades with (a tilt, an along-track drift) did not show in the spread, and a sweep
            # yaw of -0.7 deg on a square one stood out as significant
            ests = [joint.held(q, delta, final, sub=np.flatnonzero(group == k), free=free)[0]
                    for k in range(N_GROUPS)]
            joint.shift(delta)
        se = np.where(free, np.std(np.array(ests), axis=0, ddof=1) / math.sqrt(N_GROUPS), math.nan)
    applied = tuple(bool(m and abs(v) > N_SIGNIFICANT * e) for v, e, m in zip(q, se, matters, strict=True))
    # The same points, on the same planes, before the correction: what it changed.
    r0 = np.einsum("ij,ij->i", prob.points(q0, idx_all[on]), n[j[on]]) - d[j[on]]
    rms_square, rms_fitted = robust_rms(r0), robust_rms(r[on])
    refused, lever_change = None, None
    if any(applied) and drift is None:
        # Every point's distance from its nearest plane with and without the correction, so the points
        # either mount puts on the structure count (not only those the fitted one does).
        prob.angles.linearize(0.0)
        r_square = nearest_plane(prob.points(q0), n, d, final, prob.allowed())[1]
        j_square = nearest_plane(prob.points(q0), n, d, BAND * final, prob.allowed())[0]
        gain, gain_se = _misfit_gain(r_square / final, r / final, sweep)
        inside, inside_se = _inside_excess(j, r, sweep)
        inside_square, _ = _inside_excess(j_square, r_square, sweep)
        if not gain > N_SIGNIFICANT * gain_se:
            applied = (False,) * 4
            refused = ("not applied: it does not bring the floor and walls closer to their planes by more than the "
                       f"noise (mean squared distance {gain:+.3f} +- {gain_se:.3f} noise sigmas squared)")
        elif inside > N_SIGNIFICANT * inside_se and inside > inside_square:
            applied = (False,) * 4
            refused = ("not applied: it holds the planes with points inside the building (of the points near a "
                       f"plane, {inside * 100:.1f} +- {inside_se * 100:.1f} % more inside than outside, "
                       f"{inside_square * 100:.1f} % without it), where a plane's own noise is symmetric and only "
                       "the pile is inside")
        elif (lever := lever_alternative(prob, idx_all[on], n[j[on]], r0, final[on]))[1] <= rms_fitted:
            # A lever arm entered off moves every point by one vector in the body, which none of the four parameters
            # is: the fit takes the nearest of them (a sideways error of 5 cm under the datasheet's noise was taken
            # for a servo scale of -1.3 %, a 162 m³ pile read 32 % low; docs/design-notes.md). A correction is kept
            # only where it explains the structure better than such a translation does.
            dx, dy, dz = (100.0 * v for v in lever[0])
            applied = (False,) * 4
            if float(np.linalg.norm(lever[0])) > noise:  # a change that matters, as a parameter's must (`matters`)
                lever_change = tuple(float(v) for v in lever[0])
            refused = (f"not applied: the lever arm moved by {dx:+.1f}, {dy:+.1f}, {dz:+.1f} cm (forward, right, down) "
                       f"puts the floor and walls' own points as close to their planes ({lever[1] * 100:.2f} cm RMS "
                       f"against {rms_fitted * 100:.2f} cm with the correction)"
                       + (": check the LiDAR's lever arm (`pilescan-ground report --lever-arm X Y Z` takes another)"
                          if lever_change is not None else ", a change within the sensor's noise"))
        elif not rms_fitted < rms_square:
            # A real mount error puts the structure off its planes by its size, and its correction brings the
            # same points back; a fit that leaves its own plane points as far off as the square mount does
            # (a lockstep Appendix A flight of pile 2: 3 deg and -5 % "significant", 13.07 -> 13.08 cm, Ve
            # 0.9 -> 5.4 %) has found a trade between parameters, not an error.
            applied = (False,) * 4
            refused = ("not applied: it leaves the floor and walls' own points as far off their planes "
                       f"({rms_fitted * 100:.2f} cm RMS against {rms_square * 100:.2f} cm with the mount as "
                       "configured)")
    return MountEstimate(tuple(float(v) for v in q), tuple(float(v) for v in se), applied, counts,
                         rms_square, rms_fitted, observable=tuple(bool(f) for f in free), refused=refused,
                         lever_change_m=lever_change, with_drift=drift is not None, held=held)


def lever_alternative(prob: _Problem, idx: np.ndarray, normals: np.ndarray, r_square: np.ndarray,
                      window_m: np.ndarray) -> tuple[np.ndarray, float]:
    """The change of the lever arm (body forward, right, down, m) that best puts the points idx back on their planes
    (normals, one a point) from their distances r_square under the mount as configured, and the robust RMS it leaves.

    A point's distance from its plane moves by n . R_wb dl for a lever arm moved by dl, so this is a linear fit of
    three numbers, made robust as the mount's is (a Cauchy weight at the fit's window: the pile's points near a plane
    count for little): `ground.pose_correction.lever_shift` with the down component and no prior."""
    return lever_shift(prob.r_wb[idx], normals, r_square, window_m, prior_m=None, n_axes=3)


def _misfit_gain(before: np.ndarray, after: np.ndarray, sweep: np.ndarray) -> tuple[float, float]:
    """(gain, its standard error): how much closer a correction brings the points to the building's planes,
    as the mean drop of their squared distance from the nearest plane in noise units (before, after: each
    point's distance in final windows, bounded at BAND as in the fit, so a pile point far from any plane
    counts alike either way), and how much that varies from sweep to sweep (a sweep's points one draw,
    as in `_cluster_cov`: the noise of the gain, measured from the data).

    Why: under noise the fit can be biased (the pile's points near a wall or the floor are all on its
    inside, a one-sided contamination of the plane's band, and the band is wider the noisier the data),
    and a bias is as consistent from sweep group to sweep group as a real error, so the estimate's own
    significance does not tell them apart. What does: a real mount error has put the structure off its
    planes and its correction brings it back by the error's size, while a biased fit of a square mount
    moves the structure's points off their planes to gain a few pile points."""
    drop = np.minimum(before * before, BAND * BAND) - np.minimum(after * after, BAND * BAND)
    if len(drop) < 2:
        return 0.0, math.inf
    gain = float(np.mean(drop))
    _, inv = np.unique(sweep, return_inverse=True)
    per_sweep = np.bincount(inv, weights=drop - gain)
    return gain, float(math.sqrt(np.sum(per_sweep * per_sweep)) / len(drop))


def _inside_excess(j: np.ndarray, r: np.ndarray, sweep: np.ndarray) -> tuple[float, float]:
    """(excess, its standard error): of the points in a plane's band (j: plane index, -1 outside every
    band; r: signed distance), the share more inside the building than outside it, and how much that
    varies from sweep to sweep (a sweep's points one draw).

    Why: a plane's own points scatter symmetrically about it at the true mount (the range noise does),
    the pile's are all inside. A fit that a pile next to the planes has biased (the false corrections on
    noisy flights) holds pile points in the bands from the inside and pushes the planes' own out of
    them: the excess inside stands out. A real correction brings the planes' own points back to both
    sides."""
    on = j >= 0
    if np.count_nonzero(on) < 2:
        return 0.0, math.inf
    side = np.sign(INSIDE_SIGN[j[on]] * r[on])
    excess = float(np.mean(side))
    _, inv = np.unique(sweep[on], return_inverse=True)
    per_sweep = np.bincount(inv, weights=side - excess)
    return excess, float(math.sqrt(np.sum(per_sweep * per_sweep)) / len(side))


PLANE_SETS = ("floor", "walls beside the track", "walls facing the track", "all")
"""The plane sets of `plane_set_errors`: a wall is beside the track while the vehicle heads within
BESIDE_RAD of it (the straight legs), else it faces the track (the turns at the corners)."""
BESIDE_RAD = math.radians(5.0)


def plane_set_errors(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, storage: Storage,
                     est: MountEstimate, resim: Resimulated | None = None) -> dict[str, tuple[int, np.ndarray]]:
    """The observability analysis, for the record: what each set of planes alone pins down.

    At the estimate, the structure points within three fit residuals (never under 2 mm) of a plane,
    split by PLANE_SETS; for each set, the points and the four parameters' standard errors (rad,
    fraction) from those points alone (the estimator's cluster-robust sandwich; inf: not constrained).
    """
    s = samples[np.isfinite(samples["range_m"]) & (samples["range_m"] > 0)]
    s = s[::max(1, len(s) // MAX_POINTS)]
    prob = _Problem(s, np.asarray(lever_arm_body_m, dtype=float), frame, resim)
    n, d = planes(storage)
    q = np.array(est.values, dtype=float)
    prob.angles.linearize(float(q[1]))
    window = 3.0 * max(est.rms_after_m, 0.002)
    j, r = nearest_plane(prob.points(q), n, d, np.full(len(s), window))
    on = np.flatnonzero(j >= 0)
    jac = _jacobian(prob, q, on, n[j[on]]) / window
    u = r[on] / window
    sweep = np.concatenate([[0], np.cumsum(np.diff(s["sweep_dir"].astype(np.int64)) != 0)])[on]
    along = np.abs(np.einsum("ij,ij->i", prob.r_wb[on][:, :, 0], n[j[on]]))  # the track's direction on the normal
    wall = j[on] > 0
    masks = (j[on] == 0, wall & (along < math.sin(BESIDE_RAD)), wall & (along >= math.sin(BESIDE_RAD)),
             np.ones(len(on), dtype=bool))
    out = {}
    for name, m in zip(PLANE_SETS, masks, strict=True):
        se = (np.sqrt(np.maximum(np.diag(_cluster_cov(jac[m], u[m], sweep[m])), 0.0)) if m.sum() > 4
              else np.full(4, math.inf))
        out[name] = (int(m.sum()), se)
    return out


def apply_mount(samples: np.ndarray, est: MountEstimate, resim: Resimulated | None,
                base: Boresight = SQUARE) -> tuple[np.ndarray, Boresight]:
    """The samples with the servo angles the applied estimate gives, and the beam's boresight (the
    configured one, base, plus the applied deviations). Nothing applied: the samples themselves and base."""
    offset, scale, boresight = est.correction(base)
    if offset == 0.0 and scale == 0.0:
        return samples, boresight
    out = samples.copy()
    out["servo_rad"] = ServoAngles(samples, resim)(offset, scale)
    return out, boresight


def describe(est: MountEstimate, base: Boresight = SQUARE) -> str:
    """One line for the report: what was found and applied (angles in degrees; the boresight's as
    deviations from the configured one, base)."""
    names = ("servo offset", "servo scale", "boresight tilt", "sweep-plane yaw")
    parts = []
    for name, v, e, a in zip(names, est.values, est.std_errors, est.applied, strict=True):
        if a and est.given:
            parts.append(f"{name} {v * 100:+.2f} %" if name == "servo scale" else f"{name} {math.degrees(v):+.2f} deg")
        elif a:
            parts.append(f"{name} {v * 100:+.2f} +- {e * 100:.2f} %" if name == "servo scale"
                         else f"{name} {math.degrees(v):+.2f} +- {math.degrees(e):.2f} deg")
    on_top = "" if base.square else (
        f" on top of the configured boresight ({math.degrees(base.tilt_rad):+.2f} deg tilt, "
        f"{math.degrees(base.sweep_yaw_rad):+.2f} deg sweep-plane yaw)")
    if est.given:
        return (f"the mount as given (--mount) applied in place of the self-calibration from the building: "
                f"{', '.join(parts)}{on_top}")
    held = [name for name, o, h in zip(names, est.observable, est.held, strict=True) if not (o or h)]
    chosen = [name for name, h in zip(names, est.held, strict=True) if h]
    drift = ("; fitted together with the pose's drift, as the mount alone did not explain the floor and walls (a "
             "drift bends them)" if est.with_drift else "")
    return (f"self-calibration from the building applied: {', '.join(parts)}{on_top} (structure points off their "
            f"planes: {est.rms_before_m * 100:.1f} -> {est.rms_after_m * 100:.1f} cm RMS){drift}"
            + (f"; held square, as the structure seen does not constrain it: {', '.join(held)}" if held else "")
            + (f"; held as configured, as the flight is explained as well without them: {', '.join(chosen)}"
               if chosen else ""))
