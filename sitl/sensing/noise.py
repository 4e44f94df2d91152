"""The sensor noise math (`firmware_py.core.sensor_noise` says which model and why), as pure functions on
arrays: the batch sampler calls them on a whole flight, the emulated devices and the MAVLink autopilot
on one sample or one message at a time (`RangeNoiser`, `PoseNoiser`), so both paths carry the same errors.

- Ranges: `measured_ranges` (true range and incidence -> what the sensor reports, NaN for no return;
  not quantised: `quantise` does that, as each device does its own).
- Servo: `angle_errors`, added to the TRUE beam (the shaft wobbles about where the firmware's model
  puts it; the firmware logs its model).
- Pose: `pose_errors`, one draw per autopilot pose message; `pose_errors_at` carries them to the
  sample times as the payload's pose buffer does (the two messages on either side, interpolated), so
  the batch path logs what the payload would.

Every function takes its own `numpy.random.Generator`; `noise_streams(seed)` gives independent ones
per error source, so turning one source on does not change another's draws.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np

from firmware_py.core.sensor import RangefinderSpec, ReturnModel
from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel

STREAMS = ("range", "dropout", "servo", "attitude", "position")


def noise_streams(seed: int | list[int]) -> dict[str, np.random.Generator]:
    """Independent generators, one per error source (`STREAMS`), from one seed."""
    children = np.random.SeedSequence(seed).spawn(len(STREAMS))
    return {name: np.random.default_rng(s) for name, s in zip(STREAMS, children, strict=True)}


def datasheet_sigma_m(range_m: np.ndarray, spec: RangefinderSpec) -> np.ndarray:
    """sigma(r) = max(range_sigma_m, range_sigma_rel r): the datasheet's accuracy as 1 sigma."""
    return np.maximum(spec.range_sigma_m, spec.range_sigma_rel * np.abs(np.asarray(range_m, dtype=float)))


def dropout_probability(range_m: np.ndarray, cos_incidence: np.ndarray, spec: RangefinderSpec,
                        returns: ReturnModel) -> np.ndarray:
    """P(no return): 0 up to (1 - ramp) of the effective range, rising linearly to 1 at it
    (`ReturnModel`: the rated range times sqrt(rho cos i / rho_ref)). Non-finite range: 1."""
    r = np.asarray(range_m, dtype=float)
    c = np.clip(np.asarray(cos_incidence, dtype=float), 0.0, 1.0)
    r_eff = returns.effective_range_m(spec.max_range_m, c)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = (r / np.where(r_eff > 0, r_eff, np.nan) - (1.0 - returns.dropout_ramp_rel)) / returns.dropout_ramp_rel
    return np.where(np.isfinite(p), np.clip(p, 0.0, 1.0), 1.0)


def measured_ranges(true_range_m: np.ndarray, noise: SensorNoise, rngs: dict[str, np.random.Generator],
                    cos_incidence: np.ndarray | float = 1.0) -> np.ndarray:
    """What the rangefinder reports for these true ranges (NaN: no return), before quantisation.

    none: the true range. datasheet: + bias + N(0, sigma(r)), and a no-return drawn with
    `dropout_probability`. appendix-a: + N(0, 2.5 cm). A true range that is already NaN (nothing
    within the max range) stays NaN. Draws one normal and (datasheet) one uniform per range.
    """
    r = np.asarray(true_range_m, dtype=float)
    if noise.model is SensorNoiseModel.NONE:
        return r.copy()
    if noise.model is SensorNoiseModel.APPENDIX_A:
        return r + rngs["range"].normal(0.0, noise.appendix_a.range_sigma_m, r.shape)
    spec, returns = noise.spec, noise.returns
    out = r + returns.bias_m + rngs["range"].normal(0.0, 1.0, r.shape) * datasheet_sigma_m(r, spec)
    drop = rngs["dropout"].random(r.shape) < dropout_probability(r, np.broadcast_to(cos_incidence, r.shape), spec,
                                                                  returns)
    return np.where(drop, np.nan, out)


def quantise(range_m: np.ndarray, resolution_m: float) -> np.ndarray:
    """The sensor's range quantum (round to nearest)."""
    r = np.asarray(range_m, dtype=float)
    return np.round(r / resolution_m) * resolution_m if resolution_m > 0 else r


def angle_errors(n: int | tuple[int, ...], sigma_rad: float, rng: np.random.Generator) -> np.ndarray:
    """Servo angle errors N(0, sigma): the true shaft minus what the firmware believes."""
    return rng.normal(0.0, sigma_rad, n) if sigma_rad > 0 else np.zeros(n)


def pose_errors(n: int, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) pose errors N(0, sigma), one row per autopilot message (attitude rad, or position m)."""
    return rng.normal(0.0, sigma, (n, 3)) if sigma > 0 else np.zeros((n, 3))


def pose_errors_at(t_s: np.ndarray, period_s: float, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(len(t_s), 3) pose errors at the sample times, as the payload logs them: one `pose_errors` draw per
    message at k period_s, and at each sample the two messages on either side interpolated to it, as the
    payload's pose buffer does (`firmware_py.pose`: a sample waits for the pose after it).
    e(t) = (1 - f) e_k + f e_(k+1), f = t / period - k in [0, 1): white message noise comes out smoothed,
    2/3 of sigma^2 on average (sd 0.82 sigma), never more than sigma."""
    t = np.asarray(t_s, dtype=float)
    if sigma <= 0 or len(t) == 0:
        return np.zeros((len(t), 3))
    k0 = math.floor(float(t.min()) / period_s) - 1
    n = math.floor(float(t.max()) / period_s) - k0 + 2
    knots = pose_errors(n, sigma, rng)
    u = t / period_s - k0 + 1e-9  # a sample stamped with a message (to rounding) has that message
    i = np.clip(np.floor(u).astype(int), 0, n - 2)
    f = np.clip(u - i, 0.0, 1.0)[:, None]
    return knots[i] * (1.0 - f) + knots[i + 1] * f


class RangeNoise(Protocol):
    """What an emulated rangefinder asks of a noise model: the reported range (None: no return)."""

    def measure(self, range_m: float) -> float | None: ...


class RangeNoiser:
    """`measured_ranges` one sample at a time, for the emulated rangefinders: `measure(r, cos_i)` gives
    the reported range (None: no return). `incidence` is asked for the cosine when none is given
    (the simulated world caches its last ray's)."""

    def __init__(self, noise: SensorNoise, rngs: dict[str, np.random.Generator],
                 incidence: Callable[[], float] | None = None) -> None:
        self.noise, self.rngs, self.incidence = noise, rngs, incidence

    def measure(self, range_m: float | None, cos_incidence: float | None = None) -> float | None:
        if range_m is None or not math.isfinite(range_m):
            return None
        if cos_incidence is None:
            cos_incidence = self.incidence() if self.incidence is not None else 1.0
        r = float(measured_ranges(np.array([range_m]), self.noise, self.rngs, cos_incidence)[0])
        return r if math.isfinite(r) else None


class PoseNoiser:
    """`pose_errors` one message at a time, for the autopilot's ATTITUDE and LOCAL_POSITION_NED."""

    def __init__(self, noise: SensorNoise, rngs: dict[str, np.random.Generator]) -> None:
        self.noise, self.rngs = noise, rngs

    def attitude(self) -> tuple[float, float, float]:
        e = pose_errors(1, self.noise.attitude_sigma_rad, self.rngs["attitude"])[0]
        return float(e[0]), float(e[1]), float(e[2])

    def position(self) -> tuple[float, float, float]:
        e = pose_errors(1, self.noise.position_sigma_m, self.rngs["position"])[0]
        return float(e[0]), float(e[1]), float(e[2])


class ServoNoiser:
    """`angle_errors` one sample at a time: added to the emulated servo's true shaft angle."""

    def __init__(self, noise: SensorNoise, rngs: dict[str, np.random.Generator]) -> None:
        self.sigma, self.rng = noise.servo_sigma_rad, rngs["servo"]

    def error(self) -> float:
        return float(angle_errors(1, self.sigma, self.rng)[0])
