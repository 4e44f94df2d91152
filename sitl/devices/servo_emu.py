"""The servo plant: takes PWM pulses like a real servo and moves its shaft (slew limit + lag).

Its true dynamics may differ from the firmware's calibration; that is how a mis-calibrated or
slow servo is simulated.
"""

from __future__ import annotations

import collections

from firmware_py.core.servo_model import ServoCalibration, ServoModel
from firmware_py.hal import Clock


class EmulatedServo:
    """A PwmOutput whose shaft angle can be asked for at any later time."""

    def __init__(self, clock: Clock, true_cal: ServoCalibration | None = None, angle0_rad: float = 0.0) -> None:
        self.clock = clock
        self.cal = true_cal or ServoCalibration()
        self.model = ServoModel(self.cal, angle0_rad)
        self._t_ns = clock.now_ns()
        self._target = angle0_rad
        self.enabled = True
        self.stuck = False  # a fault: the shaft no longer moves (pulses still arrive)
        self.delay_ns = 0  # a fault: dead time before the servo acts on a pulse
        self._pending: collections.deque[tuple[int, float]] = collections.deque()
        self.pulses = 0

    def set_pulse_us(self, pulse_us: float) -> None:
        now = self.clock.now_ns()
        clamped = min(self.cal.max_us, max(self.cal.min_us, pulse_us))  # the servo's mechanical stops
        self.enabled = True
        self.pulses += 1
        if self.delay_ns > 0:
            self._pending.append((now + self.delay_ns, self.cal.angle_rad(clamped)))
            return
        self.angle_at(now)
        self._target = self.cal.angle_rad(clamped)

    def disable(self) -> None:
        self.angle_at(self.clock.now_ns())
        self.enabled = False

    def close(self) -> None:
        self.disable()

    def angle_at(self, t_ns: int) -> float:
        """Shaft angle at t_ns (not before the last query: the plant moves forward only)."""
        while self._pending and self._pending[0][0] <= t_ns:  # delayed pulses take effect in order
            due, target = self._pending.popleft()
            self._advance(due)
            self._target = target
        self._advance(t_ns)
        return self.model.angle_rad

    def _advance(self, t_ns: int) -> None:
        if t_ns > self._t_ns:
            if self.enabled and not self.stuck:
                self.model.advance((t_ns - self._t_ns) * 1e-9, self._target)
            self._t_ns = t_ns
