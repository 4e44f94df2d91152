"""What the report says about where the autopilot's pose came from, and the warnings that follow from it.

The log header keeps the autopilot's EKF3 source parameters as the payload read them at start
(`firmware_py.core.pose_source`). Two of those choices can bias a volume in a way the building alone may not
reveal, so the report names them when nothing corrected them:

- the height from the downward rangefinder (`EK3_SRC1_POSZ` = 2, or `EK3_RNG_USE_HGT` >= 0): over a stockpile
  it is the height above the pile, so the logged height is lower than the true one by a share of the pile under
  the vehicle, and the pile is placed that much low. The pose correction takes it out where the sweeps tie the
  height to the floor; where it did not correct the height, nothing in the interval measures it (a flight over a
  pile that hides its floor read 29 % low with a +-5 % interval: docs/design-notes.md);
- a horizontal position integrated from velocity (optical flow, wheel encoders) with the correction switched off.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from firmware_py.core.pose_source import HEADER_KEY, HeightSource, PoseSource, number
from ground.pose_correction import PoseCorrection
from ground.rangefinder_height import RangefinderShare

NOT_STATED = "not stated in the log"
"""The report's pose source when the log has no record (an older payload, or an autopilot that did not answer)."""


def pose_source_line(header: Mapping[str, Any], share: RangefinderShare | None = None) -> str:
    """The report's one line on the pose's source, and, when the log did not say that the height came from the
    downward rangefinder but the report measured its share all the same (`RangefinderShare.source_stated`), what it
    found: a surveyor reading "not stated" should know the height was checked for it."""
    source = PoseSource.from_header(header)
    line = NOT_STATED if source is None else source.describe()
    if share is not None and not share.source_stated:
        found = (f"{share.share:.2f} ± {share.sigma:.2f}, taken out" if share.applied else
                 f"none taken out ({share.reason})" if share.reason else "none taken out")
        line += f"; the downward rangefinder's share of the height measured all the same: {found}"
    return line


def autopilot_params(header: Mapping[str, Any]) -> dict[str, float | None] | None:
    """The header's record (report.json keeps it for whoever reads the parameters themselves): a parameter's value
    as a number, None where the record holds anything else (report.json is strict JSON: no NaN)."""
    record = header.get(HEADER_KEY)
    if not isinstance(record, Mapping) or not record:
        return None
    return {str(k): number(v) for k, v in record.items()}


def _height_corrected(pose: PoseCorrection | None) -> bool:
    return pose is not None and pose.applied and bool(pose.height_sigma_m)


def pose_source_warnings(header: Mapping[str, Any], pose: PoseCorrection | None, correction_on: bool,
                         rangefinder_applied: bool = False, rangefinder_reason: str | None = None) -> list[str]:
    """The warnings the autopilot's pose sources call for, given what the pose correction did (None: not run),
    whether the rangefinder's share of the height was taken out (`ground.rangefinder_height`), and why not when the
    step ran and did not (rangefinder_reason: the surveyor is told what the report could not do, and what did the
    work instead)."""
    source = PoseSource.from_header(header)
    if source is None or not source.known:
        return []
    out = []
    if source.height_from_rangefinder and not _height_corrected(pose) and not rangefinder_applied:
        how = ("as its height source" if source.height is HeightSource.RANGEFINDER else
               f"below {source.rangefinder_height_pct:g} % of its range") + f" ({source.rangefinder_height_setting})"
        if not correction_on:
            why = "the pose correction is off (--no-pose-correction)"
        else:
            reason = pose.reason if pose is not None and not pose.applied and pose.reason else None
            reason = reason.removeprefix("not applied: ") if reason else None
            why = "the building did not correct the height" + (f" ({reason})" if reason else "")
            if rangefinder_reason:
                why += f", nor could the crossings measure the rangefinder's share to take out: {rangefinder_reason}"
        out.append(f"the autopilot's height came from its downward rangefinder {how}: over a stockpile that is the "
                   "height above the pile, not the floor, so the logged height is low by a share of the pile under "
                   f"the vehicle and the pile is placed that much low; {why}, and the 90 % interval does not "
                   "include it. Read the volume as possibly low; fly with the barometer as the height source "
                   "(EK3_SRC1_POSZ = 1, EK3_RNG_USE_HGT = -1) or where the sweeps see the floor")
    elif source.height_from_rangefinder and not rangefinder_applied and rangefinder_reason:
        out.append("the autopilot's EKF took its height from the downward rangefinder, but the crossings did not "
                   f"measure a share of it to take out: {rangefinder_reason}; the height was corrected from the "
                   "floor and walls instead")
    if source.horizontal_drifts and not correction_on:
        out.append(f"the autopilot's position was {source.horizontal_words()}, "
                   "which drifts with the distance flown, and the pose correction is off (--no-pose-correction): "
                   "points may lie decimetres to metres from where they were seen")
    return out
