"""The sample-log header: what the ground station needs to turn a log into points and a volume.

`LogHeader` is the header, typed, with `to_dict()` / `from_dict()`; one pure function
(`build_log_header`) builds it for every writer (the SITL's runs and the payload program on the
drone), so the keys cannot drift apart and the payload never imports `sitl`. The ground station reads:

- ``sensor``: a `firmware_py.core.sensor.RangefinderSpec` as a dict: the range error model
  (``range_sigma_m``, ``range_sigma_rel``, ``resolution_m``) that sizes its wall/roof tolerances, plus
  the sensor's rate, range and beam;
- ``lever_arm_body_m``, ``storage``, ``storage_frame``: the geometry of eqs. (3)-(6);
- ``site`` (when known): where the building stands on Earth (`firmware_py.core.site.Site`: its floor
  corner and heading); ``storage_frame`` is that site about the autopilot's EKF origin;
- ``servo``: the eq. (1) waveform, ``mission_id`` / ``mission``: what was flown (None when unknown);
- ``boresight`` (optional): the beam's configured mounting (`firmware_py.core.frames.Boresight`, rad);
  the ground station places points with it (square when absent);
- ``config`` (optional, the payload's): the effective configuration after flags, in the configuration
  file's sections (`firmware_py.core.config_file`), plus ``file``: the file it started from;
- ``software``, ``created_utc``, ``source``: provenance.

Key order is fixed (JSON keeps it), so two writers given the same inputs write the same header.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from firmware_py.core.frames import Boresight, StorageFrame
from firmware_py.core.numbers import is_finite_number
from firmware_py.core.sensor import LIDARLITE_V3, RangefinderSpec
from firmware_py.core.servo_model import ServoCalibration
from firmware_py.core.site import Site
from firmware_py.core.storage import Storage
from firmware_py.core.version import software_version
from firmware_py.core.waveform import Waveform


def utc_now_iso() -> str:
    """Creation time as the header writes it: ISO 8601, UTC, whole seconds."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def sensor_spec(rate_hz: float, **overrides: Any) -> dict[str, Any]:
    """The header's ``sensor`` dict: the LIDAR-Lite v3 datasheet at rate_hz, with any value overridden.

    Raises:
        ValueError: a non-finite or out-of-range value (named).
    """
    return LIDARLITE_V3.with_(rate_hz=rate_hz, **overrides).to_dict()


def servo_header(waveform_name: str, wf: Waveform, initial_position: int) -> dict[str, Any]:
    """The header's ``servo`` dict: the eq. (1) waveform the payload drove."""
    return ServoSweep.of(waveform_name, wf, initial_position).to_dict()


def waveform_from_dict(d: Any) -> Waveform:
    """The eq. (1) waveform in a header's ``servo`` (only the keys the waveform needs, so a reader that
    wants the sweep alone accepts a partial header); ValueError naming a missing or bad key."""
    d = _mapping(d, "servo")
    try:
        return Waveform(_number(d, "shape_c", "servo"), _number(d, "frequency_hz", "servo"),
                        _number(d, "amplitude_rad", "servo"), _number(d, "phase_rad", "servo"),
                        _integer(d, "direction", "servo"))
    except KeyError as exc:
        raise ValueError(f"log header servo lacks {exc}") from None


@dataclass(frozen=True)
class ServoSweep:
    """The header's ``servo``: the eq. (1) waveform the payload drove, and which of Fig. 9's 20 starts."""

    waveform: str
    shape_c: float
    frequency_hz: float
    amplitude_rad: float
    phase_rad: float
    direction: int
    initial_position: int

    def __post_init__(self) -> None:
        self.eq1()  # the waveform's own checks, with their messages
        if not isinstance(self.waveform, str) or not self.waveform:
            raise ValueError(f"servo waveform name must be a non-empty string, got {self.waveform!r}")
        if isinstance(self.initial_position, bool) or not isinstance(self.initial_position, int):
            raise ValueError(f"servo initial_position must be an integer, got {self.initial_position!r}")

    @classmethod
    def of(cls, waveform_name: str, wf: Waveform, initial_position: int) -> ServoSweep:
        return cls(waveform_name, wf.shape_c, wf.frequency_hz, wf.amplitude_rad, wf.phase_rad, wf.direction,
                   initial_position)

    def eq1(self) -> Waveform:
        """The waveform itself."""
        return Waveform(self.shape_c, self.frequency_hz, self.amplitude_rad, self.phase_rad, self.direction)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any) -> ServoSweep:
        """Parse a header's ``servo``; ValueError naming a missing key or a bad value."""
        wf = waveform_from_dict(d)
        try:
            return cls.of(str(d["waveform"]), wf, _integer(d, "initial_position", "servo"))
        except KeyError as exc:
            raise ValueError(f"log header servo lacks {exc}") from None


MIN_PWM_FRAME_S = 0.0025
"""The shortest servo PWM frame: one 2.5 ms pulse, a hobby servo's longest (400 Hz, the fastest digital servos')."""


@dataclass(frozen=True)
class ServoDrive:
    """The header's ``servo_drive``: when the sweep started on the samples' clock, and the PWM frame.

    With the servo calibration it lets the ground station re-simulate the servo the payload drove.
    """

    t0_s: float
    frame_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.t0_s) and math.isfinite(self.frame_s) and MIN_PWM_FRAME_S <= self.frame_s <= 1.0):
            raise ValueError(f"servo drive needs a finite start and a PWM frame in [{MIN_PWM_FRAME_S:g}, 1] s, "
                             f"got {self}")

    def to_dict(self) -> dict[str, float]:
        return {"t0_s": self.t0_s, "frame_s": self.frame_s}

    @classmethod
    def from_dict(cls, d: Any) -> ServoDrive:
        d = _mapping(d, "servo_drive")
        return cls(_number(d, "t0_s", "servo_drive"), _number(d, "frame_s", "servo_drive"))


MAX_LEVER_ARM_M = 5.0
"""The largest lever arm component taken (m): a multirotor is at most a few metres across, so a larger one is a
typing error (a centimetre entered as metres), refused rather than flown or reported."""

STANDARD_KEYS = ("software", "created_utc", "source", "sensor", "lever_arm_body_m", "servo", "mission_id",
                 "mission", "storage", "storage_frame")
"""The keys every header has, in the order they are written."""
OPTIONAL_KEYS = ("site", "servo_calibration", "servo_drive", "boresight")
"""Keys a header may have, typed: written after the standard ones, before any extra keys."""


@dataclass(frozen=True)
class LogHeader:
    """A sample-log header, typed (the module docstring says what each part is for).

    `to_dict()` is what the log stores (key order fixed, so two writers given the same inputs write
    the same bytes); `from_dict()` parses one back, naming the first bad key. Keys this class does not
    know travel in `extra` untouched (a newer writer's additions survive an older reader's round trip).
    """

    source: str
    sensor: RangefinderSpec
    lever_arm_body_m: tuple[float, float, float]
    servo: ServoSweep
    storage: Storage
    storage_frame: StorageFrame
    mission_id: str | None = None
    mission: Mapping[str, Any] | None = None
    software: str = field(default_factory=software_version)
    created_utc: str = field(default_factory=utc_now_iso)
    site: Site | None = None
    servo_calibration: ServoCalibration | None = None
    servo_drive: ServoDrive | None = None
    boresight: Boresight | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        lever = self.lever_arm_body_m
        if not (isinstance(lever, Sequence) and len(lever) == 3
                and all(is_finite_number(v) for v in lever)):
            raise ValueError(f"lever arm must be 3 finite numbers, got {lever!r}")
        object.__setattr__(self, "lever_arm_body_m", tuple(float(v) for v in lever))
        if not isinstance(self.source, str) or not self.source:
            raise ValueError(f"log header source must be a non-empty string, got {self.source!r}")
        clash = set(self.extra) & {*STANDARD_KEYS, *OPTIONAL_KEYS}
        if clash:
            raise ValueError(f"extra header key {sorted(clash)[0]!r} would replace a standard one")

    def to_dict(self) -> dict[str, Any]:
        """The header as the sample log stores it."""
        d: dict[str, Any] = {
            "software": self.software,
            "created_utc": self.created_utc,
            "source": self.source,
            "sensor": self.sensor.to_dict(),
            "lever_arm_body_m": list(self.lever_arm_body_m),
            "servo": self.servo.to_dict(),
            "mission_id": self.mission_id,
            "mission": dict(self.mission) if self.mission is not None else None,
            "storage": self.storage.to_dict(),
            "storage_frame": self.storage_frame.to_dict(),
        }
        if self.site is not None:
            d["site"] = self.site.to_dict()
        if self.servo_calibration is not None:
            d["servo_calibration"] = asdict(self.servo_calibration)
        if self.servo_drive is not None:
            d["servo_drive"] = self.servo_drive.to_dict()
        if self.boresight is not None:
            d["boresight"] = self.boresight.to_dict()
        d.update(self.extra)
        return d

    @classmethod
    def from_dict(cls, d: Any) -> LogHeader:
        """Parse a stored header; ValueError naming the missing or malformed key."""
        d = _mapping(d, "log header")
        missing = [k for k in STANDARD_KEYS if k not in d]
        if missing:
            raise ValueError(f"log header lacks {', '.join(missing)}")
        try:
            storage = Storage.from_dict(_mapping(d["storage"], "storage"))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"log header storage is malformed: {exc}") from None
        try:
            frame = StorageFrame.from_dict(_mapping(d["storage_frame"], "storage_frame"))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"log header storage_frame is malformed: {exc}") from None
        site = None
        if d.get("site") is not None:
            try:
                site = Site.from_dict(d["site"])
            except ValueError as exc:
                raise ValueError(f"log header site is malformed: {exc}") from None
        cal = None
        if d.get("servo_calibration") is not None:
            c = _mapping(d["servo_calibration"], "servo_calibration")
            try:
                cal = ServoCalibration(**{k: _number(c, k, "servo_calibration") for k in c})
            except (TypeError, ValueError) as exc:
                raise ValueError(f"log header servo_calibration is malformed: {exc}") from None
        mission = d["mission"]
        if mission is not None and not isinstance(mission, dict):
            raise ValueError("log header mission must be a JSON object or null")
        mission_id = d["mission_id"]
        if mission_id is not None and not isinstance(mission_id, str):
            raise ValueError(f"log header mission_id must be a string or null, got {mission_id!r}")
        for key in ("software", "created_utc"):
            if not isinstance(d[key], str):
                raise ValueError(f"log header {key} must be a string, got {d[key]!r}")
        return cls(
            source=d["source"], sensor=RangefinderSpec.from_dict(d["sensor"]),
            lever_arm_body_m=d["lever_arm_body_m"], servo=ServoSweep.from_dict(d["servo"]), storage=storage,
            storage_frame=frame, mission_id=mission_id, mission=mission, software=d["software"],
            created_utc=d["created_utc"], site=site, servo_calibration=cal,
            servo_drive=ServoDrive.from_dict(d["servo_drive"]) if d.get("servo_drive") is not None else None,
            boresight=boresight_from_dict(d["boresight"]) if d.get("boresight") is not None else None,
            extra={k: v for k, v in d.items() if k not in STANDARD_KEYS and k not in OPTIONAL_KEYS})


def boresight_from_dict(d: Any) -> Boresight:
    """A header's ``boresight``: both angles must be finite numbers within the mounting limits; ValueError
    naming the key otherwise (a forged or damaged record must not bend every point silently)."""
    d = _mapping(d, "boresight")
    try:
        return Boresight(_number(d, "tilt_rad", "boresight"), _number(d, "sweep_yaw_rad", "boresight"))
    except KeyError as exc:
        raise ValueError(f"log header boresight lacks {exc}") from None
    except ValueError as exc:
        raise ValueError(f"log header {exc}") from None


def header_boresight(header: Mapping[str, Any]) -> Boresight:
    """The beam's configured mounting a header states: square when it has no ``boresight`` (older logs)."""
    b = header.get("boresight")
    return Boresight() if b is None else boresight_from_dict(b)


def _mapping(d: Any, where: str) -> dict[str, Any]:
    if not isinstance(d, dict):
        raise ValueError(f"log header {where} must be a JSON object, got {type(d).__name__}")
    return d


def _number(d: dict[str, Any], key: str, where: str) -> float:
    v = d[key]
    if not is_finite_number(v):
        raise ValueError(f"log header {where}.{key} must be a finite number, got {v!r}")
    return float(v)


def _integer(d: dict[str, Any], key: str, where: str) -> int:
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"log header {where}.{key} must be an integer, got {v!r}")
    return v


def build_log_header(*, source: str, sensor: Mapping[str, Any], lever_arm_body_m: Sequence[float],
                     waveform_name: str, waveform: Waveform, initial_position: int, storage: Storage,
                     frame: StorageFrame, mission_id: str | None = None, mission: Mapping[str, Any] | None = None,
                     created_utc: str | None = None, site: Site | None = None,
                     extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The sample-log header dict (module docstring), ready for `SampleLogWriter`: a `LogHeader`'s `to_dict()`.

    Args:
        source: who wrote the log, e.g. "sitl/jsbsim" or "payload".
        sensor: the ``sensor`` dict (`sensor_spec`, or any `RangefinderSpec.to_dict()`).
        lever_arm_body_m: (3,) sensor position from the centre of gravity in the body frame (FRD), m.
        waveform_name, waveform, initial_position: the servo sweep (`servo_header`).
        storage, frame: the building and its placement in local NED.
        site: where the building stands on Earth, when known (the ``site`` record).
        mission_id, mission: what was flown, when known (None otherwise).
        created_utc: creation time; None = now (`utc_now_iso`).
        extra: further keys appended after the standard ones (they may not replace one);
            ``servo_calibration``, ``servo_drive`` and ``boresight`` among them are checked as their types.

    Raises:
        ValueError: a lever arm that is not 3 finite numbers, a bad sensor value (named), or an extra
            key clashing with a standard one.
    """
    more = dict(extra or {})
    clash = [k for k in more if k in STANDARD_KEYS]
    if clash:
        raise ValueError(f"extra header key {clash[0]!r} would replace a standard one")
    cal = more.pop("servo_calibration", None)
    drive = more.pop("servo_drive", None)
    boresight = more.pop("boresight", None)
    site_extra = more.pop("site", None)
    if site is None and site_extra is not None:
        site = Site.from_dict(dict(site_extra)) if isinstance(site_extra, Mapping) else site_extra
    return LogHeader(
        source=source, sensor=RangefinderSpec.from_dict(dict(sensor)), lever_arm_body_m=lever_arm_body_m,
        servo=ServoSweep.of(waveform_name, waveform, initial_position), storage=storage, storage_frame=frame,
        mission_id=mission_id, mission=mission,
        created_utc=created_utc if created_utc is not None else utc_now_iso(), site=site,
        servo_calibration=ServoCalibration(**cal) if isinstance(cal, Mapping) else cal,
        servo_drive=ServoDrive.from_dict(dict(drive)) if isinstance(drive, Mapping) else drive,
        boresight=boresight_from_dict(dict(boresight)) if isinstance(boresight, Mapping) else boresight,
        extra=more).to_dict()
