"""The sample-log header: what the ground station needs to turn a log into points and a volume.

One pure function builds it for every writer (the SITL's runs and the payload program on the drone),
so the keys cannot drift apart and the payload never imports `sitl`. The ground station reads:

- ``sensor``: a `firmware_py.core.sensor.RangefinderSpec` as a dict: the range error model
  (``range_sigma_m``, ``range_sigma_rel``, ``resolution_m``) that sizes its wall/roof tolerances, plus
  the sensor's rate, range and beam;
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

from firmware_py.core.frames import StorageFrame
from firmware_py.core.sensor import LIDARLITE_V3
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
        sensor: the ``sensor`` dict (`sensor_spec`, or any `RangefinderSpec.to_dict()`).
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
