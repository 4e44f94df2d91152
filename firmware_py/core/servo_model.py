"""The servo model: pulse-width calibration, and where a shaft without position feedback is.

A hobby servo has no position feedback, so the angle at a LiDAR sample is a prediction: the
commanded waveform passed through a model of the servo (a first-order lag with a slew-rate
limit, the two numbers a bench calibration gives). The command is issued ahead of the waveform
(lag plus half a PWM frame) so the shaft follows eq. (1) rather than a delayed copy of it; where
the waveform asks for more than the servo's top speed it cannot, and the model says so.

A shared contract: the payload's driver steps `ServoModel`, the SITL's servo plant is the same
model, and the ground station re-simulates a sweep with `modelled_sweep` from the log header's
calibration, so all three agree to rounding.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.waveform import Waveform

PWM_FRAME_S = 0.02
"""A hobby servo's PWM frame (50 Hz): the sweep sends one pulse per frame."""


@dataclass(frozen=True)
class ServoCalibration:
    """Pulse width <-> angle, and the servo's dynamics.

    Attributes:
        center_us: pulse at gamma = 0 (beam straight down).
        us_per_rad: pulse change per radian (positive: larger pulse turns the beam to starboard).
        min_us, max_us: the pulse range the servo accepts.
        slew_rad_s: the servo's top speed (datasheet ~0.2 s/60 deg -> 5.2 rad/s).
        lag_s: time constant of its position loop.
    """

    center_us: float = 1500.0
    us_per_rad: float = 1000.0 / math.pi
    min_us: float = 1000.0
    max_us: float = 2000.0
    slew_rad_s: float = 5.0
    lag_s: float = 0.02

    def __post_init__(self) -> None:
        vals = (self.center_us, self.us_per_rad, self.min_us, self.max_us, self.slew_rad_s, self.lag_s)
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"servo calibration must be finite: {self}")
        if not (500.0 <= self.min_us < self.center_us < self.max_us <= 2500.0):
            raise ValueError(f"servo pulses must satisfy 500 <= min < center < max <= 2500 us, got "
                             f"{self.min_us}, {self.center_us}, {self.max_us}")
        if self.us_per_rad == 0 or self.slew_rad_s <= 0 or self.lag_s < 0:
            raise ValueError(f"servo us_per_rad != 0, slew > 0 and lag >= 0 needed, got {self}")

    def pulse_us(self, angle_rad: float) -> float:
        """Pulse for an angle, clamped to the servo's range."""
        p = self.center_us + angle_rad * self.us_per_rad
        return min(self.max_us, max(self.min_us, p))

    def angle_rad(self, pulse_us: float) -> float:
        return (pulse_us - self.center_us) / self.us_per_rad


class ServoModel:
    """First-order lag with a slew limit, stepped in time: the predicted shaft angle."""

    def __init__(self, cal: ServoCalibration, angle_rad: float = 0.0) -> None:
        self.cal = cal
        self.angle_rad = angle_rad

    def advance(self, dt_s: float, target_rad: float) -> float:
        """Move towards target for dt_s and return the angle (`step_angle`)."""
        self.angle_rad = step_angle(self.angle_rad, dt_s, target_rad, self.cal.slew_rad_s, self.cal.lag_s)
        return self.angle_rad


def step_angle(angle_rad: float, dt_s: float, target_rad: float, slew_rad_s: float, lag_s: float) -> float:
    """The shaft angle dt_s after angle_rad, driven towards target_rad: the exact solution of
    d(err)/dt = -clip(err / lag, +-slew), rate-limited while the error is above slew * lag, exponential
    after. Being exact, it gives the same angle however time is chunked, so the firmware's prediction and
    the SITL's plant agree to rounding. A pure function of plain floats: the batch path steps it once per
    PWM frame, tens of thousands of times a report."""
    if dt_s <= 0:
        return angle_rad
    err = target_rad - angle_rad
    e_sat = slew_rad_s * lag_s
    if err > e_sat or -err > e_sat:
        sign = 1.0 if err >= 0 else -1.0
        t_lin = (abs(err) - e_sat) / slew_rad_s
        if dt_s <= t_lin:
            return angle_rad + sign * slew_rad_s * dt_s
        dt_s -= t_lin
        err = sign * e_sat
    return target_rad - (err * math.exp(-dt_s / lag_s) if lag_s > 0 else 0.0)


def servo_angles(t_s: np.ndarray, cmd_t_s: np.ndarray, cmd_rad: np.ndarray, cal: ServoCalibration,
                 angle0_rad: float = 0.0) -> np.ndarray:
    """Batch version: the modelled angle at times t_s (any order), for commands held from cmd_t_s on.

    The same exact ServoModel solution as the payload's stepping: the state is stepped from command
    to command (one Python step per PWM frame, `command_states`), then every query is advanced from the
    state at the command before it, vectorised (`angles_at`). Being exact, the split does not change the
    angles (to rounding). A command takes effect before a query at the same instant; before the first
    command the shaft rests at angle0_rad.
    """
    return angles_at(t_s, command_states(cmd_t_s, cmd_rad, cal, angle0_rad), cal)


@dataclass(frozen=True)
class CommandStates:
    """The shaft's angle at each command's instant (`command_states`): the part of `servo_angles` stepped in Python,
    a PWM frame at a time, which any number of queries then share (`angles_at`)."""

    cmd_t_s: np.ndarray
    """(m,) the commands' instants, in order."""
    cmd_rad: np.ndarray
    """(m,) the commands, in that order."""
    start_rad: np.ndarray
    """(m,) the shaft's angle at each command's instant."""
    angle0_rad: float
    """Where the shaft rests before the first command."""


def command_states(cmd_t_s: np.ndarray, cmd_rad: np.ndarray, cal: ServoCalibration,
                   angle0_rad: float = 0.0) -> CommandStates:
    """The angle at each command's instant, stepped in plain floats (`servo_angles`: this loop is the cost of a
    re-simulation)."""
    order = np.argsort(np.asarray(cmd_t_s, dtype=float), kind="stable")
    ct = np.asarray(cmd_t_s, dtype=float)[order]
    cr = np.asarray(cmd_rad, dtype=float)[order]
    steps = np.diff(ct, prepend=ct[0] if len(ct) else 0.0).tolist()
    targets = [float(angle0_rad), *cr.tolist()][:len(ct)]  # each step drives towards the command before it
    slew, lag, angle = cal.slew_rad_s, cal.lag_s, float(angle0_rad)
    at_command = []
    for dt, target in zip(steps, targets, strict=True):
        angle = step_angle(angle, dt, target, slew, lag)
        at_command.append(angle)
    return CommandStates(ct, cr, np.array(at_command, dtype=float), float(angle0_rad))


def angles_at(t_s: np.ndarray, states: CommandStates, cal: ServoCalibration) -> np.ndarray:
    """The modelled angle at times t_s (any order) from the states at the commands (`servo_angles`). Commands after
    the last query change nothing: states stepped further than the queries need give the same angles."""
    t = np.asarray(t_s, dtype=float)
    ct = states.cmd_t_s
    out = np.full(len(t), states.angle0_rad)
    k = np.searchsorted(ct, t, side="right") - 1
    after = k >= 0
    if after.any():
        kk = k[after]
        out[after] = _advance(states.start_rad[kk], t[after] - ct[kk], states.cmd_rad[kk], cal)
    return out


def _advance(a: np.ndarray, dt: np.ndarray, target: np.ndarray, cal: ServoCalibration) -> np.ndarray:
    """ServoModel.advance for arrays: slew-limited while the error exceeds slew * lag, then exponential."""
    s, tau = cal.slew_rad_s, cal.lag_s
    err = target - a
    sign = np.where(err >= 0, 1.0, -1.0)
    e_sat = s * tau
    big = np.abs(err) > e_sat
    t_lin = np.where(big, (np.abs(err) - e_sat) / s, 0.0)
    on_slew = big & (dt <= t_lin)
    err_end = np.where(big, sign * e_sat, err)  # the error when the exponential part starts
    dt_exp = np.maximum(dt - t_lin, 0.0)
    decay = np.exp(-dt_exp / tau) if tau > 0 else np.zeros_like(dt_exp)
    angle = np.where(on_slew, a + sign * s * dt, target - err_end * decay)
    return np.where(dt > 0, angle, a)


def command_angles(waveform: Waveform, cal: ServoCalibration, t_s: np.ndarray,
                   frame_s: float = PWM_FRAME_S) -> np.ndarray:
    """Commanded angles at times t_s: the waveform ahead by the servo's lag plus half a PWM frame
    (the average delay of a command held for a frame), clamped to what the pulses can reach."""
    a = waveform.angle(np.asarray(t_s, dtype=float) + cal.lag_s + 0.5 * frame_s)
    pulse = np.clip(cal.center_us + a * cal.us_per_rad, cal.min_us, cal.max_us)
    return (pulse - cal.center_us) / cal.us_per_rad


def modelled_sweep(waveform: Waveform, cal: ServoCalibration, t_s: np.ndarray,
                   frame_s: float = PWM_FRAME_S, gain: float = 1.0, offset_rad: float = 0.0) -> np.ndarray:
    """Batch path: the shaft angle at times t_s of a servo driven as SweepServo drives it (a pulse at
    every frame from t = 0), starting at rest on the waveform's initial angle.

    gain, offset_rad: a shaft whose true angle is gain * the calibrated one + offset_rad (a servo off its
    calibration, as the SITL's mounting faults fly it): the same pulses drive it, so its targets are mapped,
    and its slew limit acts on the true angle, not on the calibrated one."""
    t = np.asarray(t_s, dtype=float)
    return angles_at(t, sweep_states(waveform, cal, t.max() if len(t) else 0.0, frame_s, gain, offset_rad), cal)


def sweep_states(waveform: Waveform, cal: ServoCalibration, until_s: float, frame_s: float = PWM_FRAME_S,
                 gain: float = 1.0, offset_rad: float = 0.0) -> CommandStates:
    """`modelled_sweep`'s states, its pulses from t = 0 to until_s (and one frame on). A pulse is the same whatever the
    horizon (`np.arange` makes each instant from its index), so states to a later horizon answer the same queries to
    the bit: a search over the servo's timing steps them once for all its delays (`ground.servo_timing`)."""
    cmd_t = np.arange(0.0, until_s + frame_s, frame_s)
    cmd = command_angles(waveform, cal, cmd_t, frame_s)
    return command_states(cmd_t, gain * cmd + offset_rad, cal, gain * float(waveform.angle(0.0)) + offset_rad)
