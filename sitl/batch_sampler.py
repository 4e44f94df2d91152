"""Batch sample path: whole-flight LiDAR samples from a trajectory, in one vectorised pass.

The same math functions the payload firmware uses per sample (servo waveform eq. 1, beam
geometry eqs. 3-6) are applied to arrays here, then the world is ray traced once for all beams.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from firmware_py.drivers.servo import ServoCalibration, modelled_sweep
from firmware_py.frames import StorageFrame, beam_rays_w
from firmware_py.samplelog import SAMPLE_DTYPE, SampleFlags
from firmware_py.servo_waveform import Waveform
from sitl.ideal_plant import Trajectory
from sitl.raycast import LIDAR_MAX_RANGE_M, World

NO_RETURN_READING_M = 0.01
"""What a LIDAR-Lite v3 reads when no echo comes back: 1 cm."""


@dataclass(frozen=True)
class LidarSpec:
    """The single-point LiDAR (defaults: Garmin LIDAR-Lite v3, Table 1 and its datasheet).

    range_sigma_m / range_sigma_rel describe the datasheet accuracy (+-2.5 cm below 5 m, ~1 %
    beyond); they travel in the log header so the ground station can size its tolerances.
    """

    model: str = "Garmin LIDAR-Lite v3"
    rate_hz: float = 500.0
    max_range_m: float = LIDAR_MAX_RANGE_M
    resolution_m: float = 0.01
    range_sigma_m: float = 0.025
    range_sigma_rel: float = 0.01
    beam_divergence_rad: float = 0.008

    def __post_init__(self) -> None:
        for name in ("rate_hz", "max_range_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"LiDAR {name} must be > 0, got {v}")
        if not (np.isfinite(self.resolution_m) and self.resolution_m >= 0):
            raise ValueError(f"LiDAR resolution must be >= 0 m, got {self.resolution_m}")

    def to_dict(self) -> dict:
        return asdict(self)


def sample_flight(traj: Trajectory, waveform: Waveform, world: World, lidar: LidarSpec,
                  lever_arm_body_m, frame: StorageFrame, servo: ServoCalibration | None = None,
                  servo_t0_s: float = 0.0) -> np.ndarray:
    """Records (SAMPLE_DTYPE) of a LiDAR on the swept servo along a trajectory.

    Ideal sensing: the pose is the true pose (age 0), the range is the true range quantised to
    the sensor resolution; no echo within the max range reads as the sensor's 1 cm and is flagged
    NO_RETURN. The servo follows eq. (1) exactly, or, given a calibration, the modelled shaft of a
    servo driven as the payload drives it from time servo_t0_s (the same functions the payload
    uses, so the two paths can be compared sample for sample).
    """
    if servo is None:
        gamma = waveform.angle(traj.t_s)
    else:
        gamma = modelled_sweep(waveform, servo, traj.t_s - servo_t0_s)
    origins, dirs = beam_rays_w(traj.pos_ned_m, traj.roll_rad, traj.pitch_rad, traj.yaw_rad, gamma,
                                lever_arm_body_m, frame)
    r = world.cast(origins, dirs, max_range_m=lidar.max_range_m).range_m
    if lidar.resolution_m > 0:
        r = np.round(r / lidar.resolution_m) * lidar.resolution_m
    no_ret = ~np.isfinite(r)
    rec = np.zeros(len(traj.t_s), dtype=SAMPLE_DTYPE)
    rec["t_s"] = traj.t_s
    rec["range_m"] = np.where(no_ret, NO_RETURN_READING_M, r)
    rec["servo_rad"] = gamma
    rec["sweep_dir"] = waveform.sweep_direction(traj.t_s)
    rec["flags"] = np.where(no_ret, int(SampleFlags.NO_RETURN), 0)
    rec["x_m"], rec["y_m"], rec["z_m"] = traj.pos_ned_m.T
    rec["roll_rad"], rec["pitch_rad"], rec["yaw_rad"] = traj.roll_rad, traj.pitch_rad, traj.yaw_rad
    rec["pose_age_s"] = 0.0
    return rec
