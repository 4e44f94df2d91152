"""Indoor pose-estimate error: what an EKF without GNSS reports, as an error on the true pose.

Indoors ArduPilot flies on optical flow + a downward rangefinder (`flow`) or on visual odometry
(`vio`), and its estimate drifts (docs/pose_error.md has the sources and says which numbers are
assumptions). The error e = estimate - truth, in local NED and yaw, is built from:

- horizontal position, driven by the true motion (a velocity sensor's errors integrate):
  * scale: the flow's (or VIO's) scale error s, one draw per flight: e += s * dp;
  * heading: the velocity is rotated into NED with the estimated yaw, off by dpsi: e += dpsi * J dp
    (J: 90 deg to the right), so a heading error bends every leg;
  * drift: a slowly turning velocity-error direction b(t) (first-order Gauss-Markov, |b| RMS =
    drift_rel, correlation time drift_tau_s) times the ground speed: e += b |dp|, about drift_rel of
    the distance flown over a leg;
  * a random walk in time (the hover drift), hover_rw_m_per_sqrt_s per axis;
- heading: a constant gyro-bias residual (one draw per flight) times t, plus a random walk;
- altitude reference: a barometer random walk; for `flow` also the downward rangefinder, which
  measures height above whatever is below (the pile, not the floor): a fraction rangefinder_weight of
  the surface's height below, low-passed with rangefinder_tau_s, makes the vehicle think it is lower
  over the pile.

Deterministic for a seed: every random draw sits on a fixed time grid (KNOT_S), consumed in order,
and the random-walk terms are linear between knots (continuous: no white jumps), so the error at a
time does not depend on how often it is asked for. The motion-driven terms integrate the true
displacement between updates: `PoseDrift.update` is called along the true flight, by the vehicle at
every physics step (it flies on the estimate), or by `pose_error_series` on a recorded trajectory.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, NamedTuple

import numpy as np

HEADER_KEY = "pose_error"
"""The log header's and truth.json's record of the pose-error profile flown."""
SEED_TAG = 0x9053
"""Mixed into the run's seed for the pose-error draws: independent of the sensor noise and faults."""
KNOT_S = 0.1
"""Time grid of the random draws (10 Hz: the random walks are linear between knots)."""
_SQRT_KNOT_S = math.sqrt(KNOT_S)


class PoseErrorProfile(enum.Enum):
    """Which indoor estimator the simulated autopilot flies on."""

    NONE = "none"  # the truth (the SITL as before)
    FLOW = "flow"  # optical flow + downward rangefinder, barometer, gyro heading
    VIO = "vio"  # visual-inertial odometry (T265-like), barometer height


@dataclass(frozen=True)
class DriftParams:
    """One profile's error sizes (1 sigma). Sources and assumptions: docs/pose_error.md."""

    scale_sigma_rel: float
    """Velocity scale error, one draw per flight (flow: uncalibrated FLOW_FXSCALER/FYSCALER; vio: scale)."""
    drift_rel: float
    """RMS of the velocity-error fraction b: horizontal drift per metre flown."""
    drift_tau_s: float
    """Correlation time of b's direction and size."""
    hover_rw_m_per_sqrt_s: float
    """Random walk of the horizontal position in time, per axis."""
    yaw_bias_sigma_rad_s: float
    """Residual gyro bias of the heading (no compass indoors), one draw per flight."""
    yaw_rw_rad_per_sqrt_s: float
    """Random walk of the heading."""
    baro_rw_m_per_sqrt_s: float
    """Random walk of the barometric height (indoor pressure changes, temperature)."""
    rangefinder_weight: float = 0.0
    """Fraction of the height of the surface below that reaches the reported altitude (0: baro only)."""
    rangefinder_tau_s: float = 1.0
    """Time constant with which the EKF's height follows a change of the rangefinder's height."""

    def __post_init__(self) -> None:
        for name, v in asdict(self).items():
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"pose-error parameter {name} must be finite and >= 0, got {v!r}")
        if self.drift_tau_s <= 0 or self.rangefinder_tau_s <= 0:
            raise ValueError("pose-error time constants must be > 0 s")
        if self.rangefinder_weight > 1:
            raise ValueError(f"rangefinder_weight must be 0-1, got {self.rangefinder_weight}")


PROFILES: dict[PoseErrorProfile, DriftParams] = {
    PoseErrorProfile.FLOW: DriftParams(
        scale_sigma_rel=0.02, drift_rel=0.02, drift_tau_s=60.0, hover_rw_m_per_sqrt_s=0.01,
        yaw_bias_sigma_rad_s=math.radians(0.01), yaw_rw_rad_per_sqrt_s=math.radians(0.02),
        baro_rw_m_per_sqrt_s=0.02, rangefinder_weight=0.25, rangefinder_tau_s=1.0),
    PoseErrorProfile.VIO: DriftParams(
        scale_sigma_rel=0.005, drift_rel=0.01, drift_tau_s=60.0, hover_rw_m_per_sqrt_s=0.005,
        yaw_bias_sigma_rad_s=math.radians(0.005), yaw_rw_rad_per_sqrt_s=math.radians(0.02),
        baro_rw_m_per_sqrt_s=0.02),
}
"""The named profiles' parameters (docs/pose_error.md: which are from sources, which assumed)."""


EKF_SOURCES: dict[PoseErrorProfile, dict[str, float]] = {
    # ArduPilot's defaults: GNSS position and velocity, barometer height, compass heading. The truth flown as a
    # vehicle with a good fix would report it.
    PoseErrorProfile.NONE: {"AHRS_EKF_TYPE": 3.0, "EK3_SRC1_POSXY": 3.0, "EK3_SRC1_VELXY": 3.0, "EK3_SRC1_POSZ": 1.0,
                            "EK3_SRC1_YAW": 1.0, "EK3_RNG_USE_HGT": -1.0},
    # Optical flow: no position source, flow velocity, barometer height with the downward rangefinder taken as the
    # height source below 70 % of its range (what the profile's rangefinder term stands for).
    PoseErrorProfile.FLOW: {"AHRS_EKF_TYPE": 3.0, "EK3_SRC1_POSXY": 0.0, "EK3_SRC1_VELXY": 5.0, "EK3_SRC1_POSZ": 1.0,
                            "EK3_SRC1_YAW": 1.0, "EK3_RNG_USE_HGT": 70.0},
    # Visual odometry as ExternalNav for position, velocity and heading; barometer height (ArduPilot's advice for
    # a T265, whose height is the first to go under vibration).
    PoseErrorProfile.VIO: {"AHRS_EKF_TYPE": 3.0, "EK3_SRC1_POSXY": 6.0, "EK3_SRC1_VELXY": 6.0, "EK3_SRC1_POSZ": 1.0,
                           "EK3_SRC1_YAW": 6.0, "EK3_RNG_USE_HGT": -1.0},
}
"""What the simulated autopilot's EKF3 source parameters say for each profile: served over MAVLink as ArduPilot
serves its own (read-only here: the profile, not the parameter, decides the error), and read by the payload into
the log header (`firmware_py.core.pose_source`)."""


def ekf_source_params(profile: PoseErrorProfile) -> dict[str, float]:
    """The EKF3 source parameters the simulated autopilot reports for a profile."""
    return dict(EKF_SOURCES[PoseErrorProfile(profile)])


def profile_params(profile: PoseErrorProfile) -> DriftParams | None:
    """A profile's parameters (None: `none`, no error)."""
    return PROFILES.get(PoseErrorProfile(profile))


class PoseError(NamedTuple):
    """Estimate minus truth: local NED position, m, and yaw, rad."""

    dn_m: float
    de_m: float
    dd_m: float
    dyaw_rad: float


ZERO = PoseError(0.0, 0.0, 0.0, 0.0)

GroundBelow = Callable[[float, float, float], float]
"""(north, east, down) of the vehicle -> height above the floor of the surface straight below it, m."""


def gauss_markov_step(x: np.ndarray, dt_s: float, tau_s: float, sigma: float, w: np.ndarray) -> np.ndarray:
    """One exact step of a first-order Gauss-Markov process of stationary sd sigma (w: standard normals)."""
    a = math.exp(-dt_s / tau_s)
    return a * x + sigma * math.sqrt(1.0 - a * a) * w


def low_pass_step(y: float, x: float, dt_s: float, tau_s: float) -> float:
    """One step of a first-order low pass (exact for x held over dt)."""
    return y + (x - y) * (1.0 - math.exp(-dt_s / tau_s))


def record(profile: PoseErrorProfile, seed: int) -> dict[str, Any] | None:
    """The header's and truth.json's ``pose_error`` (None for ``none``: both stay as they were)."""
    p = profile_params(profile)
    if p is None:
        return None
    return {"profile": PoseErrorProfile(profile).value, "seed": int(seed), "params": asdict(p)}


class PoseDrift:
    """The estimator error along one flight: `update(t, true position, true yaw)` -> `PoseError`.

    Draws on the KNOT_S grid (see the module docstring): per knot, standard normals for the hover walk
    (2), the heading walk (1), the barometer walk (1) and b (2), in that order.
    """

    def __init__(self, params: DriftParams, seed: int | list[int],
                 ground_below: GroundBelow | None = None, ekf_params: dict[str, float] | None = None) -> None:
        self.p = params
        self.ekf_params = dict(ekf_params or {})
        """The EKF source parameters of the estimator this error stands for (`EKF_SOURCES`)."""
        self.rng = np.random.default_rng(np.random.SeedSequence(seed))
        self.scale = float(self.rng.normal(0.0, params.scale_sigma_rel))
        self.yaw_bias_rad_s = float(self.rng.normal(0.0, params.yaw_bias_sigma_rad_s))
        b0 = self.rng.normal(0.0, params.drift_rel / math.sqrt(2.0), 2)
        self.ground_below = ground_below
        self._knots: list[tuple[float, ...]] = []  # per knot: (hover n, hover e, yaw walk, baro walk, b n, b e)
        self._b0 = b0
        # A knot's step, as scalars (the walks' sd per sqrt(s); b's exact Gauss-Markov factors: the same
        # operations, in the same order, as `gauss_markov_step` on arrays, so the same values to the bit).
        self._walk_sd = (params.hover_rw_m_per_sqrt_s, params.hover_rw_m_per_sqrt_s, params.yaw_rw_rad_per_sqrt_s,
                         params.baro_rw_m_per_sqrt_s)
        self._b_a = math.exp(-KNOT_S / params.drift_tau_s)
        self._b_w = params.drift_rel / math.sqrt(2.0) * math.sqrt(1.0 - self._b_a * self._b_a)
        self._k_first = 0  # the knot index of self._knots[0]
        self._t0: float | None = None
        self._t_last = 0.0
        self._p_last = (0.0, 0.0, 0.0)
        self._integrated = [0.0, 0.0]  # motion-driven horizontal error
        self._ground_lp = 0.0
        self.error = ZERO

    def _knot(self, k: int) -> tuple[float, ...]:
        """Knot k's values (drawn, in order, when first needed; only the newest few are kept: time does not
        go back, so a long served flight does not grow this)."""
        while self._k_first + len(self._knots) <= k:
            if not self._knots:
                self._knots.append((0.0, 0.0, 0.0, 0.0, float(self._b0[0]), float(self._b0[1])))
                continue
            z = self.rng.normal(0.0, 1.0, 6).tolist()
            prev = self._knots[-1]
            sq, sd, a, w = _SQRT_KNOT_S, self._walk_sd, self._b_a, self._b_w
            self._knots.append((prev[0] + z[0] * sq * sd[0], prev[1] + z[1] * sq * sd[1],
                                prev[2] + z[2] * sq * sd[2], prev[3] + z[3] * sq * sd[3],
                                a * prev[4] + w * z[4], a * prev[5] + w * z[5]))
            if len(self._knots) > 4:
                del self._knots[0]
                self._k_first += 1
        return self._knots[k - self._k_first]

    def _walks(self, tau_s: float) -> tuple[float, ...]:
        """The knot processes at tau_s since the start, linear between knots."""
        u = max(tau_s, 0.0) / KNOT_S
        k = math.floor(u)
        f = u - k
        a, b = self._knot(k), self._knot(k + 1)
        return tuple(x + (y - x) * f for x, y in zip(a, b, strict=True))

    def update(self, t_s: float, pos_ned_m: tuple[float, float, float]) -> PoseError:
        """The error at t_s, the vehicle truly at pos_ned_m (call along the flight, t_s not decreasing)."""
        n, e, d = float(pos_ned_m[0]), float(pos_ned_m[1]), float(pos_ned_m[2])
        if self._t0 is None:
            self._t0, self._t_last, self._p_last = t_s, t_s, (n, e, d)
            if self.ground_below is not None and self.p.rangefinder_weight > 0:
                self._ground_lp = self.ground_below(n, e, d)
        dt = t_s - self._t_last
        tau = t_s - self._t0
        w = self._walks(tau)
        dyaw = self.yaw_bias_rad_s * tau + float(w[2])
        if dt > 0:
            dn, de = n - self._p_last[0], e - self._p_last[1]
            step = math.hypot(dn, de)
            # scale error, the heading error rotating the velocity (J: 90 deg right), the slow drift b
            self._integrated[0] += self.scale * dn - dyaw * de + float(w[4]) * step
            self._integrated[1] += self.scale * de + dyaw * dn + float(w[5]) * step
            if self.ground_below is not None and self.p.rangefinder_weight > 0:
                self._ground_lp = low_pass_step(self._ground_lp, self.ground_below(n, e, d), dt,
                                                self.p.rangefinder_tau_s)
        self._t_last, self._p_last = t_s, (n, e, d)
        dd = float(w[3]) + self.p.rangefinder_weight * self._ground_lp
        self.error = PoseError(self._integrated[0] + float(w[0]), self._integrated[1] + float(w[1]), dd, dyaw)
        return self.error


def make_drift(profile: PoseErrorProfile, seed: int, ground_below: GroundBelow | None = None) -> PoseDrift | None:
    """The drift of a profile for a run's seed (None: `none`)."""
    p = profile_params(profile)
    return None if p is None else PoseDrift(p, [int(seed), SEED_TAG], ground_below, ekf_source_params(profile))


def pose_error_series(profile: PoseErrorProfile, seed: int, t_s: np.ndarray, pos_ned_m: np.ndarray,
                      ground_below: GroundBelow | None = None) -> np.ndarray:
    """(N, 4) errors [dn, de, dd, dyaw] along a true trajectory (zeros for `none`)."""
    t = np.asarray(t_s, dtype=float)
    out = np.zeros((len(t), 4))
    drift = make_drift(profile, seed, ground_below)
    if drift is None:
        return out
    pos = np.asarray(pos_ned_m, dtype=float)
    for i in range(len(t)):
        out[i] = drift.update(float(t[i]), (pos[i, 0], pos[i, 1], pos[i, 2]))
    return out


def world_ground_below(world, frame) -> GroundBelow:
    """The `GroundBelow` of a simulated building (`sitl.world.raycast.World`, its `StorageFrame`): a ray
    straight down from the vehicle; the floor (0) when it sees nothing (out of range, outside)."""
    down = np.array([0.0, 0.0, -1.0])

    def below(n: float, e: float, d: float) -> float:
        p_w = frame.ned_to_w(np.array([[n, e, d]]))[0]
        r = world.cast_one(p_w, down)
        return max(0.0, float(p_w[2] - r)) if math.isfinite(r) else 0.0
    return below


def error_stats(err: np.ndarray) -> dict[str, float]:
    """RMS and max of the horizontal error, RMS of the vertical and of the heading (deg) of (N, 4) errors."""
    e = np.asarray(err, dtype=float).reshape(-1, 4)
    if len(e) == 0:
        return {"horizontal_rms_m": 0.0, "horizontal_max_m": 0.0, "vertical_rms_m": 0.0, "heading_rms_deg": 0.0}
    h = np.hypot(e[:, 0], e[:, 1])
    return {"horizontal_rms_m": float(np.sqrt(np.mean(h ** 2))), "horizontal_max_m": float(h.max()),
            "vertical_rms_m": float(np.sqrt(np.mean(e[:, 2] ** 2))),
            "heading_rms_deg": float(np.degrees(np.sqrt(np.mean(e[:, 3] ** 2))))}
