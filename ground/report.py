"""The ground pipeline end to end: sample log -> cloud -> surface -> volume -> report files. Its two records are in
`ground.survey`, a log's warnings in `ground.log_warnings`, the figures' jobs in `ground.report_figures`."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np
from numpy.lib.recfunctions import repack_fields

from firmware_py.core.cli import NoVolumeError, UserError, reading_input
from firmware_py.core.frames import Boresight, StorageFrame
from firmware_py.core.header import header_boresight
from firmware_py.core.pose_source import PoseSource
from firmware_py.core.rundir import SAMPLES_FILE, TRUTH_FILE, OutputFolder, check_free
from firmware_py.core.safe_read import InputError, json_number, json_object, load_json
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD, SampleLog, read_samplelog
from firmware_py.core.site import Site, site_difference
from firmware_py.core.storage import Storage
from firmware_py.core.surface_file import SURFACE_FILE
from firmware_py.core.version import software_version
from firmware_py.core.waveform import MAX_FREQUENCY_HZ
from ground.base import FLOOR, FLOOR_BASE, BaseKind, fitted_floor_base, rebased_terms, survey_base
from ground.blas_threads import one_blas_thread
from ground.building_check import SizeCheck, check_building
from ground.consistency import MAX_SWEEP_DISAGREEMENT_M, sweep_disagreement_m
from ground.crossing_cells import not_the_pile
from ground.deliverable import add_deliverable
from ground.despike import SpikeThreshold, why_no_threshold
from ground.echo_reach import echo_reach, echo_record, echo_warning
from ground.exports.formats import EXPORT_FILES
from ground.exports.write import check_exports, write_exports
from ground.figure_jobs import cores_available
from ground.floor_check import FloorLevel, floor_other_reading, measure_floor
from ground.log_warnings import log_warnings, sensor_noise_line
from ground.metadata import printable, sha256_of
from ground.piles import PILES_CSV, write_piles_csv
from ground.plane_stretches import Beams, TimingSplit, beams, nearest_plane, placed_beams, planes, stretch_floor_m
from ground.plausibility import PlausibilityLimits, implausible, in_time, out_of_time, without_implausible
from ground.pointcloud import N_SIGMA as FLOOR_N_SIGMA
from ground.pointcloud import (
    Cloud,
    SensorErrorModel,
    cloud_from_samples,
    merge_clouds,
    posed_beams,
    stretch_sigma_m,
    structure_mask,
    structure_n_sigma,
)
from ground.pointing_bias import along_beam_bias_m, grid_normals, sweep_directions
from ground.pose_correction import (
    PoseCorrection,
    apply_pose_correction,
    estimate_pose_correction,
    timing_as_logged,
    with_closest_wall,
)
from ground.pose_decisions import explains_more
from ground.pose_height import crossings_misfit_m
from ground.pose_knots import BAND, KNOT_SWEEPS, PoseCorrectionOptions
from ground.pose_source_check import autopilot_params, pose_source_line
from ground.rangefinder_height import RangefinderShare, estimate_share
from ground.report_figures import write_outputs
from ground.self_calibration import (
    N_SIGNIFICANT,
    DriftNuisance,
    MountEstimate,
    apply_mount,
    estimate_mount,
)
from ground.servo_timing import (
    LAST_BUT_ONE_STEP_S,
    Resimulated,
    ServoTiming,
    ShiftScale,
    estimate_servo_timing,
    sweep_center_rad,
)
from ground.site_check import HEADING_TOLERANCE_DEG, SITE_TOLERANCE_M, header_site
from ground.smoothing import (
    DEFAULT_SMOOTHING,
    CubicLimit,
    NodeSlopes,
    SmoothingOptions,
    cloud_vertical_sigma_m,
)
from ground.surface import (
    CONTACT_POLICIES,
    DEFAULT_CELL_M,
    MEASURED_MAX_CELL_M,
    STRIP_POLICIES,
    Grid,
    clip_to_building,
    fill_empty,
    fit_heights,
    fit_surface,
    grid_volume,
    reconstructed_ratio_pct,
    volume_error_pct,
)
from ground.surface_file import SavedSurface, load_surface, save_surface
from ground.survey import ReportOptions, Survey
from ground.sweep_heights import N_SIGMA as SWEEP_N_SIGMA
from ground.sweep_heights import sweep_heights
from ground.uncertainty import (
    DEFAULT_INTERVAL_MODEL,
    INTERVAL_LEVEL,
    ErrorTerms,
    SurveyErrors,
    face_spread_m,
    point_sigma_m,
    pose_term_m3,
    scatter_sigma_m,
    shared_draws,
    survey_errors,
)
from ground.unseen import free_space_ceilings_m, passed_over
from ground.volume_warnings import (
    faces_warning,
    level_warning,
    open_floor_reading,
    open_floor_warning,
    pose_warning,
    unseen_warning,
    wide_interval_warning,
)
from ground.wall_contact import WallContacts, contact_ceiling_m, contact_nodes, wall_contacts
from ground.wall_strip import contradicted_strip

LOW_COVERAGE_PCT = 95.0
GRID_BYTES_PER_CELL = 200
"""Peak memory of the report per grid cell, measured with its figures (cell centres, Delaunay lookups, fit,
fill, counts, plots): 205 B at 0.05 m and 211 B at 0.03 m cells on the golden log (peak RSS less the 150 MB
of a 1 m-cell run); `--cell 0.01` (24 M cells) peaked at 4.7 GB, 196 B a cell."""
def locate_inputs(source: str | Path) -> tuple[Path, Path | None]:
    """A run directory (log + truth.json) or a bare sample log."""
    src = Path(source)
    if src.is_dir():
        log = src / SAMPLES_FILE
        if not log.exists():
            raise UserError(f"{src} is a directory without a {SAMPLES_FILE} sample log")
        truth = src / TRUTH_FILE  # present but not a regular file (a FIFO, a directory): refused when read
        return log, truth if truth.exists() else None
    if not src.exists():
        raise UserError(f"no such run directory or sample log: {src}")
    return src, None


def read_truth_volume(truth_path: Path | None) -> float | None:
    """true_volume_m3 of a run's truth.json (bounded, strict read: `firmware_py.core.safe_read`)."""
    if truth_path is None:
        return None
    try:
        v = json_object(load_json(truth_path, "truth file"), f"truth file {truth_path}").get("true_volume_m3")
        if v is None:
            return None
        return json_number(v, f"{truth_path}: true_volume_m3 (0 for an empty building)", minimum=0.0)
    except InputError as exc:
        raise UserError(str(exc)) from None


@dataclass(frozen=True)
class LogInput:
    """A survey's log, where it and its truth.json are, and the geometry its header states."""

    log: SampleLog
    log_path: Path
    truth_path: Path | None
    storage: Storage
    frame: StorageFrame
    lever_arm_body_m: np.ndarray


def read_log_input(source: str | Path) -> LogInput:
    """The log of a run directory or sample log with its header's geometry; one-line UserError for a log
    without samples. Call within `reading_input()`, which turns the readers' own errors into one line."""
    log_path, truth_path = locate_inputs(source)
    log = read_samplelog(log_path)
    storage, frame, lever = header_geometry(log, log_path)
    if len(log.samples) == 0:
        raise UserError(f"{log_path}: no samples could be read ({log.blocks_corrupt} corrupt block(s))")
    return LogInput(log, log_path, truth_path, storage, frame, lever)


def header_geometry(log: SampleLog, path: Path) -> tuple[Storage, StorageFrame, np.ndarray]:
    """Storage, frame and lever arm from the log header, with one clear error when unusable."""
    if log.header is None:
        raise UserError(f"{path}: the log header is missing or corrupt, so the storage and sensor "
                        "geometry are unknown")
    log.require_supported_format(str(path))
    h = log.header
    try:
        storage = Storage.from_dict(h["storage"])
        frame = StorageFrame.from_dict(h["storage_frame"])
        lever_raw = h.get("lever_arm_body_m", [0.0, 0.0, 0.0])
        if not isinstance(lever_raw, list) or any(isinstance(v, bool) or not isinstance(v, int | float)
                                                   for v in lever_raw):
            raise ValueError(f"lever_arm_body_m must be a list of numbers, got {lever_raw!r}"[:200])
        lever = np.asarray(lever_raw, dtype=float)
    except KeyError as exc:
        raise UserError(f"{path}: log header lacks a usable {exc}") from None
    except (TypeError, ValueError) as exc:
        raise UserError(f"{path}: log header storage, storage_frame or lever_arm_body_m is malformed: {exc}") from None
    if lever.shape != (3,) or not np.all(np.isfinite(lever)):
        raise UserError(f"{path}: log header lever_arm_body_m must be 3 finite numbers")
    try:
        SensorErrorModel.from_header(h)
        header_boresight(h)
    except ValueError as exc:
        raise UserError(f"{path}: {exc}") from None
    return storage, frame, lever


# ----- several flights of one survey (`pilescan-ground report RUN1 RUN2 ... --out DIR`) -------------------

TRUTH_TOLERANCE_REL = 1e-9
"""Runs of one survey carry one true volume (the simulator writes the same pile's): they agree to rounding."""


@dataclass(frozen=True)
class Flight:
    """One flight of a merged survey: its log and its own survey (the per-log steps applied to it alone)."""

    inp: LogInput
    survey: Survey


def survey_mismatch(inputs: Sequence[LogInput]) -> str | None:
    """Why these logs are not flights of one survey (another building, site, storage frame or sensor, or one
    log twice), or None."""
    first = inputs[0]
    h0 = first.log.header or {}
    seen = {sha256_of(first.log_path): first.log_path}
    for inp in inputs[1:]:
        h = inp.log.header or {}
        where = f"{first.log_path} and {inp.log_path}"
        digest = sha256_of(inp.log_path)
        if digest in seen:
            return f"{seen[digest]} and {inp.log_path} are the same log: each flight's log once"
        seen[digest] = inp.log_path
        a, b = first.storage, inp.storage
        if max(abs(a.length_m - b.length_m), abs(a.width_m - b.width_m), abs(a.height_m - b.height_m)) \
                > SITE_TOLERANCE_M:
            return f"{where} are surveys of different buildings ({a} and {b})"
        s0, s1 = header_site(h0)[0], header_site(h)[0]
        if s0 is not None and s1 is not None:
            why = site_difference(Site.from_dict(s0), Site.from_dict(s1))
            if why is not None:
                return f"{where} are surveys of different buildings: {why}"
        else:  # no site to tie them: their storage frames must be one
            f0, f1 = first.frame, inp.frame
            turn = (math.degrees(f0.heading_rad - f1.heading_rad) + 180.0) % 360.0 - 180.0
            if np.max(np.abs(np.subtract(f0.origin_ned_m, f1.origin_ned_m))) > SITE_TOLERANCE_M \
                    or abs(turn) > HEADING_TOLERANCE_DEG:
                return f"{where} have different storage frames (and no site record to relate them)"
        m0, m1 = ((x.get("sensor") or {}).get("model") if isinstance(x.get("sensor"), dict) else None
                  for x in (h0, h))
        if m0 != m1:
            return f"{where} were flown with different sensors ({m0} and {m1})"
    return None


def merged_truth(truths: Sequence[float | None], inputs: Sequence[LogInput]) -> float | None:
    """The one true volume the runs state (bare logs state none); UserError when two differ."""
    stated = [(t, i.log_path) for t, i in zip(truths, inputs, strict=True) if t is not None]
    for t, where in stated[1:]:
        if abs(t - stated[0][0]) > TRUTH_TOLERANCE_REL * max(1.0, abs(t), abs(stated[0][0])):
            raise UserError(f"the runs' true volumes differ ({stated[0][0]:,.3f} m³ for {stated[0][1]}, {t:,.3f} m³ "
                            f"for {where}): not flights over one pile")
    return stated[0][0] if stated else None


def merged_survey(flights: Sequence[Flight], opts: ReportOptions) -> Survey:
    """One survey of several flights: each flight's cloud as its own log made it (despiked, sweep-checked,
    re-timed, self-calibrated, pose-corrected), merged and surfaced by `survey_of_cloud` like one log's."""
    inp = flights[0].inp
    err = SensorErrorModel.from_header(inp.log.header or {})
    merged = survey_of_cloud(merge_clouds([f.survey.cloud for f in flights]), inp.storage, opts, err)
    poses = [f.survey.pose for f in flights]
    merged = with_pose_term(merged, least_certain_height(poses), least_certain_level(poses),
                            least_certain_untied(poses))
    counts = [f.survey.implausible for f in flights if f.survey.implausible is not None]
    implausible = None if not counts else {k: sum(c.get(k, 0) for c in counts) for k in dict.fromkeys(
        k for c in counts for k in c)}
    return replace(merged, implausible=implausible,
                   despike_unavailable=next((f.survey.despike_unavailable for f in flights
                                             if f.survey.despike_unavailable), None))


def least_certain_height(poses: Sequence[PoseCorrection | None]) -> PoseCorrection | None:
    """The flights' corrected pose whose height's standard error is largest (None: no flight's height corrected): a
    merged survey's pose term. Each flight's height errs on its own, and a merged cell's height is a weighted mean
    of the flights' points there, whose error's standard deviation is at most the largest flight's (Minkowski)."""
    return _least_certain(poses, lambda p: p.height_sigma_m if p is not None and p.applied else None)


def _least_certain(poses: Sequence[PoseCorrection | None],
                   sigma_of: Callable[[PoseCorrection | None], float | None]) -> PoseCorrection | None:
    """The pose whose sigma (sigma_of: None or 0 when it has none) is largest; None when none has one."""
    return max((p for p in poses if sigma_of(p)), key=sigma_of, default=None)


def logged_level_sigma_m(pose: PoseCorrection | None) -> float | None:
    """The standard error of the corrected height's level when it rests on the logged reference (no floor anchors it,
    `PoseCorrection.level_sigma_m`); None when a floor does, confirmed by the walls' feet or not (a floor seen only
    away from the walls has its own warning, `ground.volume_warnings.open_floor_warning`), or nothing was applied."""
    if pose is None or not pose.applied or pose.open_floor_shift_m is not None:
        return None
    return pose.level_sigma_m


def least_certain_level(poses: Sequence[PoseCorrection | None]) -> PoseCorrection | None:
    """The flights' corrected pose whose level rests on the logged reference with the largest standard error (None:
    no flight's does): a merged survey's level term, as `least_certain_height`."""
    return _least_certain(poses, logged_level_sigma_m)


def untied_stretches_sigma_m(pose: PoseCorrection | None) -> float | None:
    """The standard error the stretches no floor tied put on the corrected height's mean (`PoseCorrection.
    untied_sigma_m`), when the level itself rests on a floor; None when the level term spans the whole flight
    (`logged_level_sigma_m`), when tied throughout, or nothing was applied."""
    if pose is None or not pose.applied or logged_level_sigma_m(pose) is not None:
        return None
    return pose.untied_sigma_m or None


def least_certain_untied(poses: Sequence[PoseCorrection | None]) -> PoseCorrection | None:
    """The flights' corrected pose whose untied stretches' standard error is largest (None: no flight has one): a
    merged survey's untied term, as `least_certain_height`."""
    return _least_certain(poses, untied_stretches_sigma_m)


def merged_log(inputs: Sequence[LogInput]) -> SampleLog:
    """The flights' logs as one: the first's header (the building, frame and sensor they share), every
    sample, the damage summed."""
    logs = [i.log for i in inputs]
    return SampleLog(logs[0].header, np.concatenate([lg.samples for lg in logs]),
                     sum(lg.blocks_ok for lg in logs), sum(lg.blocks_corrupt for lg in logs),
                     sum(lg.blocks_truncated for lg in logs), sum(lg.bytes_skipped for lg in logs),
                     sum(lg.blocks_unknown for lg in logs),
                     # closed as a whole only when no flight's log was cut short (each flight's warning says which)
                     None if any(lg.closed_cleanly is False for lg in logs) else {"records": sum(len(lg.samples)
                                                                                                 for lg in logs)})


def flight_record(f: Flight) -> dict:
    """What report.json says of one merged flight: which log (its SHA-256), when, and what it alone saw."""
    t = in_time(f.inp.log.samples["t_s"])
    t = t if len(t) else np.full(1, np.nan)  # no record in time: NaN, as a log of no samples
    h = f.inp.log.header or {}
    st = f.survey.servo_timing
    return {"log": str(f.inp.log_path), "log_sha256": sha256_of(f.inp.log_path),
            "created_utc": h.get("created_utc") if isinstance(h.get("created_utc"), str) else None,
            "t_first_s": float(np.nanmin(t)), "t_last_s": float(np.nanmax(t)),
            "duration_s": float(np.nanmax(t) - np.nanmin(t)), "mission_id": printable(h.get("mission_id")),
            "n_samples": f.survey.cloud.n_samples, "n_points_used": len(f.survey.pile_points_w),
            "coverage_ratio_pct_alone": reconstructed_ratio_pct(f.survey.heights_fit),
            "servo_retimed": f.survey.servo_retimed and st is not None,
            "self_calibration_applied": f.survey.mount is not None and f.survey.mount.any_applied,
            "pose_correction_applied": f.survey.pose is not None and f.survey.pose.applied,
            "building_measured": building_record(f.survey.building),
            "floor_measured": None if f.survey.floor is None else f.survey.floor.as_dict()}


def building_record(checks: tuple[SizeCheck, SizeCheck] | None) -> dict | None:
    """report.json's `building_measured`: each dimension the sweeps measured, against the header's (None: not
    measured, a log without the samples' times)."""
    return None if checks is None else {c.axis.value: c.as_dict() for c in checks}


def merged_metadata(report: dict, flights: Sequence[Flight]) -> None:
    """report["metadata"] of a merged survey, in place: the first flight's start, the flights' summed logged
    time, every log's file and SHA-256 (and the flights' list: `flight_record`)."""
    meta = report["metadata"]
    recs = report["flights"]
    meta["survey_duration_s"] = sum(r["duration_s"] for r in recs)
    meta["log_file"] = ", ".join(str(f.inp.log_path) for f in flights)
    meta["log_sha256"] = ", ".join(r["log_sha256"] for r in recs)
    meta["mission_id"] = ", ".join(str(r["mission_id"]) for r in recs)
    meta["flights_merged"] = len(recs)
    meta["flights"] = [{k: r[k] for k in ("log", "log_sha256", "created_utc", "duration_s")} for r in recs]


def check_grid_memory(storage: Storage, cell_m: float, max_bytes: int) -> None:
    """Refuse a cell size whose grid would need more than max_bytes (GRID_BYTES_PER_CELL a cell), naming
    the smallest cell that fits, instead of running the machine out of memory."""
    Grid(storage.length_m, storage.width_m, cell_m)  # its own checks first (cell size range, MAX_CELLS)

    def cells(c: float) -> int:
        return max(1, round(storage.length_m / c)) * max(1, round(storage.width_m / c))

    need = cells(cell_m) * GRID_BYTES_PER_CELL
    if need > max_bytes:
        fits = math.ceil(math.sqrt(storage.floor_area_m2 * GRID_BYTES_PER_CELL / max_bytes) * 1000) / 1000
        while cells(fits) * GRID_BYTES_PER_CELL > max_bytes:  # rounding to whole cells can add a row
            fits += 0.001
        raise UserError(f"a {storage.length_m:g} x {storage.width_m:g} m floor in {cell_m:g} m cells is "
                        f"{cells(cell_m):,} cells, about {need / 2**20:,.0f} MiB, more than the "
                        f"{max_bytes / 2**20:,.0f} MiB allowed: use a larger cell size, --cell {fits:.3g} or more "
                        "(or raise --max-grid-memory-mb)")


def _rangefinder_share(samples: np.ndarray, header: dict, storage: Storage, frame: StorageFrame, lever: np.ndarray,
                       opts: ReportOptions, mount: Boresight) -> tuple[np.ndarray, RangefinderShare | None]:
    """The samples with the rangefinder's share of their logged height taken out (`ground.rangefinder_height`),
    when the pose is corrected and the header says the autopilot's height came from its downward rangefinder, or does
    not say where it came from (no record: an older payload, an autopilot that did not answer; or parameters that
    name no EKF3 sources); else as they are (None: not run). Before everything that places points: the mount, the
    pose, the survey.

    Why measure when the log does not say: a `flow` flight over a pile that hides its floor read 23-31 % low without
    its record (5 of the 16 kept `flow` flights), and 0.1-0.7 % off its error-free twin with the share measured; the
    share is applied only when the crossings find it significant, which they did on none of the flights whose height
    did not follow the pile (docs/design-notes.md, "The rangefinder's share measured when the log does not say")."""
    source = PoseSource.from_header(header)
    period = _sweep_period_s(header)
    said_rangefinder = source is not None and source.height_from_rangefinder
    said_other = source is not None and source.known and not said_rangefinder
    if not opts.pose_correction or period is None or said_other:
        return samples, None
    share, placed = estimate_share(samples, lever, frame, storage, KNOT_SWEEPS * period, mount)
    return placed, share if said_rangefinder else replace(share, source_stated=False)


def _drive(header: dict, samples: np.ndarray) -> Resimulated | None:
    """The servo's drive the header states, if it can be the one behind these samples (`Resimulated.drives`);
    None: the exact servo model is not used."""
    resim = Resimulated.from_header(header)
    return resim if resim is not None and resim.drives(samples["t_s"]) else None


def _sweep_period_s(header: dict) -> float | None:
    """The servo's sweep period from the log header (None: unknown, no stuck-servo check)."""
    servo = header.get("servo")
    f = servo.get("frequency_hz") if isinstance(servo, dict) else None
    if isinstance(f, bool) or not isinstance(f, int | float):
        return None
    return 1.0 / f if np.isfinite(f) and 0 < f <= MAX_FREQUENCY_HZ else None  # a faster sweep cannot be commanded


def survey_from_samples(samples: np.ndarray, header: dict, storage: Storage, frame: StorageFrame,
                        lever: np.ndarray, opts: ReportOptions) -> Survey:
    """The computation, free of file handling (sweeps call it on samples that never touch disk).

    When the two sweep directions disagree (a servo slower or laggier than its model), the servo's
    real motion is re-estimated from the sweeps; if that brings them into agreement the survey is
    computed with the re-estimated angles (and says so), else it stays marked untrustworthy.

    BLAS runs on one thread throughout: with two of this function's threads calling a multi-threaded OpenBLAS
    at once, its sums came out in another order now and then, and the same log gave volumes 2 m³ apart
    (a drifting flight over pile 2, one run in three; docs/design-notes.md).
    """
    with one_blas_thread():
        survey, early = _survey_from_samples(samples, header, storage, frame, lever, opts)
        err = SensorErrorModel.from_header(header)
        building, floor = early.checks if early is not None and early.of(survey) else _placed_checks(survey, err)
        return replace(survey, building=building, floor=floor, lever_arm_body_m=np.asarray(lever, dtype=float))


_Placed = tuple[tuple[SizeCheck, SizeCheck] | None, FloorLevel | None]
"""The building's size (length, width; None: not measured) and the floor's level (None: not seen)."""


def _placed_checks(survey: Survey, err: SensorErrorModel) -> _Placed:
    """The building's size and the floor's level as the survey's placed cloud shows them."""
    return building_of(survey.cloud, survey.storage, err), floor_of(survey, err)


@dataclass(frozen=True)
class _EarlyChecks:
    """`_placed_checks` made on the first survey while the building's estimates ran beside it (the report waited for
    those doing nothing: about 0.1 s of a report), good for the final survey when nothing placed its points again
    (the same cloud and structure: `of`)."""

    cloud: Cloud
    structure: np.ndarray | None
    checks: _Placed

    def of(self, survey: Survey) -> bool:
        return survey.cloud is self.cloud and survey.structure is self.structure


def floor_of(survey: Survey, err: SensorErrorModel) -> FloorLevel | None:
    """The floor's level as the survey's placed cloud shows it (`ground.floor_check`), after every correction."""
    if survey.structure is None:
        return None
    return measure_floor(survey.cloud, survey.structure, survey.storage, err, survey.grid)


def building_of(cloud: Cloud, storage: Storage, err: SensorErrorModel) -> tuple[SizeCheck, SizeCheck] | None:
    """The building's length and width as the sweeps of the survey's cloud measured them (`ground.building_check`):
    placed with every correction the survey made, which within one sweep moves both walls alike."""
    return check_building(cloud.points_w, cloud.t_s, cloud.sweep_dir, cloud.dirs_w * cloud.range_m[:, None],
                          stretch_sigma_m(cloud, err), storage)


def _survey_from_samples(samples: np.ndarray, header: dict, storage: Storage, frame: StorageFrame,
                         lever: np.ndarray, opts: ReportOptions) -> tuple[Survey, _EarlyChecks | None]:
    check_grid_memory(storage, opts.cell_m, opts.max_grid_memory_bytes)
    err = SensorErrorModel.from_header(header)
    mount = header_boresight(header)  # the configured boresight: every cloud below is placed with it
    spikes = SpikeThreshold.from_header(header) if opts.despike else None
    found = implausible(samples, PlausibilityLimits.from_header(header, storage), frame)
    late = out_of_time(samples["t_s"])
    samples = without_implausible(samples, found)[~late]
    checked = {"implausible": {**found.counts(), "time": int(late.sum())},
               "despike_unavailable": why_no_threshold(header) if opts.despike and spikes is None else None}
    unlifted = samples
    samples, rangefinder = _rangefinder_share(samples, header, storage, frame, lever, opts, mount)
    checked["rangefinder"] = rangefinder
    share_taken_out = rangefinder is not None and rangefinder.applied
    # The building's estimates of the mount and the pose need the samples, not the survey: they run beside it, on the
    # second core (measured alone: survey 0.31 s, estimates 0.57 s, in sequence 0.86 s, side by side 0.61 s;
    # docs/design-notes.md). Used only when the servo is not re-timed, which changes the samples they were made from.
    with ThreadPoolExecutor(max_workers=1) as pool:
        ahead = pool.submit(_first_estimates, samples, header, storage, frame, lever, opts, err, mount,
                            share_taken_out, unlifted, opts.servo_retiming)
        survey = replace(_survey(samples, header, storage, frame, lever, opts, err, spikes, mount), **checked)
        before = survey.sweep_disagreement_m
        retime = opts.servo_retiming and before is not None and before > MAX_SWEEP_DISAGREEMENT_M
        early = None if retime else _EarlyChecks(survey.cloud, survey.structure, _placed_checks(survey, err))
        first = None if retime else ahead.result()
    # The floor and walls may call for the re-timing too: they show a servo timing offset (`structure_timing`), or
    # one as logged that only the pile's sweeps can confirm (`timing_to_confirm`).
    asked = first is not None and opts.servo_retiming and before is not None
    split = structure_timing(first.pose) if asked else None
    hint = timing_to_confirm(first.pose) if asked and split is None else None
    if first is not None and split is None and hint is None:
        return _self_calibrated(survey, samples, header, storage, frame, lever, opts, err, spikes, mount, first), early

    posed = posed_beams(samples, lever, frame, spike_threshold=spikes)  # the search changes the servo's fields only

    def disagreement(s: np.ndarray) -> float | None:  # the survey's cloud, less the stuck-servo check (range-only)
        cloud = posed.cloud(s["servo_rad"], s["sweep_dir"], mount)
        keep = ~structure_mask(cloud, storage, err)
        return sweep_disagreement_m(cloud.points_w[keep], cloud.sweep_dir[keep], survey.grid, survey.face_spread_m)[0]

    motion = _drive(header, samples) or ShiftScale(sweep_center_rad(samples["servo_rad"]))
    halves = np.random.default_rng(0).choice(np.array([-1, 1]), len(survey.pile_points_w))  # seeded: reports replay
    floor, _ = sweep_disagreement_m(survey.pile_points_w, halves, survey.grid, survey.face_spread_m)
    # The search's candidates on every core: the mount's and the pose's first estimates, on the second core until now,
    # are not used when the servo is re-timed, and have ended (the pool above waited for them).
    # The search copies its samples once a candidate: only the fields a candidate changes or is timed by.
    timed = repack_fields(samples[["t_s", "servo_rad", "sweep_dir"]])
    timing = estimate_servo_timing(timed, disagreement, before, motion, floor_m=floor or 0.0,
                                   threads=cores_available())
    if split is not None or hint is not None:
        confirmed = (timing is not None and (timing.delay_s, timing.gain) != (0.0, 1.0)
                     and timing.disagreement_after_m + (floor or 0.0) < before)
        if split is None and not confirmed:  # the offset as logged alone re-times nothing: the survey as logged
            return replace(_self_calibrated(survey, samples, header, storage, frame, lever, opts, err, spikes, mount,
                                            first), servo_timing=timing), early
        return _retimed_by_building(survey, samples, header, storage, frame, lever, opts, err, spikes, mount, first,
                                    split or hint, motion, checked, timing, confirmed, share_taken_out), early
    if timing is None or timing.disagreement_after_m > MAX_SWEEP_DISAGREEMENT_M:
        return replace(survey, servo_timing=timing), None
    timing, retimed, pose = _refined_by_building(samples, timing, motion, header, storage, frame, lever, opts, err,
                                                 mount, share_taken_out)
    fixed = _survey(retimed, header, storage, frame, lever, opts, err, spikes, mount)
    timing = _after_measured(timing, fixed)
    fixed = replace(fixed, servo_timing=timing, servo_retimed=True, **checked)
    return _self_calibrated(fixed, retimed, header, storage, frame, lever, opts, err, spikes, mount,
                            pose_as_is=pose), None


def _retimed_by_building(survey: Survey, samples: np.ndarray, header: dict, storage: Storage, frame: StorageFrame,
                         lever: np.ndarray, opts: ReportOptions, err: SensorErrorModel, spikes: SpikeThreshold | None,
                         mount: Boresight, first: _Estimates, split: TimingSplit, motion: ShiftScale | Resimulated,
                         checked: dict, searched: ServoTiming | None, confirmed: bool, share_taken_out: bool
                         ) -> Survey:
    """The survey with the servo re-timed when the floor and walls called for it (split: `structure_timing`, or
    `timing_to_confirm`'s offset as logged, which comes here only confirmed): by the search's dead time and speed
    when the pile's sweeps confirmed them (refined by the floor and walls, `_refined_by_building`), else by the offset
    the floor and walls showed, as a dead time. Kept when it leaves the floor and walls closer to their planes after
    the drift's fit than the logged timing did; else the survey as logged, with what the search found (not applied).
    Why the building judges: it called for the re-timing, and a pile's shape cannot fool it (a face seen from opposite
    sides splits the pile's sweeps as a lag does)."""
    pose = None
    if confirmed:
        timing, retimed, pose = _refined_by_building(samples, searched, motion, header, storage, frame, lever, opts,
                                                     err, mount, share_taken_out)
    else:
        retimed = motion.apply(samples, split.delay_s, 1.0)
        timing = ServoTiming(split.delay_s, 1.0, motion.name, survey.sweep_disagreement_m,
                             survey.sweep_disagreement_m, 0, building_shift_m=split.shift_m)  # after: below
    fixed = replace(_survey(retimed, header, storage, frame, lever, opts, err, spikes, mount), **checked)
    timing = _after_measured(timing, fixed)
    fixed = _self_calibrated(replace(fixed, servo_timing=timing, servo_retimed=True), retimed, header, storage,
                             frame, lever, opts, err, spikes, mount, pose_as_is=pose)
    # (a lag that left too few of their points near them for a drift's fit at all is judged by the fit it allows)
    before, after = first.pose.drift_rms_m, None if fixed.pose is None else fixed.pose.drift_rms_m
    if after is not None and (before is None or after < before):
        return fixed
    return replace(_self_calibrated(survey, samples, header, storage, frame, lever, opts, err, spikes, mount,
                                    None if first.cut_for_timing else first), servo_timing=searched)


def _after_measured(timing: ServoTiming, fixed: Survey) -> ServoTiming:
    """The timing with the sweeps' disagreement after it as the re-timed survey measured it, when its delay is not the
    search's own (the floor and walls set it, `building_shift_m`, or refined it, `refined_s`): the search only
    measured the disagreement at the delays it tried."""
    if (timing.building_shift_m is None and timing.refined_s is None) or fixed.sweep_disagreement_m is None:
        return timing
    return replace(timing, disagreement_after_m=fixed.sweep_disagreement_m)


def _refined_by_building(samples: np.ndarray, timing: ServoTiming, motion: ShiftScale | Resimulated, header: dict,
                         storage: Storage, frame: StorageFrame, lever: np.ndarray, opts: ReportOptions,
                         err: SensorErrorModel, mount: Boresight, share_taken_out: bool
                         ) -> tuple[ServoTiming, np.ndarray, PoseCorrection | None]:
    """The search's servo timing with its delay refined by the floor and walls, and the samples re-timed by it. Why:
    the search's objective (the pile seen on opposite sweeps, a median over cells) is piecewise flat and its last step
    is a millisecond; under the datasheet's noise it stopped at 9 ms of a 10 ms lag, and the mount's self-calibration
    then took the rest up as a servo scale (+1.25 %, applied: Ve 1.83 % against the twin's 0.24 %). On the samples it
    re-timed, the floor and walls measure what is left as a timing offset (`PoseCorrection.servo_delay`, else as
    logged where that fit cannot see it: 0.97 +- 0.06 ms there). Added when measured (N_SIGNIFICANT standard errors from
    zero), whether or not it would matter alone, as the servo is re-timed anyway and the building measures its offset
    finer than the pile's sweeps do; and when within the search's step before its last (LAST_BUT_ONE_STEP_S): further,
    the pile's sweeps and the building disagree about the servo, and the search's timing stands. Returns the timing,
    the samples re-timed by it and, when not refined, the pose's correction made on them with the configured mount
    (the first estimates use it where the mount's self-calibration applies nothing: a refined report costs one pose
    correction more, another none; without the pose correction nothing is measured or refined)."""
    retimed = motion.apply(samples, timing.delay_s, timing.gain)
    if not opts.pose_correction:
        return timing, retimed, None
    pose = _pose_of(retimed, mount, header, lever, frame, storage, err, share_taken_out, opts.baro_walk_m_per_sqrt_s)
    for split in _building_timings(pose):
        if split is not None and split.measured(N_SIGNIFICANT) and abs(split.delay_s) <= LAST_BUT_ONE_STEP_S:
            delay_s = round(timing.delay_s + split.delay_s, 6)
            return (replace(timing, delay_s=delay_s, refined_s=split.delay_s),
                    motion.apply(samples, delay_s, timing.gain), None)
    return timing, retimed, pose


def structure_timing(pose: PoseCorrection | None, as_logged: bool = True) -> TimingSplit | None:
    """The servo timing offset the floor and walls show beside the drift's fit (`PoseCorrection.servo_delay`) when
    it is measured and matters (`TimingSplit.significant`: N_SIGNIFICANT standard errors, and it moves their points by
    more than the data's noise); None otherwise. Why: the servo's re-timing runs when the pile seen on opposite sweeps
    disagrees by more than MAX_SWEEP_DISAGREEMENT_M, which a servo a few milliseconds late does not reach, yet it
    moves the points at 20 m by centimetres to decimetres, the walls and the floor the two sweep directions opposite
    ways (measured: docs/design-notes.md, 2026-12-07 eighty-third session). as_logged: failing that one, the offset
    on the floor and walls as logged where that fit cannot see a lag (`timing_as_logged`); the first estimates' cut
    asks without it, as before the mount is calibrated it reads a mount's error as a lag (eighty-fourth session)."""
    if pose is None:
        return None
    for split in _building_timings(pose, as_logged):
        if split is not None and split.significant(N_SIGNIFICANT, pose.noise_m):
            return split
    return None


def _building_timings(pose: PoseCorrection, as_logged: bool = True) -> tuple[TimingSplit | None, TimingSplit | None]:
    """The servo timing offsets the floor and walls show, in the order they are asked: beside the drift's fit first
    (the finer: its points are on their planes); failing that, on the points as logged, where that fit cannot see it
    (`timing_as_logged`: a lag that puts the walls beyond its windows; None unless as_logged)."""
    return pose.servo_delay, timing_as_logged(pose) if as_logged else None


def timing_to_confirm(pose: PoseCorrection | None) -> TimingSplit | None:
    """The servo timing offset on the floor and walls as logged (`PoseCorrection.servo_delay_raw`) when it is measured
    and matters (`TimingSplit.significant`) but `structure_timing` does not take it (the fit beside the drift was made
    and does not back it): the report then re-times the servo only if the search over the pile's sweeps confirms a
    timing (the two directions agree better by more than their own noise). Why: as logged a knot interval's drift
    reads as a few tenths of a millisecond (`timing_as_logged`), which the pile's sweeps, seconds apart at most, do not
    show; yet a 10 ms lag under the datasheet's noise (seed 1) was read 9.87 +- 0.27 ms as logged, while the fit beside
    the drift, on the points its windows kept, read 3.0 +- 1.0 ms, just short of significant, and nothing was re-timed
    (Ve 2.3 %; docs/design-notes.md, 2026-12-07 eighty-fifth session)."""
    if pose is None or pose.servo_delay_raw is None:
        return None
    raw = pose.servo_delay_raw
    return raw if raw.significant(N_SIGNIFICANT, pose.noise_m) else None


@dataclass(frozen=True)
class _Estimates:
    """The mount the building says (None: not asked), the samples and boresight it leaves, and the pose's
    correction estimated on them (None: not asked; not yet applied). joint: the mount was fitted with a drift
    beside it (`_mount_with_drift`)."""

    mount: MountEstimate | None
    samples: np.ndarray
    boresight: Boresight
    pose: PoseCorrection | None
    joint: bool = False
    cut_for_timing: bool = False
    """The first estimates stopped before the mount fitted beside a drift they would have tried next, because the
    floor and walls show a servo timing offset (`structure_timing`), which the report re-times first
    (`_first_estimates`' timing_first)."""


def _mount_of(s: np.ndarray, lever: np.ndarray, frame: StorageFrame, storage: Storage, err: SensorErrorModel,
              resim: Resimulated | None, mount: Boresight, drift: DriftNuisance | None = None,
              placed: tuple[Beams, np.ndarray] | None = None,
              held: tuple[bool, bool, bool, bool] | None = None) -> MountEstimate:
    usable = s[(s["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0]
    return estimate_mount(usable, lever, frame, storage, err.range_sigma_m, err.range_sigma_rel, resim, mount,
                          err.angle_sigma_rad, err.position_sigma_m, drift,
                          None if placed is None else placed[0].parallel, held)


def _shared_beams(s: np.ndarray, lever: np.ndarray, frame: StorageFrame, storage: Storage, err: SensorErrorModel,
                  mount: Boresight) -> tuple[Beams, np.ndarray] | None:
    """The samples' beams and their stretches along the planes (`placed_beams`), made once for both the mount's
    self-calibration and the pose correction when the two would make them alike: the same samples and mount, and a
    range sigma above both noise floors (the mount's millimetre, the pose's quantisation), so that each point's
    sigma is the same to both. None: each makes its own. Why: each estimate spent a tenth of its time on them, and
    the two estimates in sequence are the report's critical path (docs/design-notes.md)."""
    floor_m = stretch_floor_m(err.resolution_m)
    if not err.range_sigma_m >= floor_m:
        return None
    return placed_beams(s, lever, frame, mount, storage, err.range_sigma_m, err.range_sigma_rel, err.angle_sigma_rad,
                        floor_m, err.position_sigma_m)


def _pose_of(s: np.ndarray, bs: Boresight, header: dict, lever: np.ndarray, frame: StorageFrame, storage: Storage,
             err: SensorErrorModel, share_taken_out: bool,
             baro_walk_m_per_sqrt_s: float = PoseCorrectionOptions.vertical_walk_m_per_sqrt_s,
             placed: tuple[Beams, np.ndarray] | None = None) -> PoseCorrection:
    # A floor seen only away from the walls anchors the height however far it moves it only when the height came from
    # the downward rangefinder and its share was not taken out (`_rangefinder_share`): that error follows the pile
    # and nothing else removes it. Taken out, what is left drifts as a barometer's does (`PoseCorrectionOptions.
    # open_floor`; measured on three `flow` flights over a pile that hides the floor wall to wall: Ve 27.2, 12.0,
    # 13.3 % anchored on its hollow, 11.1, 12.0, 5.9 % not).
    source = PoseSource.from_header(header)
    rangefinder = source is not None and source.height_from_rangefinder
    opts = PoseCorrectionOptions(open_floor=rangefinder and not share_taken_out,
                                 vertical_walk_m_per_sqrt_s=baro_walk_m_per_sqrt_s)
    return estimate_pose_correction(s, lever, frame, storage, err.resolution_m, err.range_sigma_m,
                                    err.range_sigma_rel, err.angle_sigma_rad, _sweep_period_s(header), bs, opts,
                                    position_sigma_m=err.position_sigma_m, placed=placed,
                                    pose_draw_sigma_m=err.pose_draw_sigma_m, pose_stream_hz=err.pose_stream_hz)


def _first_estimates(samples: np.ndarray, header: dict, storage: Storage, frame: StorageFrame, lever: np.ndarray,
                     opts: ReportOptions, err: SensorErrorModel, mount: Boresight,
                     share_taken_out: bool, unlifted: np.ndarray | None = None,
                     timing_first: bool = False, pose_as_is: PoseCorrection | None = None) -> _Estimates:
    """The mount's self-calibration, then the pose's correction with the mount it leaves. The mount before the
    pose: a constant mount error is partly a constant shift of the structure, which the pose's knots took up
    when they came first (measured: docs/pose_error.md)."""
    est, corrected, boresight, pose = None, samples, mount, None
    calibrating = _calibrating(opts)
    both = calibrating and opts.pose_correction
    placed = _shared_beams(samples, lever, frame, storage, err, mount) if both else None
    if opts.mount is not None or calibrating:
        resim = _drive(header, samples)
        est = (opts.mount.estimate() if opts.mount is not None
               else _mount_of(samples, lever, frame, storage, err, resim, mount, placed=placed))
        if est.any_applied:
            corrected, boresight = apply_mount(samples, est, resim, mount)
    if opts.pose_correction:
        as_is = corrected is samples and boresight == mount  # the mount applied nothing
        pose = (pose_as_is if as_is and pose_as_is is not None else
                _pose_of(corrected, boresight, header, lever, frame, storage, err, share_taken_out,
                         opts.baro_walk_m_per_sqrt_s, placed if as_is else None))
        beside_drift = partial(_mount_with_drift, samples, samples if unlifted is None else unlifted, header, storage,
                               frame, lever, opts, err, mount, share_taken_out)
        # the mount fitted beside the drift is tried next when the drift alone did not explain the floor and walls, or
        # explained them where the mount's own fit was refused (below)
        unexplained = calibrating and pose.unexplained
        refused_mount = calibrating and pose.applied and est is not None and est.unexplained
        if (unexplained or refused_mount) and timing_first and structure_timing(pose, as_logged=False) is not None:
            # The floor and walls show a servo timing offset: the report re-times the servo first (`_retimed_by_
            # building`), as a mount fitted with a drift beside it takes up part of it (a servo 3 ms late under a
            # `flow` drift with the datasheet's noise: a servo scale of +2.7 % applied and the offset gone from the
            # fit, Ve 1.20 % against 0.51 % without the delay; docs/design-notes.md).
            return _Estimates(est, corrected, boresight, pose, cut_for_timing=True)
        if unexplained:
            joint = beside_drift(pose)
            if joint is not None:
                return _boresight_if_needed(joint, partial(beside_drift, pose, held=BORESIGHT_HELD), lever, frame,
                                            storage, err.angle_sigma_rad)
        elif refused_mount:
            # The mount's fit refused because a drift bends the structure, and the drift's fit explained it alone: a
            # mount error the knots took up as a drift (a LiDAR tilted 2 deg moves the points along the track, which
            # the knots follow leg by leg; a sweep yawed 2 deg moves each side's points along the track the other
            # way, which the walls beside the track do not see) passes so. The mount fitted with the drift beside it
            # is kept when it explains the floor and walls and the pile seen twice better (`explains_more`).
            plain = _Estimates(est, corrected, boresight, pose)
            start = replace(pose, drift_fit=pose.values)
            joint = beside_drift(start)
            if joint is not None and _explains_more(plain, joint, lever, frame, storage, err.angle_sigma_rad):
                return _boresight_if_needed(joint, partial(beside_drift, start, held=BORESIGHT_HELD), lever, frame,
                                            storage, err.angle_sigma_rad)
    return _Estimates(est, corrected, boresight, pose)


def _calibrating(opts: ReportOptions) -> bool:
    """Whether the mount is estimated from the building: asked for, and no mount given (`--mount`)."""
    return opts.self_calibration and opts.mount is None


def _crossings_misfit(e: _Estimates, lever: np.ndarray, frame: StorageFrame, storage: Storage,
                      cell_m: float, angle_sigma_rad: float) -> tuple[float, float]:
    """(misfit, noise) of the pile seen at different times on the estimates' corrected samples
    (`crossings_misfit_m`), in cells of `cell_m`, the points near a wall and those a beam pointing up hit left out as
    the correction leaves them (`not_the_pile`, with the header's pointing noise angle_sigma_rad)."""
    pose = e.pose
    placed = apply_pose_correction(e.samples, pose, frame)
    b, _ = beams(placed, lever, frame, e.boresight)
    p = b.vehicle_w + b.to_point_w
    n, d = planes(storage)
    j, _ = nearest_plane(p, n, d, BAND * pose.noise_m)
    limits = PoseCorrectionOptions()
    wall = not_the_pile(j >= 1, b.to_point_w, angle_sigma_rad, limits.n_significant)
    return crossings_misfit_m(p, b.t_s, pose.knot_t_s, np.zeros(len(pose.knot_t_s)), wall, storage, cell_m,
                              limits.max_position_error_m, pose.noise_m)


def _explains_more(first: _Estimates, second: _Estimates, lever: np.ndarray, frame: StorageFrame,
                   storage: Storage, angle_sigma_rad: float) -> bool:
    """Whether the second estimates (a mount and a pose) explain the flight better than the first (a pose alone):
    the floor and walls' misfit and the pile seen at different times', each in its own noise (`explains_more`). Both
    are compared in the first pose correction's cells (what the vehicle flies in a sweep period, as that correction
    measured it), so the comparison is in one grid. The floor and walls as the drift's fit left them
    (`drift_rms_m`), before the registration on the pile seen twice traded some of their fit for its own: that is
    what a mount and a drift explain of the building, and the trade is the crossings' to judge (a LiDAR tilted 2 deg
    under a `flow` drift: the right mount's walls 0.62 cm off after the drift's fit, 1.85 after the registration;
    the pose alone's 0.71 and 1.00; the right mount's trajectory 0.11 m from the truth, the pose alone's 0.36 m)."""
    cell_m = first.pose.cell_m or second.pose.cell_m
    if cell_m is None or not cell_m > 0:
        return False
    (c0, n0), (c1, n1) = (_crossings_misfit(e, lever, frame, storage, cell_m, angle_sigma_rad) for e in (first, second))
    noise = min(first.pose.noise_m, second.pose.noise_m)
    walls = tuple(e.pose.rms_after_m if e.pose.drift_rms_m is None else e.pose.drift_rms_m for e in (first, second))
    return explains_more(walls, noise, (c0, c1), min(n0, n1))


BORESIGHT_HELD = (False, False, True, True)
"""The mount's parameters `_boresight_if_needed` holds as configured: the LiDAR's tilt and its sweep plane's yaw."""


def _boresight_if_needed(joint: _Estimates, without: Callable[[], _Estimates | None], lever: np.ndarray,
                         frame: StorageFrame, storage: Storage, angle_sigma_rad: float) -> _Estimates:
    """The mount fitted beside a drift, or the same with its boresight held as configured (`without`), when the
    servo's part is applied either way and the boresight does not explain the flight better (`_explains_more`).

    Why: beside a drift, a tilt and a sweep yaw trade with what the drift's translation cannot follow (its heading
    turns the points at the walls, as a yaw does), and the joint fit found them where there were none: a servo 5 %
    over-scaled under a `vio` drift over pile 2 came with a tilt of 2.09 deg (+0.34 %; with the scale alone +0.82 %,
    with the true scale set +0.81 %, its square twin +0.80 %), a servo 3 deg off under `flow` with a tilt of 0.75 deg.
    The simpler mount is kept unless the boresight earns its place by the same test that admits a mount beside a
    drift at all (a LiDAR tilted 2 deg on a servo 3 deg off and 5 % over-scaled keeps its tilt on each
    of the twelve such flights of the design set, under `vio` and `flow`). Tried only where the servo's part is
    applied without the boresight: a tilt or a yaw alone has no simpler mount to hold to (the pose alone was already
    weighed against it)."""
    if joint.mount is None or not any(a for a, h in zip(joint.mount.applied, BORESIGHT_HELD, strict=True) if h):
        return joint
    simpler = without()
    if simpler is None or _explains_more(simpler, joint, lever, frame, storage, angle_sigma_rad):
        return joint
    return simpler


def _mount_with_drift(samples: np.ndarray, unlifted: np.ndarray, header: dict, storage: Storage, frame: StorageFrame,
                      lever: np.ndarray, opts: ReportOptions, err: SensorErrorModel, mount: Boresight,
                      share_taken_out: bool, refused: PoseCorrection,
                      held: tuple[bool, bool, bool, bool] | None = None) -> _Estimates | None:
    """The mount fitted together with a drift of the trajectory (`DriftNuisance`, on the pose correction's knots and
    prior), when the mount's fit refused (a drift bends the structure) and the drift's fit either left the structure
    off its planes (a mount error does; `refused`) or explained it alone (its drift then is `refused.drift_fit`'s
    start, and the caller keeps the result only if it explains the flight better: `_explains_more`). The joint
    estimate is a proposal, used only when the pose correction on the mount it gives is applied, with every check of
    its own (the drift model must now explain the floor and walls). None: no proposal, or not confirmed.

    The mount is fitted on the samples as logged (unlifted): the rangefinder's share taken out of their height
    (`_rangefinder_share`) was measured on a cloud the mount bent, and its errors follow the pile, which a drift's
    knots do not (a `flow` flight with a servo 3 deg off: the joint fit left the structure 7 cm off its planes from
    those samples, 0.7 cm from the logged ones). The pose is then corrected from the samples with the share out.
    held: the mount's parameters to hold as configured (`_boresight_if_needed`)."""
    if refused.step_sigma is None or len(refused.knot_t_s) < 2:
        return None
    limits = PoseCorrectionOptions()
    # The refused correction's own drift fit is a second start (its height, on a `flow` flight, is on the samples
    # with the share out, not on the logged ones fitted here: a start only, which the fit keeps or not by the points
    # it puts on the planes)
    drift = DriftNuisance(refused.knot_t_s, refused.step_sigma[:3],
                          np.array([limits.max_position_error_m] * 2 + [limits.max_vertical_error_m]),
                          None if refused.drift_fit is None else refused.drift_fit[:, :3])
    resim = _drive(header, unlifted)
    est = _mount_of(unlifted, lever, frame, storage, err, resim, mount, drift, held=held)
    if not est.any_applied:
        return None
    corrected, boresight = apply_mount(samples, est, resim, mount)
    pose = _pose_of(corrected, boresight, header, lever, frame, storage, err, share_taken_out,
                    opts.baro_walk_m_per_sqrt_s)
    return _Estimates(est, corrected, boresight, pose, joint=True) if pose.applied else None


def _self_calibrated(survey: Survey, samples: np.ndarray, header: dict, storage: Storage, frame: StorageFrame,
                     lever: np.ndarray, opts: ReportOptions, err: SensorErrorModel,
                     spikes: SpikeThreshold | None, mount: Boresight, first: _Estimates | None = None,
                     pose_as_is: PoseCorrection | None = None) -> Survey:
    """The survey again with the mount the building says (ground.self_calibration), when that is
    significant, and then with the trajectory's correction from the building (ground.pose_correction);
    else the survey as it was, with what was found. After the servo re-timing: a late or slow servo
    makes the sweep directions disagree, a mis-mounted one does not. The first estimates (`_first_estimates`)
    may come made; an applied mount is checked again on the corrected trajectory, as under noise a drift can
    pass for one (`MOUNT_POSE_ROUNDS`). pose_as_is: the pose's correction already made on these samples with the
    configured mount, for the first estimates to use if the mount applies nothing."""
    share_taken_out = survey.rangefinder is not None and survey.rangefinder.applied
    first = first or _first_estimates(samples, header, storage, frame, lever, opts, err, mount, share_taken_out,
                                      pose_as_is=pose_as_is)
    est, pose, corrected, boresight = first.mount, first.pose, first.samples, first.boresight
    resim = _drive(header, samples)
    if pose is not None:
        # An applied mount is estimated again on the corrected trajectory, until the two agree: under sensor noise
        # a drift can pass for a mounting error (offset and scale buy part of it), and the pose then corrects a
        # cloud the mount bent (a vio flight with the datasheet's noise: -2.0 deg and +5.4 % found on a square
        # mount). Only an applied one: on a trajectory the pose left metres off (Appendix A's noise) a mount
        # estimated again found errors the first had rightly refused (4 of 18 such flights). Not a mount fitted
        # with a drift beside it (`_mount_with_drift`): the drift had no mount to pass for there, and the corrected
        # trajectory's knots took up part of the tilt, which the mount fitted again then dropped (a `flow` flight:
        # the tilt not found again, and the pose then refused on the mount left).
        for _ in range(0 if first.joint or not _calibrating(opts) else MOUNT_POSE_ROUNDS):
            if not (pose.applied and est is not None and est.any_applied):
                break
            again = _mount_of(apply_pose_correction(samples, pose, frame), lever, frame, storage, err, resim, mount)
            if not _mount_changed(est, again):
                break
            est = again
            corrected, boresight = apply_mount(samples, est, resim, mount) if est.any_applied else (samples, mount)
            pose = _pose_of(corrected, boresight, header, lever, frame, storage, err, share_taken_out,
                            opts.baro_walk_m_per_sqrt_s)
        placed = apply_pose_correction(corrected, pose, frame)
        pose = _with_sweep_heights(pose, placed, header, lever, frame, storage, boresight, err, opts)
        # placed again only when the sweeps' heights were added to the correction
        corrected = placed if pose.sweep_heights is None else apply_pose_correction(corrected, pose, frame)
        pose = with_closest_wall(pose, corrected, frame, storage)
    if corrected is samples and boresight == mount:  # nothing applied (a boresight alone leaves the samples)
        return replace(survey, mount=est, pose=pose)
    fixed = with_pose_term(_survey(corrected, header, storage, frame, lever, opts, err, spikes, boresight), pose, pose,
                           pose)
    return replace(fixed, servo_timing=survey.servo_timing, servo_retimed=survey.servo_retimed,
                   implausible=survey.implausible, despike_unavailable=survey.despike_unavailable, mount=est,
                   pose=pose, rangefinder=survey.rangefinder)


def _with_sweep_heights(pose: PoseCorrection, corrected: np.ndarray, header: dict, lever: np.ndarray,
                        frame: StorageFrame, storage: Storage, boresight: Boresight, err: SensorErrorModel,
                        opts: ReportOptions) -> PoseCorrection:
    """The applied correction with the height refined sweep by sweep from the floor (`ground.sweep_heights`), made
    on the samples it corrected; as it was when the height was not corrected, when its level rests on no floor the
    walls' feet confirm (a hollow in the pile may be what the sweeps see at z = 0), when a lever arm was placed
    instead of knots, or when no sweep sees enough floor. The floor's points are first looked for within the reach
    the correction's own prior gives the height between two knots (the walk's bridge, at most q sqrt(spacing / 4))
    and the data's noise, N_SIGMA of both."""
    period = _sweep_period_s(header)
    if (not pose.applied or pose.height_sigma_m is None or pose.level_sigma_m is not None
            or pose.open_floor_shift_m is not None or pose.lever_change_m is not None or period is None
            or len(pose.knot_t_s) < 2):
        return pose
    spacing = float(np.median(np.diff(pose.knot_t_s)))
    reach = SWEEP_N_SIGMA * math.hypot(opts.baro_walk_m_per_sqrt_s * math.sqrt(spacing / 4.0), pose.noise_m)
    heights = sweep_heights(corrected, lever, frame, storage, boresight, err.range_sigma_m, err.range_sigma_rel,
                            err.angle_sigma_rad, err.resolution_m, err.position_sigma_m, period / 2.0, reach,
                            err.pose_draw_sigma_m, err.pose_stream_hz)
    return pose if heights is None else replace(pose, sweep_heights=heights)


def with_pose_term(survey: Survey, pose: PoseCorrection | None, level_pose: PoseCorrection | None,
                   untied_pose: PoseCorrection | None) -> Survey:
    """The survey's error terms (the whole floor's and a cell mask's) with the pose term: the corrected height's
    standard error over the surfaced cells (ground.uncertainty), the level term when the height's level rests on
    the logged reference (`logged_level_sigma_m`), and the untied term when stretches of the flight were not tied
    to the floor (`untied_stretches_sigma_m`); as it was when no correction was applied. The level term comes from
    level_pose and the untied one from untied_pose (one flight's: its pose; merged flights':
    `least_certain_level`, `least_certain_untied`)."""
    sigma = pose.height_sigma_m if pose is not None and pose.applied else None
    level = logged_level_sigma_m(level_pose)
    untied = untied_stretches_sigma_m(untied_pose)
    if not (sigma or level or untied) or survey.errors is None:
        return survey

    def with_term(e: SurveyErrors, mask: np.ndarray | None) -> SurveyErrors:
        g, h = survey.grid, survey.heights
        return replace(e, terms=replace(e.terms, pose_m3=pose_term_m3(sigma, h, g, mask),
                                        level_m3=pose_term_m3(level, h, g, mask),
                                        untied_m3=pose_term_m3(untied, h, g, mask)))
    inner = survey.errors_in
    errors_in = None if inner is None else (lambda mask=None: with_term(inner(mask), mask))
    return replace(survey, errors=with_term(survey.errors, None), errors_in=errors_in)


MOUNT_POSE_ROUNDS = 4
"""At most this many times the mount is estimated again on the pose-corrected trajectory (and the pose on the new
mount); each costs a mount and a pose estimate, and only flights whose pose is corrected run any."""


def _mount_changed(before: MountEstimate, after: MountEstimate) -> bool:
    """Whether the mount estimated on the corrected trajectory is another: another set applied, or an applied
    parameter moved by more than its standard errors allow."""
    if before.applied != after.applied:
        return True
    return any(a and abs(v1 - v0) > N_SIGNIFICANT * math.hypot(e0, e1)
               for a, v0, v1, e0, e1 in zip(after.applied, before.values, after.values, before.std_errors,
                                             after.std_errors, strict=True))


def _survey(samples: np.ndarray, header: dict, storage: Storage, frame: StorageFrame, lever: np.ndarray,
            opts: ReportOptions, err: SensorErrorModel, spikes: SpikeThreshold | None,
            boresight: Boresight) -> Survey:
    cloud = cloud_from_samples(samples, lever, frame, sweep_period_s=_sweep_period_s(header), spike_threshold=spikes,
                               boresight=boresight)
    return survey_of_cloud(cloud, storage, opts, err)


def pile_sigma_m(cloud: Cloud, structure: np.ndarray, err: SensorErrorModel,
                 range_from_neighbours: bool = False) -> np.ndarray:
    """The vertical 1-sigma error of each pile point (the cloud's points outside `structure`), from the sensor
    model in the log header (`ground.smoothing.vertical_sigma_m`): what the default surface fit weighs them by."""
    return cloud_vertical_sigma_m(cloud, err, ~structure, range_from_neighbours)


CONTACT_FIT_SLOPES = NodeSlopes.CURVATURE
"""The `wall-contact` fill's surface takes scipy's least-curvature slopes whatever `--surface-slopes` says: across an
unseen strip along a wall its cubic spans from the corners' contacts to the points, and the GP's slopes lifted such a
strip 1-3 m (the paper's pile 2 at P_traj 30 % under the datasheet's noise). Measured over ten servo phases with
`--surface-slopes gp` (mean |Ve|, the GP's slopes in both fits -> in the points' own fit only): datasheet, piles 1 / 2
at 30 %, 3.39 / 2.01 -> 3.35 / 1.71 %; Appendix A at 25 and 30 %, pile 1 0.23 / 0.66 -> 0.18 / 0.59 %, pile 2
0.59 / 0.40 -> 0.65 / 0.51 %; and it saves the second kriging (docs/design-notes.md)."""


def contact_fit_m(pile_w: np.ndarray, pile_sigma: np.ndarray, contacts: WallContacts, grid: Grid, storage: Storage,
                  surface_fit: str, wanted: np.ndarray | None = None,
                  smoothing: SmoothingOptions = DEFAULT_SMOOTHING) -> np.ndarray | None:
    """The `wall-contact` fill's surface: the pile points and the wall contacts (`ground.wall_contact.contact_nodes`,
    each with its sigma) fitted together by the survey's surface fit, its slopes CONTACT_FIT_SLOPES whatever
    smoothing's, cells that leave the building emptied; in the wanted cells only (`fit_heights`), or all. None without
    contacts: there is nothing to add to the points' fit."""
    nodes, node_sigma = contact_nodes(contacts)
    if not len(nodes):
        return None
    both = fit_heights(np.concatenate([pile_w, nodes]), grid, surface_fit, np.concatenate([pile_sigma, node_sigma]),
                       replace(smoothing, slopes=CONTACT_FIT_SLOPES), wanted=wanted)
    return clip_to_building(both, storage.height_m)[0]


def survey_of_cloud(cloud: Cloud, storage: Storage, opts: ReportOptions, err: SensorErrorModel) -> Survey:
    """The surface, volume terms and sweep check of a placed cloud: one log's, or several flights' merged
    (`merged_survey`), so a merged survey is computed by the same code as a single one."""
    structure = structure_mask(cloud, storage, err)
    pile = cloud.points_w[~structure]
    grid = Grid(storage.length_m, storage.width_m, opts.cell_m)
    # The noise corrections (--noise-corrections) take off three biases of a surface estimated from noisy points, each
    # measured (docs/design-notes.md, "Four biases of the noisy surface"): each point's sigma from its neighbours'
    # range, not its own noisy one; each chosen window refitted as a quadratic, which a curved pile does not flatten;
    # a wall contact's floor test by the floor's own tolerance. --pointing-bias moves the points back along their
    # beams by what the header's pointing error puts them behind the surface (ground.pointing_bias). Neither is the
    # default yet: every page the volumes move is to be made again with them (tools.regenerate), and the pointing
    # bias is wrong in sign at grazing incidence near a wall, where beams turned off the surface hit something else.
    fixes = opts.noise_corrections
    sigma = pile_sigma_m(cloud, structure, err, range_from_neighbours=fixes)
    smoothing = SmoothingOptions(slopes=opts.surface_slopes, quadratic=fixes, limit=opts.surface_limit)
    fit, n_clipped, edge = _clipped_fit(pile, grid, opts.surface_fit, sigma, smoothing, storage)
    if opts.pointing_bias and err.angle_sigma_rad > 0:  # a pointing error put every point behind the surface: refit
        bias = along_beam_bias_m(cloud.range_m[~structure], cloud.dirs_w[~structure],
                                 sweep_directions(cloud.dirs_w)[~structure], grid_normals(pile, fit, grid.cell_xy_m),
                                 err.angle_sigma_rad)
        pile = pile - bias[:, None] * cloud.dirs_w[~structure]
        fit, n_clipped, edge = _clipped_fit(pile, grid, opts.surface_fit, sigma, smoothing, storage)
    disagreement = None
    pile_dir = None if cloud.sweep_dir is None else cloud.sweep_dir[~structure]
    typical = point_sigma_m(cloud.range_m, err.range_sigma(cloud.range_m), err.position_sigma_m, err.angle_sigma_rad)
    n_sigma = structure_n_sigma(len(pile))
    spread = face_spread_m(grid, typical, n_sigma)
    if pile_dir is not None:
        disagreement, _ = sweep_disagreement_m(pile, pile_dir, grid, spread)
    contact_fit = contact_top = None  # the surface through the points and the wall contacts, and their tops
    counts = grid.counts(pile)
    contacts = hull_fit = None
    if opts.empty_cells in CONTACT_POLICIES:
        contacts = wall_contacts(cloud, structure, storage, err, grid.cell_m, floor_by_plane=fixes)
        if opts.empty_cells in STRIP_POLICIES:  # the hull's bridge along a wall the contacts contradict: the fill's
            hull_fit = fit
            fit = np.where(contradicted_strip(fit, counts, contacts, grid, n_sigma * typical), np.nan, fit)
    unseen = ~np.isfinite(fit)
    if contacts is not None:
        contact_top = contact_ceiling_m(contacts, grid.x_edges, grid.y_edges)
        if unseen.any():  # only the unseen cells take it: fit it from the nodes that shape it there
            contact_fit = contact_fit_m(pile, sigma, contacts, grid, storage, opts.surface_fit, wanted=unseen,
                                        smoothing=smoothing)
    needs_ceiling = opts.empty_cells in ("bounded", *CONTACT_POLICIES) and unseen.any()
    ceiling = shadow = None
    if needs_ceiling:  # what the beams left free above the unseen cells, and which of them a beam passed over
        own, ceiling = free_space_ceilings_m(cloud, grid, storage, err, err.angle_sigma_rad, where=unseen)
        shadow = unseen & passed_over(own, storage.height_m)
    heights = fill_empty(fit, opts.empty_cells, ceiling, contact_fit, grid.cell_xy_m, shadow)
    roof_or_ceiling = storage.height_m if ceiling is None else ceiling
    if contact_top is not None:  # the contacts bound the unseen cells at the walls too
        roof_or_ceiling = np.fmin(np.broadcast_to(roof_or_ceiling, grid.shape), contact_top)

    shared = shared_draws(None if cloud.t_s is None else cloud.t_s[~structure], err.pose_draw_sigma_m,
                          err.pose_stream_hz)

    def errors_in(mask: np.ndarray | None = None) -> SurveyErrors:  # the whole floor, or one pile's cells
        return survey_errors(pile, pile_dir, fit, heights, counts, grid, typical, n_sigma, upper_m=roof_or_ceiling,
                             mask=mask, shared=shared, edge_m=edge)
    return Survey(cloud, pile, grid, fit, heights, counts, storage, n_clipped, disagreement, errors=errors_in(),
                  face_spread_m=spread, errors_in=errors_in, structure=structure, heights_hull=hull_fit, edge_fit=edge)


def _clipped_fit(pile_w: np.ndarray, grid: Grid, surface_fit: str, sigma: np.ndarray, smoothing: SmoothingOptions,
                 storage: Storage) -> tuple[np.ndarray, int, np.ndarray | None]:
    """The points' surface held in the building (`clip_to_building`), the count of cells it emptied, and the same
    nodes' surface with scipy's slopes when the GP's made it (`ground.surface.SurfaceFit`; None otherwise)."""
    surf = fit_surface(pile_w, grid, surface_fit, sigma, smoothing)
    fit, n_clipped = clip_to_building(surf.heights_m, storage.height_m)
    edge = None if surf.scipy_slopes_m is None else clip_to_building(surf.scipy_slopes_m, storage.height_m)[0]
    return fit, n_clipped, edge


def echo_of(survey: Survey, log: SampleLog) -> dict | None:
    """report.json's `echo` for one flight (`ground.echo_reach`): its samples without an echo traced on the poses the
    survey placed its points with (the correction applied, when it was), with its lever arm and the header's mount;
    None when the header names no sensor with a known return model or no frame."""
    header = log.header or {}
    try:
        frame = StorageFrame.from_dict(header["storage_frame"])
        mount = header_boresight(header)
    except (KeyError, TypeError, ValueError):
        return None
    samples = log.samples
    if survey.pose is not None and survey.pose.applied:
        samples = apply_pose_correction(samples, survey.pose, frame)
    lever = survey.lever_arm_body_m if survey.lever_arm_body_m is not None else header.get("lever_arm_body_m")
    if lever is None:
        return None
    reach = echo_reach(samples, header, np.asarray(lever, dtype=float), frame, survey.storage, survey.grid, mount)
    if reach is None:
        return None
    errors_in = survey.errors_in
    term = None if errors_in is None else (lambda cells: DEFAULT_INTERVAL_MODEL.unseen_m3(errors_in(cells).terms))
    return echo_record(reach, survey.heights_fit, survey.heights, survey.grid, term)


def summarise(survey: Survey, log: SampleLog, opts: ReportOptions, truth_m3: float | None,
              flights: Sequence[Flight] | None = None) -> dict:
    """report.json's figures and warnings. With flights (a merged survey: `merged_survey`, `log` their merged
    log), each flight's own checks are its warnings, named by its log, and the report lists the flights."""
    g = survey.grid
    base = survey.base or FLOOR_BASE
    volume = base.volume_m3(survey.heights, g)  # over z = 0: grid_volume(survey.heights, g), as always
    echo = echo_of(survey, log) if flights is None else None
    ra = reconstructed_ratio_pct(survey.heights_fit)
    n_struct = len(survey.cloud.points_w) - len(survey.pile_points_w)
    site, _ = header_site(log.header or {})
    if flights is None:
        warnings = log_warnings(survey, log, opts)
    else:
        warnings = [f"flight {k} ({f.inp.log_path}): {w}" for k, f in enumerate(flights, 1)
                    for w in log_warnings(f.survey, f.inp.log, opts)]
    if ra < LOW_COVERAGE_PCT and opts.empty_cells == "leave":
        warnings.append(f"only {ra:.1f} % of the floor is reconstructed (R_a); the volume misses the "
                        "uncovered cells")
    interval, terms, other = None, None, None
    if survey.errors is not None:
        terms = survey.errors.terms
        interval = base.interval_m3(volume, terms, DEFAULT_INTERVAL_MODEL)
        pose = survey.pose if survey.pose is not None and survey.pose.applied else None
        open_floor = {"shift_m": None if pose is None else pose.open_floor_shift_m, "heights": survey.heights,
                      "grid": g, "volume_m3": volume, "max_pct": opts.max_interval_pct,
                      "level_sigma_m": None if pose is None else pose.level_sigma_m, "terms": terms,
                      "model": DEFAULT_INTERVAL_MODEL}
        other = open_floor_reading(**open_floor)
        if other is None and flights is None and base.kind is BaseKind.FLOOR:  # a floor seen below z = 0
            other = floor_other_reading(survey.floor, survey.storage, survey.heights, g, volume, interval)
        why = [w for w in (
            unseen_warning(survey.heights_fit, survey.heights, g, terms, DEFAULT_INTERVAL_MODEL, volume,
                           opts.max_interval_pct),
            faces_warning(survey.errors.faces, g, terms, DEFAULT_INTERVAL_MODEL),
            pose_warning(terms, DEFAULT_INTERVAL_MODEL, volume, opts.max_interval_pct),
            level_warning(terms, DEFAULT_INTERVAL_MODEL, volume, opts.max_interval_pct, opts.baro_walk_m_per_sqrt_s),
            open_floor_warning(**open_floor),
            echo_warning(echo, volume, opts.max_interval_pct)) if w]
        stock = base.details.get("base_volume_m3") if base.kind is BaseKind.SURVEY else None
        wide = wide_interval_warning(volume, interval, opts.max_interval_pct,
                                     explained=bool(why) or bool(base.warnings), stock_m3=stock)
        warnings += why + ([wide] if wide else [])
    for k, f in enumerate(flights or (), 1):  # a merged survey: each flight's own anchor on a floor in the open
        fs = f.survey
        w = None if fs.pose is None or not fs.pose.applied else open_floor_warning(
            fs.pose.open_floor_shift_m, fs.heights, fs.grid, grid_volume(fs.heights, fs.grid), opts.max_interval_pct)
        if w:
            warnings.append(f"flight {k} ({f.inp.log_path}): {w}")
    if opts.cell_m > MEASURED_MAX_CELL_M and interval is not None:
        warnings.append(f"cells of {opts.cell_m:g} m are coarser than the {MEASURED_MAX_CELL_M:g} m up to which the "
                        "grid's own error was measured small (docs/cell_sensitivity.md): the 90 % interval does not "
                        "include that error, which grows with the cell (up to 0.6 % at 1 m); use the default "
                        f"--cell {DEFAULT_CELL_M:g} for the volume")
    warnings += list(base.warnings)
    if volume < 0 and base.kind is not BaseKind.SURVEY:  # below an earlier survey: material taken away
        warnings.append(f"the surface lies {-volume:,.1f} m³ below the floor on balance: no material above the "
                        "floor's noise; read the volume as 0" + (f" (90 % interval {interval[0]:,.1f}-"
                                                                 f"{interval[1]:,.1f} m³)" if interval else ""))
    n_implausible = sum((survey.implausible or {}).values())
    if len(survey.pile_points_w) < 3:
        warnings.append("fewer than 3 points on the stockpile: no surface could be fitted")
    st = survey.servo_timing
    if survey.n_cells_clipped:
        warnings.append(f"the fitted surface left the building in {survey.n_cells_clipped} cells (left empty, "
                        "filled by the empty-cell policy): points contradict each other there, e.g. a LiDAR buried "
                        "in the pile")
    return {
        "volume_m3": volume,
        "true_volume_m3": truth_m3,
        "volume_interval_m3": None if interval is None else list(interval),
        "interval_level": INTERVAL_LEVEL,
        "volume_other_reading": None if other is None else other.as_dict(),
        "base": base.record(survey.heights, g),
        "interval_terms_m3": None if terms is None else terms.as_dict(),
        "volume_error_pct": volume_error_pct(volume, truth_m3),
        "volume_error_m3": None if truth_m3 is None else volume - truth_m3,
        "truth_in_interval": None if truth_m3 is None or interval is None else interval[0] <= truth_m3 <= interval[1],
        "coverage_ratio_pct": ra,
        "n_samples": survey.cloud.n_samples,
        "n_points_used": len(survey.pile_points_w),
        "n_points_removed_walls": n_struct,
        "n_samples_excluded": survey.cloud.n_excluded,
        "echo": echo,
        "cell_size_m": g.length_m / g.shape[0],
        "cell_area_m2": g.cell_area_m2,
        "empty_cell_policy": opts.empty_cells,
        "sensor_noise": sensor_noise_line(log.header or {}),
        "pose_source": pose_source_line(log.header or {}, survey.rangefinder),
        "autopilot_params": autopilot_params(log.header or {}),
        "surface_fit": opts.surface_fit,
        "surface_slopes": NodeSlopes(opts.surface_slopes).value,
        "surface_limit": CubicLimit(opts.surface_limit).value,
        "noise_corrections": opts.noise_corrections,
        "pointing_bias": opts.pointing_bias,
        "n_cells_clipped": survey.n_cells_clipped,
        "n_samples_servo_suspect": survey.cloud.n_servo_suspect,
        "n_samples_spikes": survey.cloud.n_spikes,
        "despike": opts.despike and survey.despike_unavailable is None,
        "despike_unavailable": survey.despike_unavailable,
        "n_samples_implausible": n_implausible,
        "implausible": survey.implausible,
        "sweep_disagreement_m": survey.sweep_disagreement_m,
        "servo_timing": None if st is None else {
            "applied": survey.servo_retimed, "model": st.model, "delay_s": st.delay_s, "gain": st.gain,
            "disagreement_before_m": st.disagreement_before_m, "disagreement_after_m": st.disagreement_after_m,
            "building_shift_m": st.building_shift_m, "refined_by_building_s": st.refined_s},
        "self_calibration": None if survey.mount is None else survey.mount.as_dict(),
        "pose_correction": None if survey.pose is None else survey.pose.as_dict(),
        "rangefinder_height": None if survey.rangefinder is None else survey.rangefinder.as_dict(),
        "uncovered_area_m2": float((~np.isfinite(survey.heights_fit)).sum() * g.cell_area_m2),
        "bridged_area_m2": float(survey.bridged.sum() * g.cell_area_m2),
        "storage": survey.storage.to_dict(),
        "building_measured": building_record(survey.building),
        "floor_measured": None if survey.floor is None else survey.floor.as_dict(),
        "site": site,
        "mission_id": printable((log.header or {}).get("mission_id")),
        "boresight_deg": _boresight_deg(log.header or {}),
        "config": (log.header or {}).get("config"),
        "log": {"blocks_ok": log.blocks_ok, "blocks_corrupt": log.blocks_corrupt,
                "blocks_truncated": log.blocks_truncated, "bytes_skipped": log.bytes_skipped,
                "closed_cleanly": log.closed_cleanly},
        "warnings": warnings,
        "flights": None if flights is None else [flight_record(f) for f in flights],
        "software_version": software_version(),
    }


def _boresight_deg(header: dict) -> dict[str, float]:
    """The configured boresight the points were placed with, in degrees (the report's reader thinks in them)."""
    b = header_boresight(header)
    return {"tilt": math.degrees(b.tilt_rad), "sweep_yaw": math.degrees(b.sweep_yaw_rad)}


REPORT_FILE = "report.json"
"""The report's marker: put in place last, so a folder without it holds no finished report."""
REPORT_FILES = (REPORT_FILE, "report.md", "report.html", "cloud.ply", "cloud_top.png", "height_map.png",
                "coverage.png", PILES_CSV, *EXPORT_FILES)
"""Every file a report directory may hold (what --force removes)."""
REPORT_FILES = (*REPORT_FILES, SURFACE_FILE)  # the final height grid, a later survey's base (ground.surface_file)
REPORT_FILES = (*REPORT_FILES, "report.pdf", "site_map.png", "surface_3d.png", "sections.png")  # the customer's page
REPORT_FILES = (*REPORT_FILES, "trajectory_correction.png")  # the pose's correction over time (ground.correction_plot)


def make_report(source: str | Path | Sequence[str | Path], out_dir: str | Path, opts: ReportOptions | None = None, *,
                force: bool = False) -> dict:
    """Run the pipeline on a run directory or a log (or several flights' of one survey, merged) and write the
    report directory.

    The inputs are read and the volume computed before the output is touched; the files are then
    written into a staging folder and moved into place, report.json last (`rundir.OutputFolder`), so a
    report that fails half-way leaves nothing new beside an old one. An --out that already holds a
    report is refused unless force. Raises NoVolumeError (exit 5) when no surface could be fitted: a
    report would only say "0 m^3". Several sources must be flights of one survey (`survey_mismatch`):
    each log's own steps run on it alone (`survey_from_samples`), their clouds are merged
    (`merged_survey`), and the report lists the flights.
    """
    t0 = time.perf_counter()
    opts = opts or ReportOptions()
    sources = [source] if isinstance(source, str | Path) else list(source)
    if not sources:
        raise UserError("no run directory or sample log given")
    for what, path in [*(("run directory or sample log", s) for s in sources), ("report directory (--out)", out_dir)]:
        if not str(path).strip():  # Path("") is the current directory
            raise UserError(f"the {what} must be a non-empty path")
    out = check_free(out_dir, REPORT_FILES, force=force, what="report")  # before the long part
    for src in map(Path, sources):  # a report among the flight's own files would make the run a report directory too
        folder = src if src.is_dir() else src.parent
        if folder.exists() and out.exists() and out.resolve() == folder.resolve():
            raise UserError(f"--out {out} is the folder of the input {src}: write the report to a folder of its own")
    if opts.base.kind is BaseKind.SURVEY:
        survey_source_kind(Path(opts.base.source))  # a wrong --base is refused before the long part too
    with reading_input():
        inputs = [read_log_input(s) for s in sources]
        truths = [None if opts.truth_volume_m3 is not None or opts.base.kind is BaseKind.SURVEY  # not a change
                  else read_truth_volume(i.truth_path) for i in inputs]
    if opts.storage is not None:  # the surveyor's building for a header's wrong one (`storage_warning` says so)
        inputs = [replace(i, storage=opts.storage) for i in inputs]
    if opts.lever_arm_m is not None:  # the surveyor's lever arm for a header's wrong one (`lever_arm_warning`)
        inputs = [replace(i, lever_arm_body_m=np.asarray(opts.lever_arm_m, dtype=float)) for i in inputs]
    if len(inputs) > 1 and (why := survey_mismatch(inputs)) is not None:
        raise UserError(f"cannot merge: {why}")
    truth = opts.truth_volume_m3 if opts.truth_volume_m3 is not None else merged_truth(truths, inputs)
    inp = inputs[0]
    header, log_path, storage = inp.log.header or {}, inp.log_path, inp.storage
    check_exports(opts.exports, header, storage, opts.cell_m, opts.max_grid_memory_bytes)
    flights = [Flight(i, survey_from_samples(i.log.samples, i.log.header or {}, i.storage, i.frame,
                                             i.lever_arm_body_m, opts)) for i in inputs]
    merged = len(flights) > 1
    survey = merged_survey(flights, opts) if merged else flights[0].survey
    log = merged_log(inputs) if merged else inp.log
    if np.isfinite(survey.heights_fit).any():
        survey = with_base(survey, header, opts)
    report = summarise(survey, log, opts, truth, flights if merged else None)
    report["source"] = " + ".join(map(str, sources))
    t_s = log.samples["t_s"] if merged else in_time(log.samples["t_s"])  # merged: each flight's own, below
    pile_labels = add_deliverable(report, header=header, log_path=log_path, t_s=t_s, info=opts.info,
                                  piles=opts.piles, heights_fit=survey.heights_fit, heights=survey.heights,
                                  grid=survey.grid, errors=survey.errors, errors_in=survey.errors_in, base=survey.base)
    if merged:
        merged_metadata(report, flights)
    if not np.isfinite(survey.heights_fit).any():
        c = survey.cloud
        raise NoVolumeError(f"{report['source']}: no volume: no surface could be fitted from "
                            f"{report['n_points_used']} point(s) on the stockpile ({c.n_samples} samples: "
                            f"{c.n_excluded} unusable, {report['n_points_removed_walls']} on the walls or roof)")
    from ground.render import write_html, write_markdown
    from ground.report_pdf import write_pdf
    with OutputFolder(out, REPORT_FILES, REPORT_FILE, force=force, what="report") as folder:
        images = write_outputs(survey, report, folder.staging, opts.plots, pile_labels)
        save_surface(saved_surface(survey, header, opts, report["source"]), folder.staged(SURFACE_FILE))
        write_piles_csv(report["piles"], folder.staged(PILES_CSV))
        written = write_exports(survey, header, opts.exports, folder.staging)
        report["exports"] = list(written.files)
        report["warnings"] += written.warnings
        report["elapsed_s"] = time.perf_counter() - t0
        folder.staged(REPORT_FILE).write_text(json.dumps(report, indent=2) + "\n")
        write_markdown(report, images, folder.staged("report.md"))
        write_html(report, images, folder.staged("report.html"))
        write_pdf(report, images, folder.staged("report.pdf"))
        folder.commit()
    return report


# ----- base surfaces (ground.base) -----------------------------------------------------------------------

def with_base(survey: Survey, header: dict, opts: ReportOptions) -> Survey:
    """The survey measured from the base opts ask for (ground.base): the base, and the error terms that depend
    on it (a fitted floor's); the surface's own terms are kept in own_terms for the saved surface."""
    spec = opts.base
    if spec.kind is BaseKind.FLOOR:
        return replace(survey, base=FLOOR_BASE)
    if spec.kind is BaseKind.FITTED_FLOOR:
        err = SensorErrorModel.from_header(header)
        c = survey.cloud
        structure = survey.structure if survey.structure is not None else structure_mask(c, survey.storage, err)
        base = fitted_floor_base(c.points_w[~structure], pile_sigma_m(c, structure, err), survey.heights, survey.grid,
                                 FLOOR_N_SIGMA)
    else:
        earlier = earlier_surface(spec.source, replace(opts, base=FLOOR, plots=False))
        base = survey_base(earlier, saved_surface(survey, header, opts, ""), str(spec.source))
    if survey.errors is None:
        return replace(survey, base=base)
    own = survey.errors.terms
    scatter = scatter_sigma_m(survey.pile_points_w, survey.heights_fit, survey.grid)

    def rebased(t: ErrorTerms, mask: np.ndarray | None = None) -> ErrorTerms:
        return rebased_terms(t, survey.heights_fit, survey.heights, survey.grid, scatter, base,
                             survey.storage.height_m, mask, survey.edge_fit)

    inner = survey.errors_in

    def errors_in(mask: np.ndarray | None = None) -> SurveyErrors:  # one pile's terms over the same base
        e = inner(mask)
        return replace(e, terms=rebased(e.terms, mask))

    return replace(survey, base=base, errors=replace(survey.errors, terms=rebased(own)), own_terms=own,
                   errors_in=None if inner is None else errors_in)


def saved_surface(survey: Survey, header: dict, opts: ReportOptions, source: str) -> SavedSurface:
    """The survey's final surface (heights above z = 0) with its own uncertainty, whatever base it was measured from."""
    terms = survey.own_terms or (survey.errors.terms if survey.errors is not None else None)
    below, above = (0.0, 0.0) if terms is None else DEFAULT_INTERVAL_MODEL.half_widths_m3(terms)
    st = survey.storage
    return SavedSurface(np.asarray(survey.heights, dtype=np.float64), st.length_m, st.width_m, st.height_m, opts.cell_m,
                        grid_volume(survey.heights, survey.grid), below, above,
                        scatter_sigma_m(survey.pile_points_w, survey.heights_fit, survey.grid),
                        header_site(header)[0], source, software_version(), np.isfinite(survey.heights_fit))


def survey_source_kind(src: Path) -> str:
    """"report" or "run" for a directory that holds one (checked before any long computation); UserError else."""
    if not src.exists():
        raise UserError(f"no such run or report directory: {src}")
    if not src.is_dir():
        raise UserError(f"{src} is not a run or report directory (a directory holding {SAMPLES_FILE} or {REPORT_FILE})")
    if (src / REPORT_FILE).exists():
        if not (src / SURFACE_FILE).exists():
            raise UserError(f"{src} is a report directory without its {SURFACE_FILE} (written by reports since "
                            f"{software_version()}): report the run again, or give its run directory")
        return "report"
    if not (src / SAMPLES_FILE).exists():
        raise UserError(f"{src} is neither a run directory (no {SAMPLES_FILE}) nor a report directory "
                        f"(no {REPORT_FILE})")
    return "run"


def earlier_surface(source: str | Path, opts: ReportOptions) -> SavedSurface:
    """The surface of a report directory (its saved surface.npz) or of a run directory (computed from its log
    as its report would be, with opts); one-line UserError for anything else."""
    src = Path(source)
    if survey_source_kind(src) == "report":
        return load_surface(src / SURFACE_FILE)
    with reading_input():
        inp = read_log_input(src)
    header = inp.log.header or {}
    survey = survey_from_samples(inp.log.samples, header, inp.storage, inp.frame, inp.lever_arm_body_m, opts)
    if not np.isfinite(survey.heights_fit).any():
        raise UserError(f"{inp.log_path}: no surface could be fitted, so it cannot serve as a base or be compared")
    return saved_surface(survey, header, opts, str(src))
