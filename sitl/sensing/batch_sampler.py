"""Batch sample path: whole-flight LiDAR samples from a trajectory, in one vectorised pass.

The same math functions the payload firmware uses per sample (servo waveform eq. 1, beam
geometry eqs. 3-6) are applied to arrays here, then the world is ray traced once for all beams.
"""

from __future__ import annotations

import numpy as np

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame, beam_rays_w
from firmware_py.core.samplelog import SAMPLE_DTYPE, SampleFlags
from firmware_py.core.sensor import LIDARLITE_V3_NO_RETURN_M, RangefinderSpec
from firmware_py.core.sensor_noise import SensorNoise
from firmware_py.core.servo_model import ServoCalibration, modelled_sweep
from firmware_py.core.waveform import Waveform
from sitl.sensing.noise import angle_errors, measured_ranges, noise_streams, pose_errors_at, quantise
from sitl.vehicle.ideal_plant import Trajectory
from sitl.world.raycast import World


def sample_flight(traj: Trajectory, waveform: Waveform, world: World, lidar: RangefinderSpec,
                  lever_arm_body_m, frame: StorageFrame, servo: ServoCalibration | None = None,
                  servo_t0_s: float = 0.0, noise: SensorNoise | None = None,
                  seed: int | list[int] = 0, pose_error: np.ndarray | None = None,
                  servo_gain: float = 1.0, servo_offset_rad: float = 0.0,
                  boresight: Boresight = SQUARE) -> np.ndarray:
    """Records (SAMPLE_DTYPE) of a LiDAR on the swept servo along a trajectory.

    Ideal sensing: the pose is the true pose (age 0), the range is the true range quantised to
    the sensor resolution; no echo within the max range reads as the sensor's 1 cm and is flagged
    NO_RETURN. The servo follows eq. (1) exactly, or, given a calibration, the modelled shaft of a
    servo driven as the payload drives it from time servo_t0_s (the same functions the payload
    uses, so the two paths can be compared sample for sample).

    With `noise` (`firmware_py.core.sensor_noise`), the errors of `sitl.sensing.noise`, drawn from
    `noise_streams(seed)` (a draw is part of the experiment): the true beam is off the logged servo
    angle by the servo error; the range is what the sensor reports (noise, bias, no returns); the
    logged pose carries the autopilot's pose errors, one draw per pose message, interpolated.

    A mount that is not what the log says (the mounting's faults, `sitl.faults.injector.MOUNT_FAULTS`): the
    true shaft maps the same pulses to servo_gain * the calibrated angle + servo_offset_rad (with a servo
    model, its slew acting on the true angle, as the firmware's emulated servo does), and the beam leaves at
    the true boresight; the log keeps the angle the payload believes, as the firmware's does.

    `pose_error` (N, 4) [dn, de, dd, dyaw] at the sample times: the indoor estimator's error
    (`sitl.sensing.pose_drift`), added to the logged pose as the autopilot reports it; the beam stays true.
    """
    mounted = servo_gain != 1.0 or servo_offset_rad != 0.0
    if servo is None:
        gamma = waveform.angle(traj.t_s)
        beam = servo_gain * gamma + servo_offset_rad if mounted else gamma
    else:
        gamma = modelled_sweep(waveform, servo, traj.t_s - servo_t0_s)
        beam = (modelled_sweep(waveform, servo, traj.t_s - servo_t0_s, gain=servo_gain, offset_rad=servo_offset_rad)
                if mounted else gamma)
    n = len(traj.t_s)
    rngs = noise_streams(seed) if noise is not None and noise.active else None
    beam = beam if rngs is None else beam + angle_errors(n, noise.servo_sigma_rad, rngs["servo"])
    origins, dirs = beam_rays_w(traj.pos_ned_m, traj.roll_rad, traj.pitch_rad, traj.yaw_rad, beam,
                                lever_arm_body_m, frame, boresight)
    hits = world.cast(origins, dirs, max_range_m=lidar.max_range_m)
    r = hits.range_m
    if rngs is not None:
        r = measured_ranges(r, noise, rngs, hits.cos_incidence)
    r = quantise(r, lidar.resolution_m)
    no_ret = ~np.isfinite(r)
    rec = np.zeros(n, dtype=SAMPLE_DTYPE)
    rec["t_s"] = traj.t_s
    rec["range_m"] = np.where(no_ret, LIDARLITE_V3_NO_RETURN_M, r)
    rec["servo_rad"] = gamma
    rec["sweep_dir"] = waveform.sweep_direction(traj.t_s)
    rec["flags"] = np.where(no_ret, int(SampleFlags.NO_RETURN), 0)
    rec["x_m"], rec["y_m"], rec["z_m"] = traj.pos_ned_m.T
    rec["roll_rad"], rec["pitch_rad"], rec["yaw_rad"] = traj.roll_rad, traj.pitch_rad, traj.yaw_rad
    rec["pose_age_s"] = 0.0
    if pose_error is not None:
        err = np.asarray(pose_error, dtype=float).reshape(n, 4)
        rec["x_m"] += err[:, 0]
        rec["y_m"] += err[:, 1]
        rec["z_m"] += err[:, 2]
        rec["yaw_rad"] = (rec["yaw_rad"] + err[:, 3] + np.pi) % (2 * np.pi) - np.pi
    if rngs is not None and noise.pose_noisy:
        period_s = 1.0 / noise.pose_stream_hz
        att = pose_errors_at(traj.t_s, period_s, noise.attitude_sigma_rad, rngs["attitude"])
        pos = pose_errors_at(traj.t_s, period_s, noise.position_sigma_m, rngs["position"])
        for j, k in enumerate(("roll_rad", "pitch_rad", "yaw_rad")):
            rec[k] += att[:, j]
        for j, k in enumerate(("x_m", "y_m", "z_m")):
            rec[k] += pos[:, j]
    return rec
