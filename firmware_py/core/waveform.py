"""Servo sweep waveform, eqs. (1)-(2) of Alsayed & Nabawy (2022).

    gamma(t)     = gamma_max / asin(C) * asin(C cos(theta)),      theta = d * 2 pi f t + phi0
    gamma_dot(t) = gamma_max / asin(C) * (-2 pi f d C sin(theta)) / sqrt(1 - C^2 cos^2(theta))

C -> 0 gives a sinusoid (the limit gamma_max cos(theta) is used exactly at C = 0), C -> 1 a
triangle. The sweep direction d = +1/-1 runs the waveform forwards or backwards in time, which
with the phase phi0 gives the paper's "initial angular positions" (Fig. 9: 10 phases x 2
directions). Pure, vectorised functions: the payload loop calls them per sample and the batch
sample path calls them on whole arrays, so both are provably the same math.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

N_PHASES = 10
"""Initial positions per sweep direction (the paper's Fig. 9)."""
MAX_FREQUENCY_HZ = 25.0
"""Fastest sweep: half the 50 Hz servo PWM frame rate (a faster one cannot be commanded; the paper's is 0.67 Hz)."""


@dataclass(frozen=True)
class Waveform:
    """A servo sweep.

    Attributes:
        shape_c: C_gamma in [0, 1): 0 sinusoidal, 0.95 the paper's semi-triangular.
        frequency_hz: sweep frequency f.
        amplitude_rad: gamma_max (pi/2 sweeps +-90 deg).
        phase_rad: phi0.
        direction: +1 or -1, the initial sweep direction.
    """

    shape_c: float = 0.95
    frequency_hz: float = 0.67
    amplitude_rad: float = math.pi / 2
    phase_rad: float = 0.0
    direction: int = 1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.shape_c) and 0.0 <= self.shape_c < 1.0):
            raise ValueError(f"waveform shape C_gamma must be in [0, 1), got {self.shape_c}")
        if not (math.isfinite(self.frequency_hz) and 0.0 < self.frequency_hz <= MAX_FREQUENCY_HZ):
            raise ValueError(f"servo frequency must be in (0, {MAX_FREQUENCY_HZ:g}] Hz, got {self.frequency_hz}")
        if not (math.isfinite(self.amplitude_rad) and 0.0 < self.amplitude_rad <= math.pi / 2):
            raise ValueError(f"servo amplitude must be in (0, pi/2] rad, got {self.amplitude_rad}")
        if not math.isfinite(self.phase_rad):
            raise ValueError(f"servo phase must be finite, got {self.phase_rad}")
        if self.direction not in (1, -1):
            raise ValueError(f"sweep direction must be +1 or -1, got {self.direction}")

    @property
    def peak_rate_rad_s(self) -> float:
        """Largest |gamma_dot| over a period (reached at theta = pi/2)."""
        return peak_rate(self.shape_c, self.frequency_hz, self.amplitude_rad)

    def angle(self, t_s: np.ndarray | float) -> np.ndarray:
        return servo_angle(t_s, self.shape_c, self.frequency_hz, self.amplitude_rad, self.phase_rad,
                           self.direction)

    def rate(self, t_s: np.ndarray | float) -> np.ndarray:
        return servo_rate(t_s, self.shape_c, self.frequency_hz, self.amplitude_rad, self.phase_rad,
                          self.direction)

    def sweep_direction(self, t_s: np.ndarray | float) -> np.ndarray:
        """+1 where the angle is increasing, -1 where it is decreasing (0 never returned)."""
        return np.where(self.rate(t_s) >= 0.0, 1, -1).astype(np.int8)

    def sweep_direction_at(self, t_s: float) -> int:
        """`sweep_direction` for one time, in plain floats (the payload asks 500 times a second).
        Eq. (2)'s sign is that of -direction * sin(theta): its other factors are positive."""
        theta = self.direction * 2.0 * math.pi * self.frequency_hz * t_s + self.phase_rad
        return 1 if -self.direction * math.sin(theta) >= 0.0 else -1


def _gain(shape_c: float, amplitude_rad: float) -> float:
    """gamma_max / asin(C) * C, the factor that tends to gamma_max as C -> 0."""
    if shape_c == 0.0:
        return amplitude_rad
    return amplitude_rad * shape_c / math.asin(shape_c)


def servo_angle(t_s, shape_c: float, frequency_hz: float, amplitude_rad: float = math.pi / 2,
                phase_rad: float = 0.0, direction: int = 1) -> np.ndarray:
    """Eq. (1): servo angle gamma [rad] at times t_s [s] (any shape)."""
    theta = direction * 2.0 * np.pi * frequency_hz * np.asarray(t_s, dtype=float) + phase_rad
    if shape_c == 0.0:
        return amplitude_rad * np.cos(theta)
    return amplitude_rad / math.asin(shape_c) * np.arcsin(shape_c * np.cos(theta))


def servo_rate(t_s, shape_c: float, frequency_hz: float, amplitude_rad: float = math.pi / 2,
               phase_rad: float = 0.0, direction: int = 1) -> np.ndarray:
    """Eq. (2): servo angular rate d(gamma)/dt [rad/s] at times t_s [s]."""
    theta = direction * 2.0 * np.pi * frequency_hz * np.asarray(t_s, dtype=float) + phase_rad
    c = np.cos(theta)
    return (_gain(shape_c, amplitude_rad) * (-2.0 * np.pi * frequency_hz * direction) * np.sin(theta)
            / np.sqrt(1.0 - shape_c**2 * c * c))


def peak_rate(shape_c: float, frequency_hz: float, amplitude_rad: float = math.pi / 2) -> float:
    """Peak |gamma_dot| [rad/s]: 2 pi f gamma_max C / asin(C) (pi f gamma_max... at C=0)."""
    return 2.0 * math.pi * frequency_hz * _gain(shape_c, amplitude_rad)


def frequency_for_peak_rate(peak_rate_rad_s: float, shape_c: float,
                            amplitude_rad: float = math.pi / 2) -> float:
    """The f that makes the servo reach a given peak rate (Table 1: 5 rad/s -> 0.67 Hz at C=0.95)."""
    if not (math.isfinite(peak_rate_rad_s) and peak_rate_rad_s > 0):
        raise ValueError(f"peak servo rate must be > 0 rad/s, got {peak_rate_rad_s}")
    f = peak_rate_rad_s / (2.0 * math.pi * _gain(shape_c, amplitude_rad))
    if f > MAX_FREQUENCY_HZ:
        top = peak_rate(shape_c, MAX_FREQUENCY_HZ, amplitude_rad)
        raise ValueError(f"peak servo rate {peak_rate_rad_s:g} rad/s needs a {f:.3g} Hz sweep; at most {top:.0f} rad/s "
                         f"({MAX_FREQUENCY_HZ:g} Hz: a 50 Hz PWM frame cannot command a faster sweep)")
    return f


def initial_position(k: int, n_phases: int = N_PHASES) -> tuple[float, int]:
    """Phase and direction of the k-th of the paper's 2 x n_phases initial servo positions.

    k in [0, n_phases) sweeps one way, [n_phases, 2 n_phases) the other way from the same angles.
    Phases sit at the centres of n_phases equal slices of half a period, so every one of the
    2 n_phases runs starts at a distinct (angle, direction) pair; none starts at a turning point
    where the two directions would coincide.
    """
    if not (0 <= k < 2 * n_phases):
        raise ValueError(f"servo initial position must be 0..{2 * n_phases - 1}, got {k}")
    direction = 1 if k < n_phases else -1
    phase = math.pi * ((k % n_phases) + 0.5) / n_phases
    return phase, direction


def named_waveform(name: str, peak_rate_rad_s: float = 5.0, k: int = 0) -> Waveform:
    """The paper's two waveforms by name, at the given peak servo rate and initial position k."""
    shapes = {"semi-triangular": 0.95, "sinusoidal": 0.0}
    if name not in shapes:
        raise ValueError(f"unknown waveform {name!r}; choose one of {', '.join(shapes)}")
    c = shapes[name]
    phase, direction = initial_position(k)
    return Waveform(shape_c=c, frequency_hz=frequency_for_peak_rate(peak_rate_rad_s, c),
                    phase_rad=phase, direction=direction)
