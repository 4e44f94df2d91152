"""The rangefinder's datasheet, once: what the payload writes into the log header, the SITL emulates
and the ground station sizes its tolerances from.

`RangefinderSpec.to_dict()` is the header's ``sensor`` mapping (keys `SENSOR_KEYS`, in that order).
`LIDARLITE_V3` is the Garmin LIDAR-Lite v3 of the paper's Table 1; a different sensor is a different
instance, never a different set of constants scattered across the programs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from enum import Enum
from typing import Any

import numpy as np

from firmware_py.core.numbers import is_finite_number, is_number

SENSOR_KEYS = ("model", "rate_hz", "max_range_m", "resolution_m", "range_sigma_m", "range_sigma_rel",
               "beam_divergence_rad")
"""The header's ``sensor`` keys, in order."""


@dataclass(frozen=True)
class RangefinderSpec:
    """A single-point rangefinder as the survey needs to know it.

    Attributes:
        model: the sensor's name, for the report.
        rate_hz: ranges per second the payload takes.
        max_range_m: farthest range it reports (an echo beyond reads as no return).
        resolution_m: the range quantum.
        range_sigma_m: 1-sigma range error at short range ...
        range_sigma_rel: ... and, as a fraction of the range, beyond (the datasheet's "1 %").
        beam_divergence_rad: full beam divergence.
    """

    model: str
    rate_hz: float
    max_range_m: float
    resolution_m: float
    range_sigma_m: float
    range_sigma_rel: float
    beam_divergence_rad: float

    def __post_init__(self) -> None:
        if not isinstance(self.model, str) or not self.model:
            raise ValueError(f"sensor model must be a non-empty string, got {self.model!r}")
        for name in ("rate_hz", "max_range_m"):
            value = getattr(self, name)
            if not (is_finite_number(value) and value > 0):
                raise ValueError(f"sensor {name} must be a finite number > 0, got {value!r}")
        for name in ("resolution_m", "range_sigma_m", "range_sigma_rel", "beam_divergence_rad"):
            value = getattr(self, name)
            if not (is_finite_number(value) and value >= 0):
                raise ValueError(f"sensor {name} must be a finite number >= 0, got {value!r}")
        for f in fields(self):
            if f.name != "model":
                object.__setattr__(self, f.name, float(getattr(self, f.name)))

    def to_dict(self) -> dict[str, Any]:
        """The header's ``sensor`` mapping (keys `SENSOR_KEYS`)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any) -> RangefinderSpec:
        """Parse a header's ``sensor`` mapping; ValueError naming a missing key or a bad value."""
        if not isinstance(d, dict):
            raise ValueError(f"sensor must be a mapping, got {type(d).__name__}")
        missing = [k for k in SENSOR_KEYS if k not in d]
        if missing:
            raise ValueError(f"sensor lacks {', '.join(missing)}")
        return cls(**{k: d[k] for k in SENSOR_KEYS})

    def with_(self, **changes: Any) -> RangefinderSpec:
        """A copy with some values changed (validated like a new spec)."""
        return replace(self, **changes)


LIDARLITE_V3 = RangefinderSpec(
    model="Garmin LIDAR-Lite v3",
    rate_hz=500.0,  # the paper's Table 1 (the fast preset reaches it)
    max_range_m=40.0,
    resolution_m=0.01,
    range_sigma_m=0.025,  # datasheet: +-2.5 cm below 5 m ...
    range_sigma_rel=0.01,  # ... and ~1 % of the range beyond
    beam_divergence_rad=0.008,
)
"""Garmin LIDAR-Lite v3 (datasheet, and the paper's Table 1)."""

LIDARLITE_V3_NO_RETURN_M = 0.01
"""What a LIDAR-Lite v3 reads when no echo comes back: 1 cm."""

TFMINI_S = RangefinderSpec(
    model="Benewake TFmini-S",
    rate_hz=100.0,  # the factory frame rate (1000/n Hz settable)
    max_range_m=12.0,  # 90 % reflective board, indoors
    resolution_m=0.01,
    range_sigma_m=0.06,  # manual: +-6 cm from 0.1 to 6 m ...
    range_sigma_rel=0.01,  # ... and +-1 % from 6 to 12 m
    beam_divergence_rad=0.035,  # 2 deg field of view
)
"""Benewake TFmini-S (product manual SJ-PM-TFmini-S), the family's most common member and the
sensor of the paper's authors' 2025 flight rig (a TFMini on UART)."""


class Rangefinder(Enum):
    """The rangefinders the payload drives (`--rangefinder`; the config file's ``[payload] rangefinder``).

    The value is the name the user types; `spec` is the datasheet written into the log header.
    """

    LIDARLITE_V3 = "lidarlite-v3"
    TFMINI = "tfmini"

    @property
    def spec(self) -> RangefinderSpec:
        return LIDARLITE_V3 if self is Rangefinder.LIDARLITE_V3 else TFMINI_S

    @property
    def streams(self) -> bool:
        """Whether the part streams readings at its own rate (the TFMini on its UART) rather than
        measuring when triggered (the LIDAR-Lite on I2C): a streaming part paces the payload's loop."""
        return self is Rangefinder.TFMINI

    @classmethod
    def named(cls, name: str) -> Rangefinder:
        """The rangefinder called `name` (ValueError listing the known names)."""
        for r in cls:
            if r.value == name:
                return r
        raise ValueError(f"unknown rangefinder {name!r} (known: {', '.join(r.value for r in cls)})")


@dataclass(frozen=True)
class ReturnModel:
    """When a rangefinder gets an echo at all: the datasheet's rated range and the reflectance it is rated on.

    The received power of an extended diffuse (Lambertian) target falls as rho cos(i) / r^2, so the
    range at which the echo is just detectable scales as sqrt(rho cos(i) / rho_ref) of the rated range.
    The TFMini family's datasheets, which rate two reflectances, are that law or better: at 10 % the
    TF-Luna reaches 2.5 m of its 8 m (the law: 2.7 m), the TFmini 5 m and the TFmini-i 7 m of their
    12 m (the law: 4 m). So the model errs towards losing returns, never towards keeping them.

    Attributes:
        reference_reflectance: the target reflectance the datasheet's max_range_m is rated on.
        target_reflectance: what the survey's surfaces are assumed to reflect in the near infrared; no
            datasheet knows it (concrete and most bulk materials: 0.2-0.5), so it is a stated assumption.
        dropout_ramp_rel: the no-return probability ramps from 0 at (1 - this) of the effective range
            to 1 at the effective range (the datasheets give a rated range, not a detection curve).
        bias_m: a systematic range offset (neither datasheet states one: both give a symmetric accuracy).
    """

    reference_reflectance: float
    target_reflectance: float = 0.3
    dropout_ramp_rel: float = 0.1
    bias_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("reference_reflectance", "target_reflectance"):
            v = getattr(self, name)
            if not (is_number(v) and 0.0 < v <= 1.0):
                raise ValueError(f"{name} must be a number in (0, 1], got {v!r}")
        if not (is_number(self.dropout_ramp_rel) and 0.0 < self.dropout_ramp_rel <= 1.0):
            raise ValueError(f"dropout_ramp_rel must be a number in (0, 1], got {self.dropout_ramp_rel!r}")
        if not (is_finite_number(self.bias_m) and abs(self.bias_m) <= 1.0):
            raise ValueError(f"bias_m must be a finite number within +-1 m, got {self.bias_m!r}")

    def effective_range_m(self, max_range_m: float, cos_incidence: np.ndarray | float = 1.0) -> np.ndarray:
        """The farthest echo at these incidences on the assumed target (inverse-square law above), for one incidence
        or many at once: the one statement of the law, which the simulated dropouts (`sitl.sensing.noise`), the
        mission's range check and the report's echo diagnosis all read."""
        c = np.maximum(np.asarray(cos_incidence, dtype=float), 0.0)
        return max_range_m * np.sqrt(c * self.target_reflectance / self.reference_reflectance)

    def sure_range_m(self, max_range_m: float, cos_incidence: np.ndarray | float = 1.0) -> np.ndarray:
        """The farthest certain echo at these incidences: (1 - dropout_ramp_rel) of the effective range. What a
        mission is planned on (`sitl.missions.range_check`) and what a report judges its samples without an echo by
        (`ground.echo_reach`)."""
        c = np.clip(np.asarray(cos_incidence, dtype=float), 0.0, 1.0)
        return (1.0 - self.dropout_ramp_rel) * self.effective_range_m(max_range_m, c)


def sure_echo_range_m(max_range_m: float, returns: ReturnModel | None,
                      cos_incidence: np.ndarray | float = 1.0) -> np.ndarray:
    """The farthest certain echo at these incidences: `ReturnModel.sure_range_m`, or without a return model (ideal
    sensing, the paper's Appendix A) max_range_m at any incidence."""
    if returns is None:
        return np.full(np.shape(cos_incidence), float(max_range_m))
    return returns.sure_range_m(max_range_m, cos_incidence)


LIDARLITE_V3_RETURNS = ReturnModel(reference_reflectance=0.70)
"""LIDAR-Lite v3: 40 m "with a 70 % reflective target" (operation manual, specifications)."""

TFMINI_S_RETURNS = ReturnModel(reference_reflectance=0.90)
"""TFmini-S: 0.1-12 m "@90% reflectivity" (datasheet SJ-GU-TFmini-S-01 A00, table 1)."""

RETURN_MODELS = {LIDARLITE_V3.model: LIDARLITE_V3_RETURNS, TFMINI_S.model: TFMINI_S_RETURNS}
"""The datasheet return model of each known rangefinder, by `RangefinderSpec.model`."""


def return_model_for(spec: RangefinderSpec) -> ReturnModel:
    """The datasheet return model of spec's sensor; ValueError naming the sensor when none is known."""
    try:
        return RETURN_MODELS[spec.model]
    except KeyError:
        raise ValueError(f"no datasheet return model for {spec.model!r} (known: {', '.join(RETURN_MODELS)})") from None
