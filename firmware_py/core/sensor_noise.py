"""Which sensor noise a simulated survey flew with, and its parameters: the log header's ``sensor_noise``.

Three models (`SensorNoiseModel`, `pilescan-sitl fly/serve --sensor-noise`):

- ``none``: ideal sensing (the range quantised to the sensor's resolution, nothing else). No header
  record is written, so a noise-free run's log is what it always was.
- ``datasheet``: the rangefinder's own datasheet (`firmware_py.core.sensor`): range noise
  sigma(r) = max(range_sigma_m, range_sigma_rel r), its bias, its range quantum, and no-returns
  (`ReturnModel`: the rated range shrinks with the target's reflectance and the incidence). Servo
  and pose are exact.
- ``appendix-a``: the paper's Appendix A: range 2.5 cm, servo angle 1 deg, attitude 0.143 deg,
  position 0.113 m (normal, 1 sigma). The servo error moves the true beam; the pose error is on what
  the autopilot reports, one draw per pose message at ``pose_stream_hz``.

The ground station sizes its tolerances from the header: `stated_range_sigma` and
`stated_position_sigma_m` combine the sensor spec with this record (the larger of the two).
The noise math itself lives in the simulator (`sitl.sensing.noise`); this is the contract only.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from enum import StrEnum
from typing import Any

from firmware_py.core.numbers import is_finite_number
from firmware_py.core.sensor import RangefinderSpec, ReturnModel, return_model_for

HEADER_KEY = "sensor_noise"
POSE_STREAM_HZ = 50.0
"""ATTITUDE and LOCAL_POSITION_NED rate the payload asks of the autopilot: one pose error per message."""


class SensorNoiseModel(StrEnum):
    NONE = "none"
    DATASHEET = "datasheet"
    APPENDIX_A = "appendix-a"


@dataclass(frozen=True)
class AppendixANoise:
    """The paper's Appendix A (normal, 1 sigma): LiDAR range, servo angle, attitude (IMU), position."""

    range_sigma_m: float = 0.025
    servo_sigma_rad: float = math.radians(1.0)
    attitude_sigma_rad: float = math.radians(0.143)
    position_sigma_m: float = 0.113

    def __post_init__(self) -> None:
        for name, v in asdict(self).items():
            if not (is_finite_number(v) and v >= 0):
                raise ValueError(f"noise {name} must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class SensorNoise:
    """The noise one survey flew with: the model, the rangefinder it applies to, and the parameters.

    Build with `SensorNoise.of(model, spec)`; `record()` is the header's ``sensor_noise``.
    """

    model: SensorNoiseModel
    spec: RangefinderSpec
    returns: ReturnModel | None = None  # datasheet
    appendix_a: AppendixANoise | None = None  # appendix-a
    pose_stream_hz: float = POSE_STREAM_HZ

    def __post_init__(self) -> None:
        object.__setattr__(self, "model", SensorNoiseModel(self.model))
        if self.model is SensorNoiseModel.DATASHEET and self.returns is None:
            raise ValueError("datasheet noise needs the rangefinder's return model")
        if self.model is SensorNoiseModel.APPENDIX_A and self.appendix_a is None:
            raise ValueError("appendix-a noise needs its sigmas")
        if not (math.isfinite(self.pose_stream_hz) and self.pose_stream_hz > 0):
            raise ValueError(f"pose stream rate must be > 0 Hz, got {self.pose_stream_hz!r}")

    @classmethod
    def of(cls, model: SensorNoiseModel | str, spec: RangefinderSpec) -> SensorNoise:
        """The model for this rangefinder with the documented parameters (ValueError: unknown model, or
        no datasheet return model for the sensor)."""
        try:
            m = SensorNoiseModel(model)
        except ValueError:
            raise ValueError(f"unknown sensor noise {model!r}; available: "
                             f"{', '.join(x.value for x in SensorNoiseModel)}") from None
        if m is SensorNoiseModel.DATASHEET:
            return cls(m, spec, returns=return_model_for(spec))
        if m is SensorNoiseModel.APPENDIX_A:
            return cls(m, spec, appendix_a=AppendixANoise())
        return cls(m, spec)

    @property
    def active(self) -> bool:
        return self.model is not SensorNoiseModel.NONE

    # -- what the data carries (1 sigma) ----------------------------------------------------------
    def range_sigma_m(self, range_m: float) -> float:
        if self.model is SensorNoiseModel.DATASHEET:
            return max(self.spec.range_sigma_m, self.spec.range_sigma_rel * abs(range_m))
        if self.model is SensorNoiseModel.APPENDIX_A:
            return self.appendix_a.range_sigma_m
        return 0.0

    @property
    def bias_m(self) -> float:
        return self.returns.bias_m if self.returns is not None else 0.0

    @property
    def servo_sigma_rad(self) -> float:
        return self.appendix_a.servo_sigma_rad if self.appendix_a is not None else 0.0

    @property
    def attitude_sigma_rad(self) -> float:
        return self.appendix_a.attitude_sigma_rad if self.appendix_a is not None else 0.0

    @property
    def position_sigma_m(self) -> float:
        return self.appendix_a.position_sigma_m if self.appendix_a is not None else 0.0

    @property
    def pose_noisy(self) -> bool:
        return self.attitude_sigma_rad > 0 or self.position_sigma_m > 0

    # -- the header record ------------------------------------------------------------------------
    def record(self) -> dict[str, Any] | None:
        """The header's ``sensor_noise`` (None for ``none``: the header stays as it always was)."""
        if not self.active:
            return None
        d: dict[str, Any] = {"model": self.model.value, "rangefinder": self.spec.model,
                             "resolution_m": self.spec.resolution_m}
        if self.model is SensorNoiseModel.DATASHEET:
            d.update(range_sigma_m=self.spec.range_sigma_m, range_sigma_rel=self.spec.range_sigma_rel,
                     max_range_m=self.spec.max_range_m, **asdict(self.returns))
        else:
            d.update(asdict(self.appendix_a), range_sigma_rel=0.0, pose_stream_hz=self.pose_stream_hz)
        return d

    @classmethod
    def from_record(cls, d: Any, spec: RangefinderSpec) -> SensorNoise:
        """Parse a header's ``sensor_noise`` (None: ``none``); ValueError naming a missing or bad key."""
        if d is None:
            return cls(SensorNoiseModel.NONE, spec)
        if not isinstance(d, dict):
            raise ValueError(f"log header sensor_noise must be a JSON object, got {type(d).__name__}")
        try:
            model = SensorNoiseModel(d.get("model"))
        except ValueError:
            raise ValueError(f"log header sensor_noise.model must be one of "
                             f"{', '.join(x.value for x in SensorNoiseModel)}, got {d.get('model')!r}") from None
        try:
            if model is SensorNoiseModel.DATASHEET:
                spec = spec.with_(range_sigma_m=d["range_sigma_m"], range_sigma_rel=d["range_sigma_rel"],
                                  resolution_m=d["resolution_m"], max_range_m=d["max_range_m"])
                returns = ReturnModel(**{k: d[k] for k in ("reference_reflectance", "target_reflectance",
                                                           "dropout_ramp_rel", "bias_m")})
                return cls(model, spec, returns=returns)
            if model is SensorNoiseModel.APPENDIX_A:
                a = AppendixANoise(**{k: d[k] for k in ("range_sigma_m", "servo_sigma_rad", "attitude_sigma_rad",
                                                        "position_sigma_m")})
                return cls(model, spec, appendix_a=a, pose_stream_hz=_number(d, "pose_stream_hz"))
            return cls(model, spec)
        except KeyError as exc:
            raise ValueError(f"log header sensor_noise lacks {exc}") from None
        except TypeError as exc:
            raise ValueError(f"log header sensor_noise is malformed: {exc}") from None


def _number(d: dict[str, Any], key: str) -> float:
    v = d[key]
    if not is_finite_number(v):
        raise ValueError(f"log header sensor_noise.{key} must be a finite number, got {v!r}")
    return float(v)


def _stated(header: Any, key: str) -> float:
    """A sigma the header's ``sensor_noise`` states (0 when absent); ValueError when it is not a number >= 0."""
    rec = header.get(HEADER_KEY) if isinstance(header, dict) else None
    if rec is None:
        return 0.0
    if not isinstance(rec, dict):
        raise ValueError("log header sensor_noise must be a JSON object")
    v = rec.get(key, 0.0)
    if not is_finite_number(v) or v < 0:
        raise ValueError(f"log header sensor_noise.{key} must be a finite number >= 0, got {v!r}")
    return float(v)


def stated_range_sigma(header: Any) -> tuple[float, float]:
    """(range_sigma_m, range_sigma_rel) the ``sensor_noise`` record states ((0, 0) without one): the
    ground station takes the larger of these and the ``sensor`` spec's."""
    return _stated(header, "range_sigma_m"), _stated(header, "range_sigma_rel")


def stated_position_sigma_m(header: Any) -> float:
    """The position sigma the ``sensor_noise`` record states (0 without one)."""
    return _stated(header, "position_sigma_m")


def stated_pose_draw(header: Any) -> tuple[float, float]:
    """(sigma m, messages a second) of the record's pose draw: one position error per pose message, shared by the
    samples the payload tags between two messages ((0, POSE_STREAM_HZ) without a record)."""
    return _stated(header, "position_sigma_m"), _stated(header, "pose_stream_hz") or POSE_STREAM_HZ


def stated_angle_sigma_rad(header: Any) -> float:
    """The beam's pointing sigma the ``sensor_noise`` record states: servo angle and attitude combined
    (0 without one)."""
    return math.hypot(_stated(header, "servo_sigma_rad"), _stated(header, "attitude_sigma_rad"))


def describe_record(rec: Any) -> str:
    """One line for a report: the ``sensor_noise`` record's model and its parameters ("none" without one)."""
    if rec is None:
        return "none"
    if not isinstance(rec, dict):
        return "unreadable sensor_noise record"

    def num(key: str, scale: float = 1.0) -> str:
        v = rec.get(key)
        ok = is_finite_number(v)
        return f"{v * scale:.3g}" if ok else "?"

    model = rec.get("model")
    if model == SensorNoiseModel.DATASHEET:
        return (f"datasheet ({rec.get('rangefinder', '?')}): range sigma max({num('range_sigma_m', 100)} cm, "
                f"{num('range_sigma_rel', 100)} % of r), bias {num('bias_m', 100)} cm, quantum "
                f"{num('resolution_m', 100)} cm; no returns beyond {num('max_range_m')} m x "
                f"sqrt(rho cos i / {num('reference_reflectance')}) with rho = {num('target_reflectance')}")
    if model == SensorNoiseModel.APPENDIX_A:
        deg = 180 / math.pi
        return (f"appendix-a: range {num('range_sigma_m', 100)} cm, servo angle "
                f"{num('servo_sigma_rad', deg)} deg, attitude {num('attitude_sigma_rad', deg)} deg, "
                f"position {num('position_sigma_m')} m (1 sigma; pose per message at {num('pose_stream_hz')} Hz)")
    return f"unknown model {model!r}"


def noise_summary(noise: SensorNoise) -> str:
    """`describe_record` of what this noise writes in the header."""
    return describe_record(noise.record())
