"""The sweeping servo driver: drives eq. (1) through a PWM output and predicts the shaft angle.

The calibration and the lag + slew model it predicts with are a shared contract
(`firmware_py.core.servo_model`); this module is the part only the drone runs.
"""

from __future__ import annotations

import collections

import numpy as np

from firmware_py.core.servo_model import PWM_FRAME_S, ServoCalibration, ServoModel, command_angles
from firmware_py.core.waveform import Waveform
from firmware_py.hal import PwmOutput


class SweepServo:
    """Drives the servo along the waveform through a PwmOutput and predicts its angle.

    Call `update(t_s)` at least at the PWM frame rate (50 Hz); `angle_at(t_s)` gives the modelled
    angle at any time: the model is advanced, never rewound, and a time before the model's (a reading
    of a late loop's backlog, older than the pulse just sent) is answered from the state kept at each
    of the last `HISTORY` pulses, exactly (the model's solution does not depend on how time is chunked).
    """

    HISTORY = 64
    """Pulses whose state is kept for earlier times: 1.3 s at 50 Hz, beyond any backlog a driver keeps."""

    def __init__(self, pwm: PwmOutput, waveform: Waveform, cal: ServoCalibration | None = None,
                 frame_s: float = PWM_FRAME_S, early_s: float = 1e-12) -> None:
        self.pwm, self.waveform = pwm, waveform
        self.cal = cal or ServoCalibration()
        self.frame_s = frame_s
        self.early_s = early_s
        """How early an update may send the next frame's pulse: a loop whose ticks come at the
        sensor's pace rather than on a grid (the TFMini's frames) sets half its period, so a tick a
        little before the frame boundary does not hold the pulse back a whole tick."""
        self.model = ServoModel(self.cal, float(waveform.angle(0.0)))
        self._t_model = 0.0
        self._target = float(waveform.angle(0.0))
        self._next_cmd_s = 0.0
        self._pulses: collections.deque[tuple[float, float, float]] = collections.deque(
            [(0.0, self.model.angle_rad, self._target)], maxlen=self.HISTORY)  # (t_s, angle then, target after)

    def command_angle(self, t_s: float) -> float:
        return float(command_angles(self.waveform, self.cal, np.array([t_s]), self.frame_s)[0])

    def update(self, t_s: float) -> None:
        """Send a new pulse when a PWM frame is due (the servo only sees one per frame anyway)."""
        if t_s + self.early_s < self._next_cmd_s:
            return
        angle = self.angle_at(t_s)
        self._target = self.command_angle(t_s)
        self.pwm.set_pulse_us(self.cal.pulse_us(self._target))
        self._pulses.append((t_s, angle, self._target))
        self._next_cmd_s = t_s + self.frame_s

    def angle_at(self, t_s: float) -> float:
        if t_s >= self._t_model:
            if t_s > self._t_model:
                self.model.advance(t_s - self._t_model, self._target)
                self._t_model = t_s
            return self.model.angle_rad
        for t_cmd, angle, target in reversed(self._pulses):  # newest first: a backlog is a few pulses old
            if t_cmd <= t_s:
                return ServoModel(self.model.cal, angle).advance(t_s - t_cmd, target)
        return self._pulses[0][1]  # older than all kept: the oldest state known
