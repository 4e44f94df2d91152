"""Who, where, when: the survey's metadata for the report, and the one-line verdict a reader signs.

From the log header: when the log was started (``created_utc``, the payload's clock in UTC), how long the
samples span, the sensor, the software that flew, the mission and where the building stands. From the
configuration (the report's --config file or flags first, else the one the payload logged in its
``config`` record): the site's name and time zone, the operator and the aircraft. Local time needs the
site's time zone ([site] timezone, an IANA name): without it the report says "UTC only" rather than
guess from the longitude. The SHA-256 of the log file ties the report to the bytes it was made from.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import math
import zoneinfo
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ground.uncertainty import ErrorTerms, IntervalModel

HASH_CHUNK_BYTES = 1 << 20


@dataclass(frozen=True)
class SurveyInfo:
    """What the user tells the report about the survey (--site-name, --timezone, --operator, --aircraft or
    their configuration keys); None: take the logged configuration's, else unknown."""

    site_name: str | None = None
    timezone: str | None = None
    operator: str | None = None
    aircraft: str | None = None

    def __post_init__(self) -> None:
        if self.timezone is not None:
            check_timezone(self.timezone)
        for name, v in (("site name", self.site_name), ("operator", self.operator), ("aircraft", self.aircraft)):
            if v is not None and not (isinstance(v, str) and v.isprintable()):  # a terminal escape, a line break
                raise ValueError(f"the {name} must be printable text on one line, got {v!r}"[:200])


def check_timezone(name: str) -> zoneinfo.ZoneInfo:
    """The IANA zone, or ValueError in one line."""
    try:
        return zoneinfo.ZoneInfo(name)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError, TypeError):
        raise ValueError(f"{name!r} is not a time zone this computer knows (an IANA name like "
                         "\"Europe/London\")") from None


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(HASH_CHUNK_BYTES):
            h.update(chunk)
    return h.hexdigest()


def printable(v: Any) -> str | None:
    """A header's text as the report prints it: stripped, one line of printable characters; None for anything else
    (a terminal escape or a line break in a log must not reach the console, the Markdown or the PDF)."""
    return v.strip() if isinstance(v, str) and v.strip() and v.isprintable() else None



def _logged(header: Mapping[str, Any], section: str, key: str) -> str | None:
    cfg = header.get("config")
    sec = cfg.get(section) if isinstance(cfg, Mapping) else None
    return printable(sec.get(key)) if isinstance(sec, Mapping) else None


def survey_metadata(header: Mapping[str, Any], info: SurveyInfo, log_path: Path,
                    t_s: np.ndarray | None = None) -> tuple[dict[str, Any], list[str]]:
    """The report's ``metadata`` record and any warnings (a malformed time or time zone in the log)."""
    warnings: list[str] = []
    start = None
    raw = header.get("created_utc")
    if raw is not None:
        try:
            start = dt.datetime.fromisoformat(str(raw))
            if start.tzinfo is None:
                raise ValueError("no UTC offset")
            start = start.astimezone(dt.UTC)
        except ValueError:
            warnings.append(f"the log header's created_utc {str(raw)[:40]!r} is not an ISO 8601 time: survey time "
                            "unknown")
            start = None
    duration = None
    if t_s is not None and len(t_s) >= 2:
        span = float(np.nanmax(t_s) - np.nanmin(t_s))
        duration = span if math.isfinite(span) and span >= 0 else None
    tz_name = info.timezone or _logged(header, "site", "timezone")
    zone = None
    if tz_name is not None:
        try:
            zone = check_timezone(tz_name)
        except ValueError as exc:
            warnings.append(f"the logged configuration's [site] timezone: {exc}: UTC only")
            tz_name = None
    local = None if start is None or zone is None else start.astimezone(zone)
    sensor = header.get("sensor")
    meta = {
        "survey_start_utc": None if start is None else start.isoformat(timespec="seconds"),
        "survey_start_local": None if local is None else local.isoformat(timespec="seconds"),
        "timezone": tz_name,
        "local_time": "UTC only (no [site] timezone)" if tz_name is None else tz_name,
        "survey_duration_s": duration,
        "site_name": info.site_name or _logged(header, "site", "name"),
        "operator": info.operator or _logged(header, "survey", "operator"),
        "aircraft": info.aircraft or _logged(header, "survey", "aircraft"),
        "sensor": printable(sensor.get("model")) if isinstance(sensor, Mapping) else None,
        "flight_software": printable(header.get("software")),
        "log_source": printable(header.get("source")),
        "mission_id": printable(header.get("mission_id")),
        "log_file": log_path.name,
        "log_sha256": sha256_of(log_path),
    }
    return meta, warnings


_METADATA_LABELS = (
    ("site_name", "Site"), ("survey_start_utc", "Survey start (UTC)"), ("survey_start_local", "Survey start (local)"),
    ("survey_duration_s", "Logged for"), ("operator", "Operator"), ("aircraft", "Aircraft"), ("sensor", "Sensor"),
    ("flight_software", "Flight software"), ("mission_id", "Mission"), ("log_file", "Log file"),
    ("log_sha256", "Log SHA-256"), ("flights_merged", "Flights merged"),
)
_ONLY_WHEN_STATED = ("flights_merged",)
"""Rows shown only when the record has them (a merged survey's), not as "not stated"."""


def metadata_rows(meta: Mapping[str, Any] | None) -> list[tuple[str, str]]:
    """(label, value) rows for the console, Markdown and HTML; unknown values say "not stated"."""
    if not isinstance(meta, Mapping):
        return []
    rows = []
    for key, label in _METADATA_LABELS:
        v = meta.get(key)
        if v is None and key in _ONLY_WHEN_STATED:
            continue
        if key == "flights_merged" and isinstance(meta.get("flights"), list):  # each flight's log, start, time
            v = f"{v}: " + "; ".join(
                f"{f.get('log')} ({f.get('created_utc') or 'start not stated'}, {f.get('duration_s', 0) / 60:.1f} min)"
                for f in meta["flights"] if isinstance(f, Mapping))
        if key == "survey_start_local":
            v = v if v is not None else meta.get("local_time") or "UTC only"
        elif key == "survey_duration_s":
            v = None if not isinstance(v, int | float) else f"{v / 60:.1f} min"
        rows.append((label, "not stated" if v is None else str(v)))
    return rows


_LIMITS = {
    "unseen": "ground the survey never saw",  # ground: beside a pile that reaches the walls it holds material
    "interpolation": "gaps between the sweep tracks",
    "noise": "the sensor's noise",
    "blur": "the sensor's noise blurring the pile's shape",
    "sweeps": "the two sweep directions disagreeing (servo or mounting)",
    "faces": "vertical faces or overhangs",
    "pose": "the height of the drifting pose, as corrected from the building",
    "level": "the drifting altitude reference, which no floor seen pinned",
    "untied": "the drifting altitude reference over stretches of the flight no floor seen tied",
    "fitted_floor": "the fitted floor's own error (its points' noise, and pile toes within its band)",
    "earlier_survey": "the earlier survey's own interval",
}
_REMEDIES = {
    "unseen": "a re-flight over the ground never seen (pilescan-sitl plan --fill-gaps on this report), or legs "
              "nearer the walls it lies along",
    "interpolation": "sweep tracks closer together: a smaller P_traj (more legs), a slower flight or a faster sweep; "
                     "or a re-flight over the ground the points' hull bridged (pilescan-sitl plan --fill-gaps on this "
                     "report)",
    "noise": "more points a cell (a slower flight or a higher range rate), a quieter sensor setting, or a steadier "
             "pose estimate (its error is shared by the samples between two pose messages)",
    "blur": "a quieter sensor or shorter ranges (a lower flight)",
    "sweeps": "the servo's calibration and the beam's mounting checked (pilescan-payload --servo-center-us, "
              "--servo-us-per-rad, --boresight); sweeps that see the floor and the walls let the report calibrate "
              "them",
    "faces": "nothing a flight changes: a look at the places the warning names (a face or an undercut that one height "
             "per cell cannot hold)",
    "pose": "legs that see the floor or the walls' feet often (nearer the walls, strips of floor left clear), or an "
            "altitude reference that does not drift over the pile",
    "level": "a leg that sees a wall's foot or a strip of clear floor",
    "untied": "legs that see the floor along the way (farther from the walls where the pile covers their feet), or "
              "passes that cross the pile where it was seen beside the floor",
    "fitted_floor": "more floor seen (legs nearer the walls, strips of floor left clear), or --base floor where the "
                    "building's z = 0 is its floor",
    "earlier_survey": "a narrower earlier survey (its report says what would narrow it)",
}
"""What narrows each term on the next flight: the report says it under the verdict (`remedies`)."""
MIN_SHARE = 0.25
"""A term 'limits' the volume when it holds at least a quarter of the interval's variance."""


def limiting_terms(terms: ErrorTerms, model: IntervalModel, base: tuple[str, float] | None = None) -> list[str]:
    """The error terms that hold most of the interval, largest first (keys of _LIMITS). base: the base's own
    term and its 90 % half-width, added to the interval in quadrature (ground.base), when it has one."""
    scaled = {"unseen": model.unseen_m3(terms),
              "interpolation": model.k_interpolation * terms.interpolation_m3, "noise": model.k_noise * terms.noise_m3,
              "blur": model.k_blur * terms.blur_m3, "sweeps": model.k_sweeps * terms.sweeps_m3,
              "faces": model.k_faces * terms.faces_m3, "pose": model.k_pose * terms.pose_m3,
              "level": model.k_level * terms.level_m3, "untied": model.k_untied * terms.untied_m3}
    if base is not None:
        scaled[base[0]] = base[1]
    total = sum(v * v for v in scaled.values())
    if total <= 0:
        return []
    return [k for k, v in sorted(scaled.items(), key=lambda kv: -kv[1]) if v * v / total >= MIN_SHARE]


def remedies(limits: list[str]) -> list[str]:
    """What would narrow the interval on the next flight, one line for each limiting term (`limiting_terms`), in
    their order."""
    return [_REMEDIES[k] for k in limits]


def verdict(volume: float, interval: tuple[float, float] | list[float] | None, limits: list[str],
            where_unseen: str | None, n_warnings: int, unit: str = "m³", per_m3: float = 1.0,
            other: dict | None = None) -> str:
    """One sentence: the volume, its 90 % interval and what limits it (in the display unit), and the survey's other
    reading when it has one (report.json's `volume_other_reading`: the volume under a condition the data cannot
    rule out, `ground.volume_warnings.open_floor_reading`)."""
    v = volume / per_m3
    head = f"{v:,.0f} {unit}" if abs(v) >= 100 else f"{v:,.1f} {unit}"
    if interval is None:
        return head + " (no interval: the survey's errors could not be estimated)"
    lo, hi = (x / per_m3 for x in interval)
    fmt = ",.0f" if abs(v) >= 100 else ",.1f"
    words = []
    for k in limits:
        w = _LIMITS[k]
        if k == "unseen" and where_unseen:
            w += f" near {where_unseen}"
        words.append(w)
    out = f"{head} (90 % interval {lo:{fmt}}–{hi:{fmt}} {unit})"
    out += f"; limited by: {'; '.join(words)}" if words else ""
    if other:
        ov = other["volume_m3"] / per_m3
        oi = other.get("volume_interval_m3")
        span = "" if not oi else f" (90 % interval {oi[0] / per_m3:{fmt}}–{oi[1] / per_m3:{fmt}} {unit})"
        out += f"; or {ov:{fmt}} {unit}{span} if {other['condition']}"
    if n_warnings:
        out += f"; {n_warnings} warning{'s' if n_warnings != 1 else ''} to read"
    return out
