"""Where the autopilot's pose came from: its EKF's source parameters, as the log header keeps them.

Every sample is tagged with the autopilot's estimate, and how far that estimate can be trusted depends on what
fed it. ArduPilot's EKF3 says so in its parameters (`EK3_SRC1_POSXY`, `_VELXY`, `_POSZ`, `_YAW`: the primary
source set; `EK3_RNG_USE_HGT`: the downward rangefinder taken as the height source below that percentage of its
range). The payload reads them from the autopilot at start (PARAM_REQUEST_READ) and writes what it was told into
the header's ``autopilot_params``; the ground station reads them back here to say, in the report, what the pose
came from and what that means for the volume:

- a horizontal source that integrates velocity (optical flow, wheel encoders) or odometry (visual odometry as
  ExternalNav) drifts with the distance flown; GNSS and beacons do not (nor motion capture, also ExternalNav);
- a height from the downward rangefinder is the height above whatever is below: over a stockpile, the pile's top,
  not the floor. ArduPilot's own advice is to use it only over a flat floor without clutter.

A shared contract (stdlib only): the names the payload asks for, the codes' meanings, the header key.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from typing import Any

HEADER_KEY = "autopilot_params"
"""The log header's record: {parameter name: value as the autopilot reported it}; absent when none answered."""

EKF_SOURCE_PARAMS: tuple[str, ...] = ("AHRS_EKF_TYPE", "EK3_SRC1_POSXY", "EK3_SRC1_VELXY", "EK3_SRC1_POSZ",
                                      "EK3_SRC1_YAW", "EK3_RNG_USE_HGT")
"""What the payload asks the autopilot for (ArduPilot's names; a PX4 or EKF2 autopilot answers none of them)."""


class HorizontalSource(Enum):
    """EK3_SRCn_POSXY / _VELXY (ArduPilot's AP_NavEKF_Source::SourceXY)."""

    NONE = 0
    GPS = 3
    BEACON = 4
    OPTICAL_FLOW = 5
    EXTERNAL_NAV = 6
    WHEEL_ENCODER = 7


class HeightSource(Enum):
    """EK3_SRCn_POSZ (ArduPilot's SourceZ)."""

    NONE = 0
    BARO = 1
    RANGEFINDER = 2
    GPS = 3
    BEACON = 4
    EXTERNAL_NAV = 6


_WORDS = {
    HorizontalSource.NONE: "none", HorizontalSource.GPS: "GNSS", HorizontalSource.BEACON: "beacons",
    HorizontalSource.OPTICAL_FLOW: "optical flow", HorizontalSource.EXTERNAL_NAV: "external navigation",
    HorizontalSource.WHEEL_ENCODER: "wheel encoders",
    HeightSource.NONE: "none", HeightSource.BARO: "barometer", HeightSource.RANGEFINDER: "downward rangefinder",
    HeightSource.GPS: "GNSS", HeightSource.BEACON: "beacons", HeightSource.EXTERNAL_NAV: "external navigation",
}
_DRIFTING = {HorizontalSource.OPTICAL_FLOW, HorizontalSource.WHEEL_ENCODER}
"""Velocity sources: the position is their integral, so its error grows with the distance flown."""


def number(value: Any) -> float | None:
    """A parameter's value as a finite float; None for anything else (a string, a bool, NaN, an integer too large
    for a float): a header is read, not trusted."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        f = float(value)
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _code(params: Mapping[str, Any], name: str, kind: type[Enum]) -> Enum | None:
    value = number(params.get(name))
    if value is None:
        return None
    try:
        return kind(round(value))
    except ValueError:
        return None


@dataclass(frozen=True)
class PoseSource:
    """The autopilot's pose sources as its parameters state them; None where it did not say (or said a code this
    version does not know)."""

    ekf_type: int | None
    position: HorizontalSource | None
    velocity: HorizontalSource | None
    height: HeightSource | None
    rangefinder_height_pct: float | None
    """EK3_RNG_USE_HGT: the rangefinder is the height source below this percentage of its range; None: off (-1)
    or not said."""

    @classmethod
    def from_params(cls, params: Mapping[str, Any]) -> PoseSource:
        ekf = number(params.get("AHRS_EKF_TYPE"))
        ekf_type = round(ekf) if ekf is not None else None
        rng = number(params.get("EK3_RNG_USE_HGT"))
        rng_pct = rng if rng is not None and rng >= 0 else None
        return cls(ekf_type, _code(params, "EK3_SRC1_POSXY", HorizontalSource),
                   _code(params, "EK3_SRC1_VELXY", HorizontalSource), _code(params, "EK3_SRC1_POSZ", HeightSource),
                   rng_pct)

    @classmethod
    def from_header(cls, header: Mapping[str, Any]) -> PoseSource | None:
        """The header's record read back; None when the log has none (an older payload, or no autopilot answered)."""
        record = header.get(HEADER_KEY)
        if not isinstance(record, Mapping) or not record:
            return None
        return cls.from_params(record)

    @property
    def known(self) -> bool:
        """Whether the parameters say anything: an EKF3 with at least its horizontal and height sources."""
        return self.ekf_type == 3 and self.height is not None and (self.position is not None
                                                                 or self.velocity is not None)

    @property
    def horizontal_drifts(self) -> bool:
        """The horizontal position is integrated velocity (no absolute position source)."""
        return self.position in (None, HorizontalSource.NONE) and self.velocity in _DRIFTING

    @property
    def height_from_rangefinder(self) -> bool:
        """The height is, at least at times, the downward rangefinder's: the height above the pile, over a pile."""
        return self.height is HeightSource.RANGEFINDER or self.rangefinder_height_pct is not None

    @property
    def rangefinder_height_setting(self) -> str | None:
        """The parameter that makes the rangefinder the height source, as "NAME = value" (None: it is not): the
        source itself when EK3_SRC1_POSZ says so, else the switch below EK3_RNG_USE_HGT % of its range."""
        if self.height is HeightSource.RANGEFINDER:
            return f"EK3_SRC1_POSZ = {HeightSource.RANGEFINDER.value}"
        if self.rangefinder_height_pct is not None:
            return f"EK3_RNG_USE_HGT = {self.rangefinder_height_pct:g}"
        return None

    def horizontal_words(self) -> str:
        """What fed the horizontal position, in words."""
        if self.position not in (None, HorizontalSource.NONE):
            if self.velocity not in (None, HorizontalSource.NONE, self.position):
                return f"{_WORDS[self.position]} (velocity: {_WORDS[self.velocity]})"
            return _WORDS[self.position]
        if self.velocity not in (None, HorizontalSource.NONE):
            return f"{_WORDS[self.velocity]} velocity, integrated"
        return "none"

    def describe(self) -> str:
        """One line for the report: what fed the position and the height."""
        if not self.known:
            if self.ekf_type not in (None, 3):
                return f"not stated (AHRS_EKF_TYPE {self.ekf_type}: only EKF3's sources are read)"
            return "not stated by the autopilot"
        horizontal = self.horizontal_words()
        height = _WORDS[self.height]
        if self.rangefinder_height_pct is not None and self.height is not HeightSource.RANGEFINDER:
            height += f", the downward rangefinder below {self.rangefinder_height_pct:g} % of its range"
        return f"position {horizontal}; height {height} (ArduPilot EKF3, source set 1)"
