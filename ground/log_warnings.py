"""The warnings one flight's log earns (`pilescan-ground report`): damage, unusable and implausible samples, spikes, a
stuck or mistimed servo, the mount, the pose and its sources, the site, a building, lever arm or floor that the
surveyor's options or the sweeps contradict. Each is one sentence saying what is wrong and what to do; they are
asked of each flight alone, whether it is reported alone or merged with others. And the line naming the sensor
noise the header states (`sensor_noise_line`), which the report shows beside them."""

from __future__ import annotations

import numpy as np

from firmware_py.core.flag_tally import FlagTally
from firmware_py.core.header import header_boresight
from firmware_py.core.samplelog import SampleLog
from firmware_py.core.sensor_noise import HEADER_KEY as NOISE_HEADER_KEY
from firmware_py.core.sensor_noise import describe_record
from firmware_py.core.storage import Storage
from ground.base import FLOOR_BASE, BaseKind
from ground.building_check import size_warning
from ground.consistency import MAX_SWEEP_DISAGREEMENT_M
from ground.floor_check import fall_warning, floor_warning
from ground.plausibility import MAX_GAP_S, in_time
from ground.pose_correction import PoseCorrection
from ground.pose_source_check import pose_source_warnings
from ground.pose_warnings import describe as describe_pose
from ground.pose_warnings import unanchored_warning as pose_unanchored_warning
from ground.pose_warnings import unconstrained_warning as pose_unconstrained_warning
from ground.pose_warnings import wall_warning as pose_wall_warning
from ground.self_calibration import MountEstimate, describe
from ground.servo_timing import Resimulated
from ground.site_check import header_site, site_mismatches
from ground.surface import grid_volume
from ground.survey import ReportOptions, Survey
from ground.uncertainty import DEFAULT_INTERVAL_MODEL

HIGH_EXCLUDED_FRACTION = 0.5
"""Above this share of a log's samples flagged unusable by the payload, the report says how many and why."""


def sensor_noise_line(header: dict) -> str:
    """What the log header says the sensing carried (a simulated survey's ``sensor_noise`` record)."""
    rec = header.get(NOISE_HEADER_KEY)
    return "none stated in the log header" if rec is None else describe_record(rec)


def cut_short_warning(log: SampleLog) -> str:
    """A log its writer never closed (no end block): the payload (or `listen`) stopped in flight, so the survey covers
    only the part flown before, and the rest of the floor is filled or missing whatever the blocks' state."""
    t = in_time(log.samples["t_s"])
    span = f" ({float(t[-1] - t[0]):,.0f} s of samples)" if len(t) > 1 else ""
    return ("the sample log was not closed: its writer (the payload; `listen` for a live log) stopped before it "
            "finished the log (a power cut, a crash or a full card), so it holds the flight up to its last whole "
            f"block{span} and the survey covers only what was flown by then: the volume and its interval are of that "
            "part, the rest of the floor filled or missing")


def unexplained_structure_warning(mount: MountEstimate | None, pose: PoseCorrection | None) -> str | None:
    """The floor and walls stay off their planes and nothing applied explains it: the mount's self-calibration or the
    pose correction found them off beyond what it can fit, and neither corrected anything. Either one's finding is
    enough (a self-calibration that found its parameters unobservable has explained nothing: measured, a header
    boresight 17 deg wrong read 18.8 % high with no word but a wide interval). None: a correction was applied, or
    neither found the structure off (None for either: not run)."""
    if (mount is not None and mount.any_applied) or (pose is not None and pose.applied):
        return None
    found = [(name, x) for name, x in (("self-calibration", mount), ("pose correction", pose))
             if x is not None and x.unexplained]
    if not found:
        return None
    why = "; ".join(f"{name}: {(x.reason or '').removeprefix('not applied: ')}" for name, x in found)
    if mount is not None and pose is not None:
        tried = "neither the mount's self-calibration nor the pose correction explains it"
    elif mount is not None:
        tried = "the mount's self-calibration does not explain it (the pose correction was off)"
    else:
        tried = "the pose correction does not explain it (the mount's self-calibration was off)"
    return (f"the building's floor and walls do not sit on their planes, and {tried} ({why}): check the log header's "
            "boresight, lever arm and building frame against the drone, and the servo's lag (a servo answering its "
            "pulses milliseconds later than the payload's servo model puts the two sweep directions' points apart); "
            "do not trust this volume until they are right")


def lever_change_warning(mount: MountEstimate | None, lever_m: np.ndarray | None,
                         pose: PoseCorrection | None = None) -> str | None:
    """The floor and walls say the lever arm is off, not the mount (`MountEstimate.lever_change_m`) nor a drifting pose
    (`PoseCorrection.lever_change_m`, forward and right): which lever arm they fit, for the surveyor to check against
    the drone and to report again with. None: they do not say so."""
    if mount is not None and mount.lever_change_m is not None:
        change = np.asarray(mount.lever_change_m, dtype=float)
        done = ("any mount correction, so none was applied and the volume is placed with the lever arm as entered: "
                "check the lever arm against the drone and report again with the one measured")
    elif pose is not None and pose.lever_change_m is not None:
        change = np.r_[np.asarray(pose.lever_change_m, dtype=float), 0.0]
        done = ("a drifting pose, so the points are placed with the lever arm they fit instead of a drift's correction "
                "(which follows it leg by leg, and on slopes and through turns gets it wrong): check the lever arm "
                "against the drone")
    else:
        return None
    dx, dy, dz = (round(100.0 * v, 1) + 0.0 for v in change)  # + 0.0: no "-0.0"
    try_m = "" if lever_m is None else " (the lever arm they fit: `--lever-arm " + " ".join(
        f"{v:.3f}" for v in np.round(np.asarray(lever_m, dtype=float) + change, 3) + 0.0) + "`)"
    return (f"the building's floor and walls sit on their planes with the LiDAR's lever arm moved by {dx:+.1f}, "
            f"{dy:+.1f}, {dz:+.1f} cm (forward, right, down) as well as with {done}{try_m}")


def log_warnings(survey: Survey, log: SampleLog, opts: ReportOptions) -> list[str]:
    """What one log's own checks found (damage, unusable and implausible samples, spikes, a stuck or mistimed
    servo, the mount, the pose, the site): per flight, whether the flight is reported alone or merged."""
    warnings = []
    why = header_site(log.header or {})[1]
    if why is not None:
        warnings.append(why)
    if log.blocks_corrupt or log.blocks_truncated:
        warnings.append(f"sample log damaged: {log.blocks_corrupt} corrupt and {log.blocks_truncated} "
                        f"truncated block(s) skipped ({log.bytes_skipped} bytes)")
    if log.closed_cleanly is False:
        warnings.append(cut_short_warning(log))
    if survey.cloud.n_samples and survey.cloud.n_excluded / survey.cloud.n_samples > HIGH_EXCLUDED_FRACTION:
        tally = FlagTally()
        tally.add(log.samples["flags"])
        warnings.append(f"{survey.cloud.n_excluded} of {survey.cloud.n_samples} samples unusable "
                        f"(by their flags: {tally.describe()}; implausible records are counted apart)")
    found = dict(survey.implausible or {})
    if n_late := found.pop("time", 0):
        warnings.append(f"{n_late} samples left out because their times do not fit the log's clock (not finite, out "
                        f"of sequence, or outside its longest stretch without a step back or a pause over "
                        f"{MAX_GAP_S / 60:.0f} min): the payload's clock is monotonic, so these records are damaged or "
                        "from another log")
    n_implausible = sum(found.values())
    if n_implausible:
        parts = ", ".join(f"{n} {what.replace('_', ' ')}" for what, n in found.items() if n)
        warnings.append(f"{n_implausible} samples left out as implausible for the logged sensor, sweep and building "
                        f"({parts} beyond the header's limits): damaged or forged records")
    if survey.despike_unavailable:
        warnings.append(f"despiking did not run: {survey.despike_unavailable}")
    if survey.cloud.n_servo_suspect:
        warnings.append(f"{survey.cloud.n_servo_suspect} samples left out: in those sweep periods the ranges did not "
                        "move like a swept beam's (servo stuck or slow?)")
    st = survey.servo_timing
    if survey.servo_retimed and st is not None and st.building_shift_m is not None:
        warnings.append(f"the servo was re-timed from the floor and walls: it reaches each logged angle "
                        f"{st.delay_s * 1e3:+.1f} ms after the log says, which moved their points "
                        f"{st.building_shift_m * 100:.1f} cm (RMS) the two sweep directions opposite ways; the samples "
                        "were re-timed by it. Measure the servo's lag again (the payload's [payload.servo] lag_s) "
                        "before the next flight")
    elif survey.servo_retimed and st is not None:
        how = (f"it answers pulses {st.delay_s * 1e3:.0f} ms late and slews at {st.gain * 100:.0f} % of its "
               "calibrated rate" if st.model == Resimulated.name else
               f"its shaft trails the firmware's model by {st.delay_s * 1e3:.0f} ms and swings {st.gain * 100:.0f} % "
               "as far")
        refined = ("" if st.refined_s is None else
                   f"; the floor and walls refined the sweeps' {(st.delay_s - st.refined_s) * 1e3:.0f} ms to "
                   f"{st.delay_s * 1e3:.1f} ms")
        warnings.append(f"the servo's angles were re-estimated from the sweeps ({st.model}): {how} (the two sweep "
                        f"directions disagreed by {st.disagreement_before_m:.2f} m, now "
                        f"{st.disagreement_after_m:.2f} m{refined}); recalibrate the servo before the next flight")
    if survey.cloud.n_spikes:
        warnings.append(f"{survey.cloud.n_spikes} isolated range spikes left out: samples that disagreed with both "
                        "time-neighbours while those agreed (garbage or glitch readings)")
    if survey.sweep_disagreement_m is not None and survey.sweep_disagreement_m > MAX_SWEEP_DISAGREEMENT_M:
        warnings.append(f"the two sweep directions disagree by {survey.sweep_disagreement_m:.2f} m (median per cell): "
                        "the servo's angles are wrong (slower or laggier than its calibration?); do not trust "
                        "this volume" + (f" (re-estimating its timing got them no closer than "
                                         f"{st.disagreement_after_m:.2f} m)" if st is not None else ""))
    if survey.mount is not None and survey.mount.any_applied:
        warnings.append(describe(survey.mount, header_boresight(log.header or {})))
    elif (lever := lever_change_warning(survey.mount, survey.lever_arm_body_m)) is not None:
        warnings.append(lever)
    else:
        unexplained = unexplained_structure_warning(survey.mount, survey.pose)
        if unexplained is not None:
            warnings.append(unexplained)
    if survey.pose is not None and survey.pose.applied and survey.pose.lever_change_m is not None:
        warnings.append(lever_change_warning(None, survey.lever_arm_body_m, survey.pose))
    elif survey.pose is not None and survey.pose.applied:
        warnings += [w for w in (describe_pose(survey.pose), pose_unconstrained_warning(survey.pose),
                                 pose_unanchored_warning(survey.pose), pose_wall_warning(survey.pose)) if w]
    rf = survey.rangefinder
    if rf is not None and rf.applied:
        warnings.append(rf.describe())
    warnings += pose_source_warnings(log.header or {}, survey.pose, opts.pose_correction,
                                     rangefinder_applied=rf is not None and rf.applied,
                                     rangefinder_reason=rf.reason if rf is not None and not rf.applied else None)
    warnings += site_mismatches(log.header or {}, opts.site, storage_given=opts.storage is not None)
    doubtful = survey.mount is not None and survey.mount.unexplained and not survey.mount.any_applied
    warnings += [w for w in (storage_warning(log.header or {}, survey.storage),
                             size_warning(survey.building, survey.storage, mount_doubtful=doubtful),
                             lever_arm_warning(log.header or {}, opts.lever_arm_m)) if w]
    if survey.pose is not None and survey.pose.applied:
        w = fall_warning(survey.floor, float(np.abs(survey.pose.values[:, 2]).max(initial=0.0)))
        if w:
            warnings.append(w)
    if opts.base.kind is BaseKind.FLOOR and survey.lever_arm_body_m is not None:  # a fitted floor, or an earlier
        # survey flown alike, takes the height out
        w = floor_warning(survey.floor, survey.storage, survey.lever_arm_body_m, flight_half_m3(survey))
        if w:
            warnings.append(w)
    return warnings


def flight_half_m3(survey: Survey) -> float | None:
    """The half-width of the volume's 90 % interval over the floor z = 0 from this survey's own terms (None: none)."""
    if survey.errors is None:
        return None
    lo, hi = FLOOR_BASE.interval_m3(grid_volume(survey.heights, survey.grid), survey.errors.terms,
                                    DEFAULT_INTERVAL_MODEL)
    return (hi - lo) / 2.0


def lever_arm_warning(header: dict, lever_arm_m: tuple[float, float, float] | None) -> str | None:
    """When the report's lever arm is not the log header's (--lever-arm): said, since the flight logged the other."""
    if lever_arm_m is None:
        return None
    logged = header.get("lever_arm_body_m")
    said = (f"the log header's {', '.join(f'{float(v):g}' for v in logged)} m"
            if isinstance(logged, list) and len(logged) == 3 else "the log header's")
    if isinstance(logged, list) and np.allclose(np.asarray(logged, dtype=float), lever_arm_m, rtol=0, atol=1e-9):
        return None
    return (f"the LiDAR's lever arm is taken as {', '.join(f'{v:g}' for v in lever_arm_m)} m (--lever-arm, body "
            f"forward, right, down), not {said}")


def storage_warning(header: dict, storage: Storage) -> str | None:
    """When the report's building is not the log header's (--storage): said, since the flight was flown and logged
    with the other."""
    try:
        logged = Storage.from_dict(header.get("storage"))
    except (KeyError, TypeError, ValueError):
        return None
    if logged == storage:
        return None
    return (f"the building is taken as {storage.length_m:g} x {storage.width_m:g} x {storage.height_m:g} m "
            f"(--storage), not the log header's {logged.length_m:g} x {logged.width_m:g} x {logged.height_m:g} m")
