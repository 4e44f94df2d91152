"""Records no working payload could have written: flagged, left out, counted.

A sample log's numbers are only as good as the bytes on the SD card. A servo angle of 1e20 rad, a
range of 300 m from a 40 m sensor or a vehicle 2 km outside the building are not measurements; turned
into points they land anywhere (1e20 rad gave 13,653 m^3 with only a coverage warning). The limits
come from the log header, i.e. from what the payload itself says it drove and carried:

- servo: |gamma| <= amplitude_rad (the eq. (1) waveform in ``servo``) + SERVO_MARGIN_RAD. The logged
  angle is the firmware's model of the sweep it commanded, which never leaves +-amplitude; the margin
  absorbs a model that lags or rounds, not a fault.
- range (samples not flagged NO_RETURN): r <= max_range_m + N_SIGMA sigma_r(max_range_m) + resolution_m
  (``sensor``): the sensor reports nothing farther.
- pose: the vehicle position, in the storage frame, within POSE_MARGIN_M + N_SIGMA position sigmas
  (``pose.position_sigma_m``, or the ``sensor_noise`` record's if larger) of the building box
  (``storage``): the survey flies inside a closed building.

Only samples the cloud would otherwise use are judged (a NO_RETURN sample's range means nothing).
The report counts each cause and warns; the samples' range (and the offending field) become NaN, so
every later stage treats them as unusable without knowing why.

- time (`out_of_time`, every record): the payload stamps its samples from a monotonic clock, so a log's times
  never step back and pause only for a stall. A time that is not finite, a record or two whose time leaves their
  neighbours' by more than OUTLIER_S, and every record outside the log's longest stretch that neither steps back
  nor pauses longer than MAX_GAP_S cannot be placed in the flight: they are removed, not made NaN (every stage
  that works in time, the servo's re-simulation, the pose's knots, the sweeps, would span the jump: a clock
  stepped by a day asked for a 25 GiB matrix).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_py.core.frames import StorageFrame
from firmware_py.core.numbers import is_finite_number
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD
from firmware_py.core.sensor_noise import stated_position_sigma_m
from firmware_py.core.storage import Storage

SERVO_MARGIN_RAD = 0.1
"""Allowance beyond the sweep amplitude (5.7 deg: far above a servo model's rounding, far below a fault's angle)."""
POSE_MARGIN_M = 1.0
"""Allowance beyond the building's walls, floor and roof for the vehicle position, on top of its stated sigma."""
N_SIGMA = 3.0
"""Stated 1-sigma errors allowed beyond a limit."""
OUTLIER_S = 1.0
"""How far a record's time may leave the median of its four neighbours' and its own (a 500 Hz log's neighbours are
milliseconds apart; a stall of the payload moves a whole run of records, which the median follows)."""
MAX_GAP_S = 900.0
"""The longest pause between two records of one flight: a small multirotor's battery (15 min). Longer, the records
on either side are not one flight's."""


@dataclass(frozen=True)
class PlausibilityLimits:
    """What a log's header allows; None for a limit the header cannot state."""

    max_abs_servo_rad: float | None
    max_range_m: float | None
    pose_lo_w_m: tuple[float, float, float]
    pose_hi_w_m: tuple[float, float, float]

    @classmethod
    def from_header(cls, header: dict, storage: Storage, *, servo_margin_rad: float = SERVO_MARGIN_RAD,
                    pose_margin_m: float = POSE_MARGIN_M, n_sigma: float = N_SIGMA) -> PlausibilityLimits:
        servo = header.get("servo") if isinstance(header.get("servo"), dict) else {}
        sensor = header.get("sensor") if isinstance(header.get("sensor"), dict) else {}
        pose = header.get("pose") if isinstance(header.get("pose"), dict) else {}
        amp = _number(servo.get("amplitude_rad"))
        max_servo = amp + servo_margin_rad if amp is not None and amp > 0 else None
        rmax = _number(sensor.get("max_range_m"))
        max_range = None
        if rmax is not None and rmax > 0:
            sigma = max(_number(sensor.get("range_sigma_m")) or 0.0,
                        (_number(sensor.get("range_sigma_rel")) or 0.0) * rmax)
            max_range = rmax + n_sigma * sigma + (_number(sensor.get("resolution_m")) or 0.0)
        try:
            noise_sigma = stated_position_sigma_m(header)
        except ValueError:
            noise_sigma = 0.0  # a malformed record: the report's intake names it (SensorErrorModel)
        m = pose_margin_m + n_sigma * max(0.0, _number(pose.get("position_sigma_m")) or 0.0, noise_sigma)
        hi = (storage.length_m + m, storage.width_m + m, storage.height_m + m)
        return cls(max_servo, max_range, (-m, -m, -m), hi)


def _number(v: object) -> float | None:
    if not is_finite_number(v):
        return None
    return float(v)


@dataclass(frozen=True)
class Implausible:
    """Per-sample masks of the records beyond each limit (among those the cloud would use)."""

    servo: np.ndarray
    range: np.ndarray
    pose: np.ndarray

    @property
    def any(self) -> np.ndarray:
        return self.servo | self.range | self.pose

    def counts(self) -> dict[str, int]:
        return {"servo_angle": int(self.servo.sum()), "range": int(self.range.sum()), "pose": int(self.pose.sum())}


def implausible(samples: np.ndarray, limits: PlausibilityLimits, frame: StorageFrame) -> Implausible:
    """Which records break which limit (module docstring). Non-finite fields are not judged here: the
    cloud already leaves them out."""
    n = len(samples)
    candidate = (samples["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0
    gamma = samples["servo_rad"].astype(float)
    rng = samples["range_m"].astype(float)
    with np.errstate(invalid="ignore", over="ignore"):
        servo = (candidate & np.isfinite(gamma) & (np.abs(gamma) > limits.max_abs_servo_rad)
                 if limits.max_abs_servo_rad is not None else np.zeros(n, bool))
        far = (candidate & np.isfinite(rng) & (rng > limits.max_range_m)
               if limits.max_range_m is not None else np.zeros(n, bool))
        pos = np.column_stack([samples["x_m"], samples["y_m"], samples["z_m"]]).astype(float)
        finite = np.isfinite(pos).all(axis=1)
        out = np.zeros(n, bool)
        if finite.any():
            w = frame.ned_to_w(pos[finite])
            out[finite] = np.any((w < np.asarray(limits.pose_lo_w_m)) | (w > np.asarray(limits.pose_hi_w_m)), axis=1)
    return Implausible(servo, far, out & candidate)


def out_of_time(t_s: np.ndarray) -> np.ndarray:
    """The records whose time cannot be placed in the flight (module docstring: time), a mask."""
    t = np.asarray(t_s, dtype=float)
    bad = ~np.isfinite(t)
    idx = np.flatnonzero(~bad)
    if len(idx) >= 5:
        tt = t[idx]
        med = np.median(np.lib.stride_tricks.sliding_window_view(np.pad(tt, 2, mode="reflect"), 5), axis=1)
        with np.errstate(over="ignore", invalid="ignore"):
            bad[idx[~(np.abs(tt - med) <= OUTLIER_S)]] = True
        idx = np.flatnonzero(~bad)
    if len(idx) > 1:
        with np.errstate(over="ignore", invalid="ignore"):
            step = np.diff(t[idx])
        cut = np.flatnonzero(~((step >= 0) & (step <= MAX_GAP_S)))
        if len(cut):
            starts, ends = np.r_[0, cut + 1], np.r_[cut + 1, len(idx)]
            k = int(np.argmax(ends - starts))  # the longest stretch; the first of equals
            keep = np.zeros(len(idx), bool)
            keep[starts[k]:ends[k]] = True
            bad[idx[~keep]] = True
    return bad


def in_time(t_s: np.ndarray) -> np.ndarray:
    """The times of the records `out_of_time` keeps: what a log's first, last and duration are read from."""
    t = np.asarray(t_s, dtype=float)
    return t[~out_of_time(t)]


def without_implausible(samples: np.ndarray, found: Implausible) -> np.ndarray:
    """A copy in which the implausible records are unusable (NaN range, and NaN in the offending field)."""
    if not found.any.any():
        return samples
    out = samples.copy()
    out["range_m"][found.any] = np.nan
    out["servo_rad"][found.servo] = np.nan
    for k in ("x_m", "y_m", "z_m"):
        out[k][found.pose] = np.nan
    return out
