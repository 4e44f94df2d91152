"""The sample-log header: what the ground station needs to turn a log into points and a volume.

One pure function builds it for every writer (the SITL's runs and the payload program on the drone),
so the keys cannot drift apart and the payload never imports `sitl`. The ground station reads:

- ``sensor``: the range error model (``range_sigma_m``, ``range_sigma_rel``, ``resolution_m``) that
  sizes its wall/roof tolerances, plus the sensor's rate, range and beam;
- ``lever_arm_body_m``, ``storage``, ``storage_frame``: the geometry of eqs. (3)-(6);
- ``servo``: the eq. (1) waveform, ``mission_id`` / ``mission``: what was flown (None when unknown);
- ``software``, ``created_utc``, ``source``: provenance.

Key order is fixed (JSON keeps it), so two writers given the same inputs write the same header.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Mapping, Sequence
from typing import Any

import firmware_py
from firmware_py.frames import StorageFrame
from firmware_py.servo_waveform import Waveform
from firmware_py.storage import Storage

SENSOR_KEYS = ("model", "rate_hz", "max_range_m", "resolution_m", "range_sigma_m", "range_sigma_rel",
               "beam_divergence_rad")
"""The ``sensor`` keys, in order: the same as `sitl.batch_sampler.LidarSpec.to_dict()`."""

LIDARLITE_V3_MODEL = "Garmin LIDAR-Lite v3"
LIDARLITE_V3_MAX_RANGE_M = 40.0
LIDARLITE_V3_RESOLUTION_M = 0.01
LIDARLITE_V3_RANGE_SIGMA_M = 0.025
"""Datasheet: +-2.5 cm below 5 m ..."""
LIDARLITE_V3_RANGE_SIGMA_REL = 0.01
"""... and ~1 % of the range beyond."""
LIDARLITE_V3_BEAM_DIVERGENCE_RAD = 0.008


def software_version() -> str:
    return f"pilescan {firmware_py.__version__}"


def utc_now_iso() -> str:
    """Creation time as the header writes it: ISO 8601, UTC, whole seconds."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def sensor_spec(rate_hz: float, *, model: str = LIDARLITE_V3_MODEL, max_range_m: float = LIDARLITE_V3_MAX_RANGE_M,
                resolution_m: float = LIDARLITE_V3_RESOLUTION_M, range_sigma_m: float = LIDARLITE_V3_RANGE_SIGMA_M,
                range_sigma_rel: float = LIDARLITE_V3_RANGE_SIGMA_REL,
                beam_divergence_rad: float = LIDARLITE_V3_BEAM_DIVERGENCE_RAD) -> dict[str, Any]:
    """The header's ``sensor`` dict (keys `SENSOR_KEYS`); defaults are the LIDAR-Lite v3 datasheet's.

    Raises:
        ValueError: a non-finite or out-of-range value (named).
    """
    if not isinstance(model, str) or not model:
        raise ValueError(f"sensor model must be a non-empty string, got {model!r}")
    for name, value, lo in (("rate_hz", rate_hz, 0.0), ("max_range_m", max_range_m, 0.0)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > lo):
            raise ValueError(f"sensor {name} must be a finite number > 0, got {value!r}")
    for name, value in (("resolution_m", resolution_m), ("range_sigma_m", range_sigma_m),
                        ("range_sigma_rel", range_sigma_rel), ("beam_divergence_rad", beam_divergence_rad)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
            raise ValueError(f"sensor {name} must be a finite number >= 0, got {value!r}")
    return {"model": model, "rate_hz": float(rate_hz), "max_range_m": float(max_range_m),
            "resolution_m": float(resolution_m), "range_sigma_m": float(range_sigma_m),
            "range_sigma_rel": float(range_sigma_rel), "beam_divergence_rad": float(beam_divergence_rad)}


def servo_header(waveform_name: str, wf: Waveform, initial_position: int) -> dict[str, Any]:
    """The header's ``servo`` dict: the eq. (1) waveform the payload drove."""
    return {"waveform": waveform_name, "shape_c": wf.shape_c, "frequency_hz": wf.frequency_hz,
            "amplitude_rad": wf.amplitude_rad, "phase_rad": wf.phase_rad, "direction": wf.direction,
            "initial_position": initial_position}


def build_log_header(*, source: str, sensor: Mapping[str, Any], lever_arm_body_m: Sequence[float],
                     waveform_name: str, waveform: Waveform, initial_position: int, storage: Storage,
                     frame: StorageFrame, mission_id: str | None = None, mission: Mapping[str, Any] | None = None,
                     created_utc: str | None = None, extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The sample-log header dict (module docstring), ready for `SampleLogWriter`.

    Args:
        source: who wrote the log, e.g. "sitl/jsbsim" or "payload".
        sensor: the ``sensor`` dict (`sensor_spec`, or the SITL's `LidarSpec.to_dict()`).
        lever_arm_body_m: (3,) sensor position from the centre of gravity in the body frame (FRD), m.
        waveform_name, waveform, initial_position: the servo sweep (`servo_header`).
        storage, frame: the building and its placement in local NED.
        mission_id, mission: what was flown, when known (None otherwise).
        created_utc: creation time; None = now (`utc_now_iso`).
        extra: further keys appended after the standard ones (they may not replace one).

    Raises:
        ValueError: a lever arm that is not 3 finite numbers, or an extra key clashing with a standard one.
    """
    lever = list(lever_arm_body_m)
    if len(lever) != 3 or not all(isinstance(v, int | float) and math.isfinite(v) for v in lever):
        raise ValueError(f"lever arm must be 3 finite numbers, got {lever_arm_body_m!r}")
    header: dict[str, Any] = {
        "software": software_version(),
        "created_utc": created_utc if created_utc is not None else utc_now_iso(),
        "source": source,
        "sensor": dict(sensor),
        "lever_arm_body_m": lever,
        "servo": servo_header(waveform_name, waveform, initial_position),
        "mission_id": mission_id,
        "mission": dict(mission) if mission is not None else None,
        "storage": storage.to_dict(),
        "storage_frame": frame.to_dict(),
    }
    for key, value in (extra or {}).items():
        if key in header:
            raise ValueError(f"extra header key {key!r} would replace a standard one")
        header[key] = value
    return header
