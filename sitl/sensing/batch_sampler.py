"""Batch sample path: whole-flight LiDAR samples from a trajectory, in one vectorised pass.

The same math functions the payload firmware uses per sample (servo waveform eq. 1, beam
geometry eqs. 3-6) are applied to arrays here, then the world is ray traced once for all beams.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from firmware_py.core.frames import StorageFrame, beam_rays_w
from firmware_py.core.samplelog import SAMPLE_DTYPE, SampleFlags
from firmware_py.core.sensor import LIDARLITE_V3_NO_RETURN_M, RangefinderSpec
from firmware_py.core.servo_model import ServoCalibration, modelled_sweep
from firmware_py.core.waveform import Waveform
from sitl.vehicle.ideal_plant import Trajectory
from sitl.world.raycast import World


@dataclass(frozen=True)
class NoiseSpec:
    """Sensor noise of the paper's Appendix A (normal, 1 sigma): LiDAR range 2.5 cm, servo angle 1 deg,
    attitude 0.143 deg (IMU), position 0.113 m. The beam goes where the true pose and shaft point it;
    what is logged (range, servo angle, pose) carries the noise, as on the drone."""

    range_sigma_m: float = 0.025
    servo_sigma_rad: float = float(np.radians(1.0))
    attitude_sigma_rad: float = float(np.radians(0.143))
    position_sigma_m: float = 0.113

    def __post_init__(self) -> None:
        for name, v in asdict(self).items():
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"noise {name} must be finite and >= 0, got {v}")


def sample_flight(traj: Trajectory, waveform: Waveform, world: World, lidar: RangefinderSpec,
                  lever_arm_body_m, frame: StorageFrame, servo: ServoCalibration | None = None,
                  servo_t0_s: float = 0.0, noise: NoiseSpec | None = None,
                  rng: np.random.Generator | None = None) -> np.ndarray:
    """Records (SAMPLE_DTYPE) of a LiDAR on the swept servo along a trajectory.

    Ideal sensing: the pose is the true pose (age 0), the range is the true range quantised to
    the sensor resolution; no echo within the max range reads as the sensor's 1 cm and is flagged
    NO_RETURN. The servo follows eq. (1) exactly, or, given a calibration, the modelled shaft of a
    servo driven as the payload drives it from time servo_t0_s (the same functions the payload
    uses, so the two paths can be compared sample for sample). With `noise`, the logged range, servo
    angle and pose carry Appendix A's noise, drawn from rng (seed it: a draw is part of the experiment).
    """
    if servo is None:
        gamma = waveform.angle(traj.t_s)
    else:
        gamma = modelled_sweep(waveform, servo, traj.t_s - servo_t0_s)
    origins, dirs = beam_rays_w(traj.pos_ned_m, traj.roll_rad, traj.pitch_rad, traj.yaw_rad, gamma,
                                lever_arm_body_m, frame)
    r = world.cast(origins, dirs, max_range_m=lidar.max_range_m).range_m
    n = len(traj.t_s)
    if noise is not None:
        rng = rng if rng is not None else np.random.default_rng(0)
        r = r + rng.normal(0.0, noise.range_sigma_m, n)
    if lidar.resolution_m > 0:
        r = np.round(r / lidar.resolution_m) * lidar.resolution_m
    no_ret = ~np.isfinite(r)
    rec = np.zeros(len(traj.t_s), dtype=SAMPLE_DTYPE)
    rec["t_s"] = traj.t_s
    rec["range_m"] = np.where(no_ret, LIDARLITE_V3_NO_RETURN_M, r)
    rec["servo_rad"] = gamma
    rec["sweep_dir"] = waveform.sweep_direction(traj.t_s)
    rec["flags"] = np.where(no_ret, int(SampleFlags.NO_RETURN), 0)
    rec["x_m"], rec["y_m"], rec["z_m"] = traj.pos_ned_m.T
    rec["roll_rad"], rec["pitch_rad"], rec["yaw_rad"] = traj.roll_rad, traj.pitch_rad, traj.yaw_rad
    rec["pose_age_s"] = 0.0
    if noise is not None:
        rec["servo_rad"] += rng.normal(0.0, noise.servo_sigma_rad, n)
        for k in ("roll_rad", "pitch_rad", "yaw_rad"):
            rec[k] += rng.normal(0.0, noise.attitude_sigma_rad, n)
        for k in ("x_m", "y_m", "z_m"):
            rec[k] += rng.normal(0.0, noise.position_sigma_m, n)
    return rec
