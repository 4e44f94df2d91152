"""Samples -> point cloud in the storage frame (eqs. 3-6), and removal of walls and roof.

Walls and roof are removed from the storage dimensions in the log header, with a per-point
tolerance derived from the sensor's own error model (also in the header): a point is structure
when it lies within its expected error of a wall or roof plane. No hand-set crop, so the same code
serves any building and any sensor. Isolated range spikes (garbage reads, glitches) are removed
before that, from the time-ordered samples (`ground.despike`), with a threshold derived the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame, beam_dirs_w, beam_frames_w
from firmware_py.core.numbers import is_finite_number
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD
from firmware_py.core.sensor_noise import (
    POSE_STREAM_HZ,
    stated_angle_sigma_rad,
    stated_pose_draw,
    stated_position_sigma_m,
    stated_range_sigma,
)
from firmware_py.core.storage import Storage
from ground.despike import SpikeThreshold, spike_mask
from ground.plane_stretches import wall_stretches
from ground.sweep_check import stuck_sweep_mask

N_SIGMA = 3.0
"""Points within at least N_SIGMA expected errors of a wall or roof plane are taken as structure."""
MAX_ERROR_M = 1000.0
"""A header's 1-sigma range or position error, or range quantum, beyond this is no sensor's (a damaged or
forged header: its square would pass float range in the error terms)."""
ESCAPES_PER_SURVEY = 0.01
"""Structure points a survey may expect to keep by chance (`structure_n_sigma`)."""


def structure_n_sigma(n_points: int, escapes: float = ESCAPES_PER_SURVEY) -> float:
    """The wall/roof tolerance in expected errors for a cloud of n_points: the smallest k >= N_SIGMA at
    which n_points normal errors put, on average, at most `escapes` points beyond k sigma on the inner
    side of a plane. At a fixed 3 sigma 0.13 % escape; of the ~20,000 wall returns of a survey whose
    ranges carry the datasheet's 1 % of range, ~30 points stay metres up the walls, a metre inside,
    and lift the surface by 0.2 m on average (measured: Ve 7.4 % instead of 0.1 %). 60,000 points
    give 5.1 sigma (the 2D/3D binner's 6 covers tens of millions: `ground.binning.N_SIGMA_MANY`)."""
    if n_points <= 0:
        return N_SIGMA
    tail = min(0.5, escapes / n_points)
    return max(N_SIGMA, -NormalDist().inv_cdf(tail))


@dataclass(frozen=True)
class SensorErrorModel:
    """1-sigma errors, as the log header states them (all may be 0 for an ideal simulated sensor)."""

    range_sigma_m: float = 0.0
    range_sigma_rel: float = 0.0
    resolution_m: float = 0.01
    position_sigma_m: float = 0.0
    angle_sigma_rad: float = 0.0  # the beam's pointing error (servo angle and attitude), sensor_noise record
    pose_draw_sigma_m: float = 0.0  # of position_sigma_m, the part one pose message's samples share (sensor_noise)
    pose_stream_hz: float = POSE_STREAM_HZ  # pose messages a second: the samples between two share their draw

    @classmethod
    def from_header(cls, header: dict) -> SensorErrorModel:
        """The model a log header states (``sensor``, ``pose`` and the ``sensor_noise`` record, the larger
        where two state a sigma); ValueError naming the field when one is not a number >= 0."""
        s = header.get("sensor", {}) or {}
        pose = header.get("pose", {}) or {}
        if not isinstance(s, dict) or not isinstance(pose, dict):
            raise ValueError("log header sensor and pose must be JSON objects")
        values = []
        for where, d, name, default, most in (("sensor", s, "range_sigma_m", 0.0, MAX_ERROR_M),
                                              ("sensor", s, "range_sigma_rel", 0.0, 1.0),
                                              ("sensor", s, "resolution_m", 0.01, MAX_ERROR_M),
                                              ("pose", pose, "position_sigma_m", 0.0, MAX_ERROR_M)):
            v = d.get(name, default)
            if not is_finite_number(v) or not 0 <= v <= most:
                raise ValueError(f"log header {where}.{name} must be a number in [0, {most:g}], got {v!r}")
            values.append(float(v))
        # A simulated survey's noise record (firmware_py.core.sensor_noise) may state more than the spec:
        # Appendix A's pose noise, say. The tolerance takes the larger of the two.
        noise_abs, noise_rel = stated_range_sigma(header)
        values[0], values[1] = max(values[0], noise_abs), max(values[1], noise_rel)
        values[3] = max(values[3], stated_position_sigma_m(header))
        draw_m, stream_hz = stated_pose_draw(header)
        return cls(*values, angle_sigma_rad=stated_angle_sigma_rad(header), pose_draw_sigma_m=draw_m,
                   pose_stream_hz=stream_hz)

    def range_sigma(self, range_m: np.ndarray) -> np.ndarray:
        return np.maximum(self.range_sigma_m, self.range_sigma_rel * np.asarray(range_m))


@dataclass(frozen=True)
class Cloud:
    """Points in W with the beam geometry that produced them.

    Attributes:
        points_w: (N, 3) hit points of usable samples.
        dirs_w: (N, 3) unit beam directions.
        range_m: (N,) ranges.
        path_w: (M, 3) vehicle positions of all samples (the flown path).
        n_samples: samples in the log.
        n_excluded: samples flagged unusable (no return, stale pose, ...) or non-finite.
    """

    points_w: np.ndarray
    dirs_w: np.ndarray
    range_m: np.ndarray
    path_w: np.ndarray
    n_samples: int
    n_excluded: int
    n_servo_suspect: int = 0  # of n_excluded: in sweep periods whose ranges show a stuck servo
    n_spikes: int = 0  # of n_excluded: isolated one- or two-sample range spikes (ground.despike)
    sweep_dir: np.ndarray | None = None  # (N,) +1 / -1 per point: which way the servo was sweeping
    t_s: np.ndarray | None = None  # (N,) each point's sample time on the log's clock (the LAS export's time)
    servo_rad: np.ndarray | None = None  # (N,) the servo angle each point was placed with (re-estimated ones too)
    flags: np.ndarray | None = None  # (N,) each point's sample flags (none of EXCLUDE_FROM_CLOUD)


def cloud_from_samples(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame,
                       sweep_period_s: float | None = None, spike_threshold: SpikeThreshold | None = None,
                       boresight: Boresight = SQUARE) -> Cloud:
    """Eqs. (3)-(6) for every usable sample (flags clear of EXCLUDE_FROM_CLOUD, all fields finite).

    With a spike threshold, isolated one- or two-sample range spikes are excluded first
    (`ground.despike`: a range no surface could give between its neighbours'). With the servo's sweep
    period, samples in periods where the ranges do not move like a swept beam's (a stuck servo:
    `ground.sweep_check`) are excluded too: their angles are wrong.
    """
    return posed_beams(samples, lever_arm_body_m, frame, sweep_period_s, spike_threshold).cloud(
        samples["servo_rad"], samples["sweep_dir"], boresight)


@dataclass(frozen=True)
class PosedBeams:
    """One flight's samples with what their poses fix of their beams (`posed_beams`): which are usable, the beams'
    origins and body-to-W rotations. `cloud` places them at any servo angles. Why: the servo's timing search
    (`ground.servo_timing`) places the same samples at a few hundred candidate angles, and the rotations were a
    quarter of each try's cost."""

    samples: np.ndarray
    lever_arm_body_m: np.ndarray
    frame: StorageFrame
    sweep_period_s: float | None
    spike_threshold: SpikeThreshold | None
    usable: np.ndarray
    """(n,) the samples placed: flags clear, fields finite (the servo angle as logged), no spike, no stuck sweep."""
    origins_w: np.ndarray
    rot_w_body: np.ndarray
    path_w: np.ndarray
    n_servo_suspect: int
    n_spikes: int

    def cloud(self, servo_rad: np.ndarray, sweep_dir: np.ndarray, boresight: Boresight = SQUARE) -> Cloud:
        """The cloud of these samples with these servo angles and sweep directions (n, in the samples' own field
        types): `cloud_from_samples` of the samples with those two fields so, to the bit. Angles not finite where the
        logged ones are (no search makes such), and with a sweep period other angles than the logged ones, are placed
        by `cloud_from_samples` itself: the spikes are judged on the usable samples, the stuck sweeps on the angles
        too."""
        s, use = self.samples, self.usable
        gamma = np.asarray(servo_rad)[use].astype(float)
        judged_on_others = (self.sweep_period_s is not None
                            and not np.array_equal(servo_rad, s["servo_rad"], equal_nan=True))
        if judged_on_others or not np.isfinite(gamma).all():
            other = s.copy()
            other["servo_rad"], other["sweep_dir"] = servo_rad, sweep_dir
            return cloud_from_samples(other, self.lever_arm_body_m, self.frame, self.sweep_period_s,
                                      self.spike_threshold, boresight)
        dirs = beam_dirs_w(self.rot_w_body, gamma, boresight)
        rng = s["range_m"][use].astype(float)
        return Cloud(self.origins_w + dirs * rng[:, None], dirs, rng, self.path_w, len(s), int(len(s) - use.sum()),
                     n_servo_suspect=self.n_servo_suspect, n_spikes=self.n_spikes,
                     sweep_dir=np.asarray(sweep_dir)[use], t_s=s["t_s"][use], servo_rad=gamma, flags=s["flags"][use])


def posed_beams(samples: np.ndarray, lever_arm_body_m, frame: StorageFrame, sweep_period_s: float | None = None,
                spike_threshold: SpikeThreshold | None = None) -> PosedBeams:
    """Which samples `cloud_from_samples` places (its docstring), and their beams' origins and rotations."""
    pos = np.column_stack([samples["x_m"], samples["y_m"], samples["z_m"]]).astype(float)
    fields = [samples[k].astype(float) for k in ("roll_rad", "pitch_rad", "yaw_rad", "servo_rad", "range_m")]
    finite = np.isfinite(pos).all(axis=1) & np.logical_and.reduce([np.isfinite(f) for f in fields])
    usable = finite & ((samples["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0) & (samples["range_m"] > 0)
    spikes = np.zeros(len(samples), dtype=bool)
    if spike_threshold is not None and len(samples):
        spikes = spike_mask(samples["t_s"], samples["range_m"], usable, spike_threshold)
        usable &= ~spikes
    suspect = np.zeros(len(samples), dtype=bool)
    if sweep_period_s is not None and len(samples):
        suspect = stuck_sweep_mask(samples["t_s"], samples["range_m"], usable, sweep_period_s,
                                   servo_rad=samples["servo_rad"])
        usable &= ~suspect
    roll, pitch, yaw = (f[usable] for f in fields[:3])
    origins, rot = beam_frames_w(pos[usable], roll, pitch, yaw, lever_arm_body_m, frame)
    path = frame.ned_to_w(pos[np.isfinite(pos).all(axis=1)])
    return PosedBeams(samples, np.asarray(lever_arm_body_m, dtype=float), frame, sweep_period_s, spike_threshold,
                      usable, origins, rot, path, int(suspect.sum()), int(spikes.sum()))


def merge_clouds(clouds: Sequence[Cloud]) -> Cloud:
    """Several flights' clouds of one survey as one (`pilescan-ground report RUN1 RUN2 ...`): their points,
    beams and paths in order, their counts summed. Each was placed, despiked and checked for a stuck servo on
    its own log (those are per flight); a per-point field one of them lacks is dropped for all."""
    if not clouds:
        raise ValueError("no cloud to merge")

    def cat(name: str) -> np.ndarray | None:
        parts = [getattr(c, name) for c in clouds]
        return None if any(p is None for p in parts) else np.concatenate(parts)
    return Cloud(cat("points_w"), cat("dirs_w"), cat("range_m"), cat("path_w"), sum(c.n_samples for c in clouds),
                 sum(c.n_excluded for c in clouds), sum(c.n_servo_suspect for c in clouds),
                 sum(c.n_spikes for c in clouds), cat("sweep_dir"), cat("t_s"), cat("servo_rad"), cat("flags"))


def plane_tolerances_m(cloud: Cloud, err: SensorErrorModel, n_sigma: float | None = None) -> np.ndarray:
    """(N, 3) each point's tolerance along the x, y and z axes (the normals of the walls, floor and roof):
    see `structure_mask`, which takes a point within it of a plane as on that plane."""
    d = cloud.dirs_w
    k = structure_n_sigma(len(cloud.range_m)) if n_sigma is None else n_sigma
    along = k * err.range_sigma(cloud.range_m) + 0.5 * err.resolution_m
    slack = k * err.position_sigma_m + 1e-3
    return along[:, None] * np.abs(d) + slack


def structure_mask(cloud: Cloud, storage: Storage, err: SensorErrorModel, n_sigma: float | None = None) -> np.ndarray:
    """True for points on a wall or the roof, or outside the building (below the floor included), which
    only noise or a sensor glitch puts there.

    A point within both a wall's and the floor's tolerance is the floor's when it lies fewer tolerances
    from the floor than from the wall (the floor along the walls is then seen, a wall's foot is not).
    A point's tolerance along a plane normal n is its range error projected on n,
    k sigma_r(r) |d . n| plus half the range resolution, plus k position sigmas (not the pointing
    error: docs/design-notes.md says why); k is n_sigma, or
    `structure_n_sigma` of the cloud's size (so no wall point escapes by chance in a whole survey).
    """
    p = cloud.points_w
    tol_x, tol_y, tol_z = plane_tolerances_m(cloud, err, n_sigma).T
    # Beside a wall, a point within both the wall's and the floor's tolerance goes to the surface it fits
    # better (its distance in tolerances): the floor along the walls and a pile's toe are seen, a wall's
    # foot stays wall.
    with np.errstate(divide="ignore", invalid="ignore"):
        to_wall = np.minimum.reduce([p[:, 0] / tol_x, (storage.length_m - p[:, 0]) / tol_x,
                                     p[:, 1] / tol_y, (storage.width_m - p[:, 1]) / tol_y])
        to_floor = np.abs(p[:, 2]) / tol_z
    walls = (to_wall <= 1.0) & ~(to_floor < to_wall)
    walls |= beside_walls(cloud, storage, err, only=~walls)
    return (walls | (p[:, 2] >= storage.height_m - tol_z)
            | (p[:, 2] < -tol_z))  # under the floor: a reading no beam could give (a glitch)


def beside_walls(cloud: Cloud, storage: Storage, err: SensorErrorModel, only: np.ndarray | None = None) -> np.ndarray:
    """The points whose stretch of sweep climbs a wall off its plane (`ground.plane_stretches.wall_stretches`): what
    the tolerance above cannot take without taking the pile points beside a wall too (it holds no pointing or
    heading error: docs/design-notes.md), the stretch's history can. None without the points' times. A stretch is
    straight within its range, position and quantum errors, not its pointing error: a pointing error drawn per
    sample (Appendix A's degree) would let a crooked stretch pass, a wall's foot with the pile top beside it (measured
    on the evaluation set: 1,000 points a survey taken, Ve moved up to 4 pp either way); a wall point it displaces is
    left to the surface's outlier test (`ground.smoothing`). only: the points to judge (None: all)."""
    if cloud.t_s is None or cloud.sweep_dir is None or len(cloud.t_s) < 2:
        return np.zeros(len(cloud.points_w), dtype=bool)
    dt = float(np.median(np.diff(cloud.t_s)))
    return wall_stretches(cloud.points_w, cloud.t_s, cloud.sweep_dir, cloud.dirs_w * cloud.range_m[:, None],
                          stretch_sigma_m(cloud, err), storage.length_m, storage.width_m, dt, only)


def stretch_sigma_m(cloud: Cloud, err: SensorErrorModel) -> np.ndarray:
    """Each point's 1-sigma error that a stretch of sweep's straightness is judged by: its range, position and range
    quantum errors, not its pointing error (`beside_walls` says why)."""
    r = cloud.range_m
    return np.sqrt(np.square(err.range_sigma(r)) + err.position_sigma_m**2 + err.resolution_m**2 / 12.0)
