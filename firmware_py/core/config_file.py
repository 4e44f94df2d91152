"""One configuration file for a flight: the site, the payload and the mission, in TOML.

Every program takes `--config FILE`; each key the file sets becomes the default of the option it maps to
(`firmware_py.core.cli.apply_config`), so a flag given on the command line still wins and a key the
file leaves out keeps the built-in default. docs/configuration.md lists every key.

    [site]            the building: length_m, width_m, height_m, origin = [lat_deg, lon_deg, alt_m]
                      (its floor corner, the storage frame's origin), heading_deg (its x axis from north),
                      name, timezone (IANA, for the report's local time)
    [payload]         rangefinder, i2c, uart, pwm, mavlink, rate_hz, log, lever_arm_m, boresight_deg,
                      lidarlite_preset, stream, signing_key, ekf_origin, stop_on_disarm, start_on_arm
    [payload.servo]   the servo's calibration (`ServoCalibration`): center_us, us_per_rad, min_us, max_us,
                      slew_rad_s, lag_s
    [payload.sweep]   the eq. (1) sweep: waveform, peak_rate_rad_s, phase
    [mission]         p_traj_pct, altitude_m, speed_m_s, yaw_rate_max_deg_s, turn
    [sitl]            sensor_noise, pose_error (the simulator only)
    [survey]          operator, aircraft: who flew it with what (the report's metadata)
    [[piles]]         one table per named pile (the report): name, x_m, y_m (a point inside it, storage frame),
                      density_kg_m3, material

The schema is the section dataclasses below: each field's metadata says its kind, unit, limits and
meaning, and the parser, the TOML writer and the reference page are all driven by it. Every key is
optional (None: not set). Limits are what the hardware or the geometry can be, not a tuned case: the
servo pulses are the hobby-servo range `ServoCalibration` accepts, the rate the payload loop's, the
angles what a mounting can be off by.

Errors: each unknown key, wrong type or bad value is one line naming the file, the section and the key
(`config.toml: [payload] rate_hz: must be 1-2000 Hz, got -5`); all of them are reported at once
(`ConfigError.details`), the checks across keys (a building's three dimensions, a pile's point) with the keys' own,
on the keys that passed; `ConfigError.config` holds those, for a program's own checks of them (the URLs). Exit 2
(a configuration file is options written down). A file that cannot
be read at all (missing, a FIFO, larger than `MAX_CONFIG_BYTES`, not UTF-8) is an input error, exit 3.

Standard library only, like the rest of `firmware_py.core`.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import json
import math
import os
import re
import tomllib
import zoneinfo
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from firmware_py.core.geodesy import ALT_MAX_M, ALT_MIN_M
from firmware_py.core.header import MAX_LEVER_ARM_M
from firmware_py.core.numbers import is_number
from firmware_py.core.safe_read import InputError, read_bounded
from firmware_py.core.servo_model import ServoCalibration
from firmware_py.core.stream_format import parse_stream_url
from firmware_py.core.waveform import N_PHASES

MAX_CONFIG_BYTES = 256 * 1024
"""Largest configuration file read: the commented example is 6 kB; anything this big is not one."""


class Rangefinder(enum.Enum):
    """The single-point LiDARs the payload drives."""

    LIDARLITE_V3 = "lidarlite-v3"  # Garmin LIDAR-Lite v3 on I2C (the paper's)
    TFMINI = "tfmini"  # Benewake TFMini family on a UART (the paper authors' real rig)


class SweepShape(enum.Enum):
    """The eq. (1) servo waveforms (C = 0.95 and C = 0)."""

    SEMI_TRIANGULAR = "semi-triangular"
    SINUSOIDAL = "sinusoidal"


class Turn(enum.Enum):
    """Corner turns of the rectangular survey (Fig. 15; `sitl.missions.rectangle.TURN_MODES`)."""

    ONE_STEP = "one-step"
    TWO_STEP = "two-step"


class SensorNoise(enum.Enum):
    """The simulator's range-noise models."""

    NONE = "none"
    DATASHEET = "datasheet"
    APPENDIX_A = "appendix-a"


class PoseError(enum.Enum):
    """The simulator's indoor pose-estimate profiles (`sitl.sensing.pose_drift.PoseErrorProfile`)."""

    NONE = "none"
    FLOW = "flow"
    VIO = "vio"


class Kind(enum.Enum):
    """What a key holds."""

    NUMBER = "number"
    INTEGER = "integer"
    BOOL = "boolean"
    TEXT = "string"
    URL = "URL"
    PATH = "path"
    VECTOR = "array of numbers"
    CHOICE = "choice"
    TIMEZONE = "IANA time zone"


def _key(kind: Kind, doc: str, *, unit: str = "", lo: float | None = None, hi: float | None = None,
         open_lo: bool = False, open_hi: bool = False, length: int = 0, names: tuple[str, ...] = (),
         choices: type[enum.Enum] | None = None, nonzero: bool = False, example: Any = None) -> dict[str, Any]:
    """One key's schema, a field's metadata (the field's default is None: the key is not set)."""
    return {
        "kind": kind, "doc": doc, "unit": unit, "lo": lo, "hi": hi, "open_lo": open_lo, "open_hi": open_hi,
        "length": length, "names": names, "choices": choices, "nonzero": nonzero, "example": example}


@dataclass(frozen=True)
class SiteSection:
    """[site]: the building and where it stands."""

    length_m: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "inside length of the building, along its x axis", unit="m", lo=0.5, hi=10_000.0, example=60.0))
    width_m: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "inside width, along y (90 deg left of x seen from above)", unit="m", lo=0.5, hi=10_000.0,
        example=40.0))
    height_m: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "inside height, floor to roof", unit="m", lo=0.5, hi=10_000.0, example=15.0))
    origin: tuple[float, float, float] | None = field(default=None, metadata=_key(
        Kind.VECTOR, "the storage frame's origin, the building's floor corner: latitude, longitude (WGS84), altitude "
        "above mean sea level", unit="deg, deg, m", length=3, names=("lat_deg", "lon_deg", "alt_m"),
        example=(53.4668, -2.2339, 50.0)))
    heading_deg: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "direction of the building's x axis (its length), clockwise from north", unit="deg", lo=-360.0,
        hi=360.0, example=0.0))
    name: str | None = field(default=None, metadata=_key(
        Kind.TEXT, "the site or building's name, as the report's reader knows it", example="North bay, Ashby depot"))
    timezone: str | None = field(default=None, metadata=_key(
        Kind.TIMEZONE, "the site's time zone (IANA name): the report shows the survey's local time beside UTC",
        example="Europe/London"))

    def dimensions(self) -> tuple[float, float, float] | None:
        """(L, W, H), or None unless all three are set (a file that passed its checks gives all or none)."""
        if self.length_m is None or self.width_m is None or self.height_m is None:
            return None
        return (self.length_m, self.width_m, self.height_m)


@dataclass(frozen=True)
class ServoSection:
    """[payload.servo]: the servo's calibration (`firmware_py.core.servo_model.ServoCalibration`)."""

    center_us: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "pulse width that points the beam straight down (gamma = 0)", unit="us", lo=500.0, hi=2500.0,
        example=1500.0))
    us_per_rad: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "pulse change per radian of shaft angle; negative when a longer pulse turns the beam to port. A "
        "hobby servo turns 90-270 deg over 1000 us: 212-637 us/rad", unit="us/rad", lo=-10_000.0, hi=10_000.0,
        nonzero=True, example=318.3))
    min_us: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "shortest pulse the servo accepts (the sweep is clamped to it)", unit="us", lo=500.0, hi=2500.0,
        example=1000.0))
    max_us: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "longest pulse the servo accepts", unit="us", lo=500.0, hi=2500.0, example=2000.0))
    slew_rad_s: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "the servo's top speed (datasheet: 0.1 s/60 deg is 10.5 rad/s)", unit="rad/s", lo=0.0, hi=100.0,
        open_lo=True, example=5.0))
    lag_s: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "time constant of the servo's position loop", unit="s", lo=0.0, hi=1.0, example=0.02))

    def calibration(self, base: ServoCalibration | None = None) -> ServoCalibration:
        """base (the built-in calibration by default) with the keys this section sets."""
        base = base or ServoCalibration()
        return dataclasses.replace(base, **{f.name: getattr(self, f.name) for f in fields(self)
                                            if getattr(self, f.name) is not None})


@dataclass(frozen=True)
class SweepSection:
    """[payload.sweep]: the eq. (1) servo sweep."""

    waveform: SweepShape | None = field(default=None, metadata=_key(
        Kind.CHOICE, "servo waveform of eq. (1): semi-triangular (C = 0.95) or sinusoidal (C = 0)", choices=SweepShape,
        example="semi-triangular"))
    peak_rate_rad_s: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "peak servo rate; sets the sweep frequency (5 rad/s: 0.67 Hz semi-triangular). At most the "
        "servo's slew_rad_s", unit="rad/s", lo=0.0, hi=100.0, open_lo=True, example=5.0))
    phase: int | None = field(default=None, metadata=_key(
        Kind.INTEGER, f"the servo's start position, 0..{2 * N_PHASES - 1} (Fig. 9: {N_PHASES} phases x 2 directions)",
        lo=0, hi=2 * N_PHASES - 1, example=0))


@dataclass(frozen=True)
class PayloadSection:
    """[payload]: the sensor head on the drone and its links."""

    rangefinder: Rangefinder | None = field(default=None, metadata=_key(
        Kind.CHOICE, "the LiDAR: lidarlite-v3 (Garmin, I2C) or tfmini (Benewake TFMini family, UART)",
        choices=Rangefinder, example="lidarlite-v3"))
    i2c: str | None = field(default=None, metadata=_key(
        Kind.URL, "the LIDAR-Lite's I2C bus: i2c:1, i2c:/dev/i2c-1, tcp:HOST:PORT (SITL bridge)", example="i2c:1"))
    uart: str | None = field(default=None, metadata=_key(
        Kind.URL, "the TFMini's serial port: serial:/dev/serial0 or serial:/dev/ttyS0:115200", example=
        "serial:/dev/serial0:115200"))
    pwm: str | None = field(default=None, metadata=_key(
        Kind.URL, "the servo's PWM output: pwm:sysfs:CHIP:CH, pwm:pca9685:BUS:ADDR:CH, pwm:mavlink:N, "
        "pwm:tcp:HOST:PORT:CH (SITL bridge)", example="pwm:sysfs:0:0"))
    mavlink: str | None = field(default=None, metadata=_key(
        Kind.URL, "the link to the autopilot: serial:/dev/ttyAMA0:921600, udp:HOST:PORT, udpout:HOST:PORT, "
        "tcp:HOST:PORT", example="serial:/dev/ttyAMA0:921600"))
    rate_hz: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "LiDAR sample rate (the payload loop's rate)", unit="Hz", lo=1.0, hi=2000.0, example=500.0))
    log: str | None = field(default=None, metadata=_key(
        Kind.PATH, "the sample log to write (.pslog); relative to this file's folder", example="survey.pslog"))
    lever_arm_m: tuple[float, float, float] | None = field(default=None, metadata=_key(
        Kind.VECTOR, "the LiDAR's position from the drone's centre of gravity, body frame (forward, right, down); a "
        "multirotor is at most a few metres across; measure it to a centimetre or two: a height error moves the "
        "volume by itself times the floor area", unit="m", length=3, names=("x", "y", "z"), lo=-MAX_LEVER_ARM_M,
        hi=MAX_LEVER_ARM_M,
        example=(0.0, 0.0, 0.10)))
    boresight_deg: tuple[float, float] | None = field(default=None, metadata=_key(
        Kind.VECTOR, "how the beam's mounting differs from square (`frames.Boresight`): tilt out of the sweep plane (> "
        "0 leans forward), yaw of the servo axis about body z (> 0 clockwise from above)", unit="deg", length=2, names=(
        "tilt", "sweep_yaw"), lo=-45.0, hi=45.0, example=(0.0, 0.0)))
    lidarlite_preset: str | None = field(default=None, metadata=_key(
        Kind.TEXT, "LIDAR-Lite register preset (firmware_py.drivers.lidarlite)", example="fast-500hz"))
    stream: str | None = field(default=None, metadata=_key(
        Kind.URL, "also stream samples live to the ground station: udp:HOST:PORT", example="udp:192.168.1.10:14600"))
    signing_key: str | None = field(default=None, metadata=_key(
        Kind.PATH, "MAVLink 2 signing key file (64 hex digits or a passphrase line, chmod 600); relative to this "
        "file's folder", example="signing.key"))
    ekf_origin: tuple[float, float, float] | None = field(default=None, metadata=_key(
        Kind.VECTOR, "sent as SET_GPS_GLOBAL_ORIGIN at start: an indoor EKF needs an origin before it publishes "
        "LOCAL_POSITION_NED", unit="deg, deg, m", length=3, names=("lat_deg", "lon_deg", "alt_m"), example=(53.4668,
        -2.2339, 50.0)))
    stop_on_disarm: bool | None = field(default=None, metadata=_key(
        Kind.BOOL, "stop logging when the autopilot disarms after having been armed", example=True))
    start_on_arm: bool | None = field(default=None, metadata=_key(
        Kind.BOOL, "open the log and start the sweep only when the autopilot arms (nothing logged on the ground)",
        example=True))
    servo: ServoSection = field(default_factory=ServoSection, metadata={"table": ServoSection})
    sweep: SweepSection = field(default_factory=SweepSection, metadata={"table": SweepSection})


MIN_YAW_RATE_DEG_S = 0.5
"""Slowest yaw rate a mission may turn at: the rectangle's four quarter turns then take 12 min, most of a small
multirotor's 15 min battery (the paper's slowest is 1 deg/s; 0.001 deg/s asked the simulator for a flight of days)."""


@dataclass(frozen=True)
class MissionSection:
    """[mission]: the rectangular survey flight (paper section 3)."""

    p_traj_pct: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "waypoint offset from the walls, percent of L and W (eqs. 17-18)", unit="%", lo=0.0, hi=50.0,
        open_lo=True, open_hi=True, example=20.0))
    altitude_m: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "flight height above the floor (must leave clearance to the roof)", unit="m", lo=0.0, hi=10_000.0,
        open_lo=True, example=12.0))
    speed_m_s: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "flight speed along the legs", unit="m/s", lo=0.05, hi=15.0, example=1.0))
    yaw_rate_max_deg_s: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "largest yaw rate in the turns", unit="deg/s", lo=MIN_YAW_RATE_DEG_S, hi=360.0, example=30.0))
    turn: Turn | None = field(default=None, metadata=_key(
        Kind.CHOICE, "corner turns (Fig. 15): one-step or two-step", choices=Turn, example="one-step"))


@dataclass(frozen=True)
class SitlSection:
    """[sitl]: what only the simulator uses."""

    sensor_noise: SensorNoise | None = field(default=None, metadata=_key(
        Kind.CHOICE, "range-noise model: none, datasheet (per rangefinder) or appendix-a (the paper's)",
        choices=SensorNoise, example="datasheet"))
    pose_error: PoseError | None = field(default=None, metadata=_key(
        Kind.CHOICE, "indoor pose estimate the simulated autopilot flies on and reports: none (the truth), flow "
        "(optical flow + downward rangefinder) or vio (visual odometry); for plan, the estimate a real flight will "
        "fly on (a warning when it can drift into the walls); docs/pose_error.md",
        choices=PoseError, example="flow"))


@dataclass(frozen=True)
class SurveySection:
    """[survey]: who flew the survey and with what (shown in the report, never used in the computation)."""

    operator: str | None = field(default=None, metadata=_key(
        Kind.TEXT, "the pilot or surveyor responsible for the survey", example="J. Smith"))
    aircraft: str | None = field(default=None, metadata=_key(
        Kind.TEXT, "the aircraft (make, model, serial or registration)", example="F450 #3"))


MAX_DENSITY_KG_M3 = 22_600.0
"""Osmium, the densest element: no bulk material is denser."""


@dataclass(frozen=True)
class PileEntry:
    """[[piles]]: one pile the report names, found by a point inside it; its material's bulk density."""

    name: str | None = field(default=None, metadata=_key(
        Kind.TEXT, "the pile's name in the report (required; unique)", example="sand"))
    x_m: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "a point inside the pile, storage frame x (required)", unit="m", lo=0.0, hi=10_000.0,
        example=12.0))
    y_m: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "the same point's y (required)", unit="m", lo=0.0, hi=10_000.0, example=8.0))
    density_kg_m3: float | None = field(default=None, metadata=_key(
        Kind.NUMBER, "the material's bulk density, for the pile's mass (else the report's --density)", unit="kg/m³",
        lo=0.0, hi=MAX_DENSITY_KG_M3, open_lo=True, example=1600.0))
    material: str | None = field(default=None, metadata=_key(
        Kind.TEXT, "what the pile is", example="washed sand"))


@dataclass(frozen=True)
class ConfigFile:
    """A parsed configuration file (every key None unless the file sets it).

    Attributes:
        path: the file it was read from (None: built in code).
    """

    site: SiteSection = field(default_factory=SiteSection, metadata={"table": SiteSection})
    payload: PayloadSection = field(default_factory=PayloadSection, metadata={"table": PayloadSection})
    mission: MissionSection = field(default_factory=MissionSection, metadata={"table": MissionSection})
    sitl: SitlSection = field(default_factory=SitlSection, metadata={"table": SitlSection})
    survey: SurveySection = field(default_factory=SurveySection, metadata={"table": SurveySection})
    piles: tuple[PileEntry, ...] = field(default=(), metadata={"array": PileEntry})
    path: str | None = field(default=None, metadata={"skip": True})

    def get(self, key: str) -> Any:
        """The value of a dotted key ("payload.servo.center_us"); None when not set. The one derived key,
        "site.dimensions", is the building as the programs' --storage takes it ("60.0x40.0x15.0").

        Raises:
            KeyError: no such key in the schema.
        """
        if key == DIMENSIONS_KEY:
            dims = self.site.dimensions()
            return None if dims is None else "x".join(repr(float(v)) for v in dims)
        obj: Any = self
        for part in key.split("."):
            if not dataclasses.is_dataclass(obj) or part not in {f.name for f in fields(obj)}:
                raise KeyError(f"no configuration key {key!r}")
            obj = getattr(obj, part)
        return obj

    def to_dict(self) -> dict[str, Any]:
        """The keys set, nested by section (enums as their values, vectors as lists): JSON and TOML ready."""
        return _section_dict(self)


def _section_dict(obj: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in fields(obj):
        if f.metadata.get("skip"):
            continue
        v = getattr(obj, f.name)
        if "table" in f.metadata:
            sub = _section_dict(v)
            if sub:
                out[f.name] = sub
        elif "array" in f.metadata:
            if v:
                out[f.name] = [_section_dict(e) for e in v]
        elif v is not None:
            out[f.name] = v.value if isinstance(v, enum.Enum) else list(v) if isinstance(v, tuple) else v
    return out


SECTIONS = ("site", "payload", "mission", "sitl", "survey", "piles")
ARRAYS = ("piles",)
"""Sections written as arrays of tables ([[piles]]), one table per item."""
DIMENSIONS_KEY = "site.dimensions"
"""The derived key for [site] length_m, width_m and height_m together (`ConfigFile.get`)."""


def key_label(key: str) -> str:
    """How an error line names a dotted key: "[payload.servo] center_us"."""
    if key == DIMENSIONS_KEY:
        return "[site] length_m, width_m, height_m"
    section, _, name = key.rpartition(".")
    return f"[[{section}]] {name}" if section in ARRAYS else f"[{section}] {name}"


def schema_keys(cls: type = ConfigFile, prefix: str = "") -> list[tuple[str, dataclasses.Field]]:
    """Every key of the schema, dotted ("payload.servo.center_us"), with its field (for docs and tests)."""
    out = []
    for f in fields(cls):
        if f.metadata.get("skip"):
            continue
        name = f"{prefix}{f.name}"
        if "table" in f.metadata or "array" in f.metadata:
            out += schema_keys(f.metadata.get("table") or f.metadata["array"], f"{name}.")
        else:
            out.append((name, f))
    return out


# ----- errors ----------------------------------------------------------------------------------------


class ConfigError(ValueError):
    """A configuration file with bad content: one line per problem (the first is the message, the
    others `details`). A ValueError, so the programs' `run_cli` exits 2 (usage) with it; it is not a
    `firmware_py.core.cli.UserError` only because that module imports this one."""

    def __init__(self, problems: list[str], config: ConfigFile | None = None) -> None:
        super().__init__(problems[0])
        self.details = tuple(problems[1:])
        self.problems = tuple(problems)
        self.config = config
        """The file's keys that passed (a bad key left unset), so a caller can run its own checks on them and
        report its problems with these in one go; None when the file could not be read as TOML at all."""


def _where(section: str, key: str | None = None) -> str:
    return f"[{section}]" + (f" {key}" if key else "")


def _describe(v: Any) -> str:
    """A TOML value as the user wrote it, short."""
    kind = {bool: "a boolean", str: "a string", int: "an integer", float: "a number", list: "an array",
            dict: "a table"}.get(type(v), type(v).__name__)
    text = json.dumps(v, default=str) if isinstance(v, bool | str | int | float | list) else str(v)
    if isinstance(v, float) and not math.isfinite(v):
        text = str(v)
    if len(text) > 60:
        text = text[:57] + "..."
    return f"{kind} {text}" if kind != "a table" else kind


def _fmt(v: float) -> str:
    return f"{v:g}"


def range_text(m: Mapping[str, Any]) -> str:
    lo, hi, unit = m["lo"], m["hi"], m["unit"]
    u = f" {unit}" if unit and unit != "%" else unit
    if lo is not None and hi is not None:
        if m["open_lo"] or m["open_hi"]:
            return f"between {_fmt(lo)} and {_fmt(hi)}{u} (exclusive)" if m["open_lo"] and m["open_hi"] \
                else f"in {'(' if m['open_lo'] else '['}{_fmt(lo)}, {_fmt(hi)}{']' if not m['open_hi'] else ')'}{u}"
        return f"{_fmt(lo)}-{_fmt(hi)}{u}" if lo >= 0 else f"within {_fmt(lo)}..{_fmt(hi)}{u}"
    return ""


def _in_range(v: float, m: Mapping[str, Any]) -> bool:
    lo, hi = m["lo"], m["hi"]
    if lo is not None and (v <= lo if m["open_lo"] else v < lo):
        return False
    if hi is not None and (v >= hi if m["open_hi"] else v > hi):
        return False
    return not (m["nonzero"] and v == 0)


_URL_RE = re.compile(r"[a-z][a-z0-9+.-]*:\S+", re.ASCII)


def _check_value(v: Any, m: Mapping[str, Any], base_dir: Path | None) -> tuple[Any, str | None]:
    """(typed value, None) or (None, what is wrong)."""
    kind: Kind = m["kind"]
    if kind in (Kind.NUMBER, Kind.INTEGER):
        if kind is Kind.INTEGER and not (isinstance(v, int) and not isinstance(v, bool)):
            return None, f"must be an integer, got {_describe(v)}"
        if not is_number(v):
            return None, f"must be a number, got {_describe(v)}"
        if not math.isfinite(v):
            return None, f"must be a finite number, got {v}"
        if not _in_range(v, m):
            rng = range_text(m)
            need = f"must be {rng}" if rng else "must be in range"
            if m["nonzero"]:
                need += " and not 0"
            return None, f"{need}, got {_fmt(v)}"
        return (v if kind is Kind.INTEGER else float(v)), None
    if kind is Kind.BOOL:
        if not isinstance(v, bool):
            return None, f"must be true or false, got {_describe(v)}"
        return v, None
    if kind is Kind.TIMEZONE:
        if not isinstance(v, str) or not v.strip():
            return None, f"must be an IANA time zone name like \"Europe/London\" (a string), got {_describe(v)}"
        try:
            zoneinfo.ZoneInfo(v)
        except (zoneinfo.ZoneInfoNotFoundError, ValueError):
            return None, ("is not a time zone this computer knows (an IANA name like \"Europe/London\"), "
                          f"got {json.dumps(v)}")
        return v, None
    if kind is Kind.CHOICE:
        names = [c.value for c in m["choices"]]
        if not isinstance(v, str):
            return None, f"must be one of {', '.join(names)} (a string), got {_describe(v)}"
        try:
            return m["choices"](v), None
        except ValueError:
            return None, f"must be one of {', '.join(names)}, got {json.dumps(v)}"
    if kind is Kind.VECTOR:
        n, names = m["length"], m["names"]
        if not isinstance(v, list) or len(v) != n:
            return None, f"must be an array of {n} numbers [{', '.join(names)}], got {_describe(v)}"
        out = []
        for name, x in zip(names, v, strict=True):
            if not is_number(x) or not math.isfinite(x):
                return None, f"{name} must be a finite number, got {_describe(x)}"
            out.append(float(x))
        problem = _vector_problem(out, m)
        return (None, problem) if problem else (tuple(out), None)
    # TEXT, URL, PATH
    if not isinstance(v, str):
        return None, f"must be a {kind.value} (a quoted string), got {_describe(v)}"
    if not v.strip() or any(not c.isprintable() for c in v):
        return None, f"must be a non-empty {kind.value} of printable characters, got {json.dumps(v)}"
    if kind is Kind.URL and not _URL_RE.fullmatch(v.strip()):
        return None, f"must be a URL like SCHEME:..., got {json.dumps(v)}"
    if kind is Kind.PATH and base_dir is not None:
        return str(base_dir / os.path.expanduser(v)) if not os.path.isabs(os.path.expanduser(v)) \
            else os.path.expanduser(v), None
    return v, None


def _vector_problem(v: list[float], m: Mapping[str, Any]) -> str | None:
    names = m["names"]
    if names[:2] == ("lat_deg", "lon_deg"):
        for name, x, lo, hi in (("lat_deg", v[0], -90.0, 90.0), ("lon_deg", v[1], -180.0, 180.0),
                                ("alt_m", v[2], ALT_MIN_M, ALT_MAX_M)):
            if not lo <= x <= hi:
                return f"{name} must be within {_fmt(lo)}..{_fmt(hi)}, got {_fmt(x)}"
        return None
    for name, x in zip(names, v, strict=True):
        if not _in_range(x, m):
            return f"{name} must be {range_text(m)}, got {_fmt(x)}"
    return None


# ----- parsing ---------------------------------------------------------------------------------------


def _suggest(name: str, known: list[str]) -> str:
    close = difflib.get_close_matches(name, known, n=1)
    return f"did you mean {close[0]}?" if close else f"known: {', '.join(known)}"


def _parse_section(cls: type, table: Any, section: str, base_dir: Path | None,
                   problems: list[str], prefix: str, bad: set[str]) -> Any:
    """The section's typed keys; each problem appended to problems, and each key the file gives but with a bad
    value or type added to bad (dotted, "payload.servo.min_us"), so the checks across keys can tell a key left
    out from one refused."""
    if not isinstance(table, dict):
        problems.append(f"{prefix}{_where(section)}: must be a table ([{section}] and keys under it), "
                        f"got {_describe(table)}")
        return cls()
    known = {f.name: f for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for name, value in table.items():
        f = known.get(name)
        if f is None:
            kind = "section" if isinstance(value, dict) else "key"
            problems.append(f"{prefix}{_where(section, name)}: unknown {kind} ({_suggest(name, list(known))})")
            continue
        if "table" in f.metadata:
            kwargs[name] = _parse_section(f.metadata["table"], value, f"{section}.{name}", base_dir, problems, prefix,
                                          bad)
            continue
        typed, problem = _check_value(value, f.metadata, base_dir)
        if problem is not None:
            problems.append(f"{prefix}{_where(section, name)}: {problem}")
            bad.add(f"{section}.{name}")
        else:
            kwargs[name] = typed
    return cls(**kwargs)


def _parse_array(cls: type, items: Any, section: str, base_dir: Path | None, problems: list[str],
                 prefix: str, bad: set[str]) -> tuple[Any, ...]:
    """An array of tables ([[piles]]): each checked as a section; its lines say which item (#1 is the first), and
    its refused keys go to bad as "piles#1.x_m"."""
    if not isinstance(items, list) or not all(isinstance(t, dict) for t in items):
        problems.append(f"{prefix}[[{section}]]: must be an array of tables (one [[{section}]] heading per item), "
                        f"got {_describe(items)}")
        return ()
    out = []
    for i, table in enumerate(items, start=1):
        mine: list[str] = []
        mine_bad: set[str] = set()
        out.append(_parse_section(cls, table, section, base_dir, mine, "", mine_bad))
        problems += [f"{prefix}[[{section}]] #{i}{line.removeprefix(f'[{section}]')}" for line in mine]
        bad |= {f"{section}#{i}.{key.removeprefix(f'{section}.')}" for key in mine_bad}
    return tuple(out)


def _pile_checks(cfg: ConfigFile, prefix: str, bad: set[str]) -> list[str]:
    """Each [[piles]] item needs its name and point; names are unique; the point lies in the building. A key
    refused already (bad) is neither missing nor checked again."""
    problems: list[str] = []
    seen: dict[str, int] = {}
    dims = cfg.site.dimensions()
    for i, p in enumerate(cfg.piles, start=1):
        where = f"{prefix}[[piles]] #{i}"
        refused = {k for k in ("name", "x_m", "y_m") if f"piles#{i}.{k}" in bad}
        missing = [k for k in ("name", "x_m", "y_m") if getattr(p, k) is None and k not in refused]
        if missing:
            problems.append(f"{where} {missing[0]}: missing (each pile needs a name and a point inside it, x_m "
                            "and y_m)")
        if missing or refused:
            continue
        if p.name in seen:
            problems.append(f"{where} name: {json.dumps(p.name)} is already pile #{seen[p.name]}'s name")
        seen.setdefault(p.name, i)  # type: ignore[arg-type]
        if dims is not None:
            for k, limit in (("x_m", dims[0]), ("y_m", dims[1])):
                if getattr(p, k) > limit:
                    problems.append(f"{where} {k}: {_fmt(getattr(p, k))} m is outside the {_fmt(limit)} m "
                                    "building ([site])")
    return problems


def _cross_checks(cfg: ConfigFile, prefix: str, bad: set[str]) -> list[str]:
    """Keys that are fine alone but not together. They run beside the keys' own checks, on the keys that passed:
    a key refused already (in bad, its line said why) is not called missing, and a check that needs it waits."""
    problems = []
    site = cfg.site
    dims = {"length_m": site.length_m, "width_m": site.width_m, "height_m": site.height_m}
    given = [k for k, v in dims.items() if v is not None or f"site.{k}" in bad]
    if given and len(given) < 3:
        missing = [k for k in dims if k not in given]
        problems.append(f"{prefix}{_where('site', missing[0])}: missing (a building needs length_m, width_m and "
                        f"height_m together; the file gives only {', '.join(given)})")
    servo = cfg.payload.servo
    pulses = ("center_us", "min_us", "max_us")
    if any(getattr(servo, k) is not None for k in pulses) and not any(f"payload.servo.{k}" in bad for k in pulses):
        base = ServoCalibration()
        lo, mid, hi = (getattr(servo, k) if getattr(servo, k) is not None else getattr(base, k)
                       for k in ("min_us", "center_us", "max_us"))
        if not lo < mid < hi:
            key = next(k for k in ("center_us", "min_us", "max_us") if getattr(servo, k) is not None)
            problems.append(f"{prefix}{_where('payload.servo', key)}: the pulses must satisfy min_us < center_us < "
                            f"max_us, got {_fmt(lo)} < {_fmt(mid)} < {_fmt(hi)}")
    sweep = cfg.payload.sweep
    if sweep.peak_rate_rad_s is not None and servo.slew_rad_s is not None \
            and sweep.peak_rate_rad_s > servo.slew_rad_s:
        problems.append(f"{prefix}{_where('payload.sweep', 'peak_rate_rad_s')}: {_fmt(sweep.peak_rate_rad_s)} rad/s "
                        f"is faster than the servo can turn ([payload.servo] slew_rad_s = {_fmt(servo.slew_rad_s)})")
    if cfg.payload.stream is not None:
        try:
            parse_stream_url(cfg.payload.stream)
        except ValueError as exc:
            problems.append(f"{prefix}{_where('payload', 'stream')}: {exc}")
    return problems + _pile_checks(cfg, prefix, bad)


def parse_config(data: Mapping[str, Any], source: str = "config", base_dir: Path | None = None) -> ConfigFile:
    """A ConfigFile from TOML's tables (or the header's ``config`` record).

    Args:
        data: the decoded TOML document.
        source: how the lines name the file (its path).
        base_dir: relative paths are taken from here (the file's folder); None keeps them as written.

    Raises:
        ConfigError: one line per unknown key, wrong type or bad value, and per keys that do not go together;
            its `config` the keys that passed.
    """
    prefix = f"{source}: "
    problems: list[str] = []
    bad: set[str] = set()
    kwargs: dict[str, Any] = {}
    for name, table in data.items():
        if name not in SECTIONS:
            what = "section" if isinstance(table, dict) else "key outside any section"
            problems.append(f"{prefix}[{name}]: unknown {what} ({_suggest(name, list(SECTIONS))})")
            continue
        if name in ARRAYS:
            cls = {f.name: f.metadata["array"] for f in fields(ConfigFile) if "array" in f.metadata}[name]
            kwargs[name] = _parse_array(cls, table, name, base_dir, problems, prefix, bad)
            continue
        cls = {f.name: f.metadata["table"] for f in fields(ConfigFile) if "table" in f.metadata}[name]
        kwargs[name] = _parse_section(cls, table, name, base_dir, problems, prefix, bad)
    cfg = ConfigFile(**kwargs, path=source)
    problems += _cross_checks(cfg, prefix, bad)  # beside the keys' own problems: every one in one report
    if problems:
        raise ConfigError(problems, cfg)
    return cfg


def load_config(path: str | os.PathLike[str]) -> ConfigFile:
    """Read and check a configuration file (module docstring).

    Raises:
        InputError (`safe_read`'s): unreadable: missing, not a regular file (a FIFO would block), too large,
            not UTF-8 (the programs exit 3: `firmware_py.core.cli.apply_config`).
        ConfigError: not TOML (the line is named), or bad content (exit 2).
    """
    name = os.fspath(path)
    try:
        raw = read_bounded(path, MAX_CONFIG_BYTES, "config file")
    except InputError:
        raise
    except OSError as exc:
        raise InputError(f"cannot read config file {name}: {exc.strerror or exc}") from exc
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"config file {name} is not UTF-8 text (byte {exc.start})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([f"{name}: not valid TOML: {str(exc).splitlines()[0]}"]) from None
    return parse_config(data, name, Path(name).resolve().parent)


# ----- writing ---------------------------------------------------------------------------------------


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)  # a JSON string is a TOML basic string
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML form for {type(v).__name__}")


def to_toml(d: Mapping[str, Any]) -> str:
    """A nested dict of sections (`ConfigFile.to_dict()`) as TOML text that `parse_config` reads back."""
    lines: list[str] = []

    def table(name: str, body: Mapping[str, Any]) -> None:
        scalars = {k: v for k, v in body.items() if not isinstance(v, Mapping)}
        subs = {k: v for k, v in body.items() if isinstance(v, Mapping)}
        if scalars or not subs:
            if lines:
                lines.append("")
            lines.append(f"[{name}]")
            lines.extend(f"{k} = {_toml_value(v)}" for k, v in scalars.items())
        for k, v in subs.items():
            table(f"{name}.{k}", v)

    for name, body in d.items():
        if isinstance(body, Mapping):
            table(name, body)
        elif isinstance(body, list | tuple):  # an array of tables
            for item in body:
                if lines:
                    lines.append("")
                lines.append(f"[[{name}]]")
                lines.extend(f"{k} = {_toml_value(v)}" for k, v in item.items())
    return "\n".join(lines) + "\n"
