"""Kept pose-error flights surveyed again with their autopilot's EKF source record in the header, with and without
the rangefinder's share of the height taken out (`ground.rangefinder_height`).

What the step is worth on the flights of the pose campaigns (`tools.pose_correction_campaign --keep DIR`): each
flight is surveyed twice, once with a record that names the barometer as the height source (the step does not run:
`BARO_RECORD`), and once with the record the simulated autopilot serves for the flight's profile
(`sitl.sensing.pose_drift.EKF_SOURCES`; `--record own`), or one profile's record put into every flight (`--record
flow`: what a header that says so wrongly costs), or none (`--record absent`: a log that does not say, where the
report measures the share all the same). Flights flown before the payload wrote the record get it the same way. Each
drifting flight is compared with its error-free twin (the `none` flight of the same pile, P_traj and seed, found
beside it) as the pose campaign does: |Ve - Ve error-free| (signed Ve, pp) and the trajectory's RMS against the truth
(the lift included: the report's lift over time).

Usage: python -m tools.rangefinder_share_check --runs runs/pose runs/pose-own runs/pose-noise-ds runs/pose-noise-aa
           [--profiles flow] [--record own|absent|flow] [--jobs 2] [--write docs/pose_error.md [--section NAME]]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

from firmware_py.core.pose_source import HEADER_KEY
from firmware_py.core.rundir import SAMPLES_FILE, TRUTH_FILE
from firmware_py.core.samplelog import read_samplelog
from ground.base import FLOOR_BASE
from ground.report import ReportOptions, header_geometry, survey_from_samples
from sitl.sensing.pose_drift import ekf_source_params
from tools.doc_sections import write_section
from tools.pose_correction_campaign import TRAJ_TARGET_M, VE_TARGET_PP, trajectory_rms_m
from tools.workers import progress_map, worker_pool

BARO_RECORD = ekf_source_params("vio")
"""A record whose height source is the barometer: the report then takes no share out (the step off). Taking the
record out no longer turns the step off: a log that does not say where its height came from has the share measured."""
BARO, ABSENT = "baro", "absent"
"""`_survey`'s records besides a profile's: the barometer's (`BARO_RECORD`), or none at all (absent)."""
FLIGHT = re.compile(r"^(none|flow|vio)-(.+)-(\d+)-(\d+)(?:-(appendix-a|datasheet))?$")


def _survey(run: Path, record: str) -> tuple[float, float]:
    """(signed Ve %, trajectory RMS after, m) of one flight surveyed with the header's record set as asked: a
    profile's, ABSENT (taken out), or BARO (`BARO_RECORD`)."""
    log = read_samplelog(run / SAMPLES_FILE)
    header = dict(log.header)
    header.pop(HEADER_KEY, None)
    if record == BARO:
        header[HEADER_KEY] = dict(BARO_RECORD)
    elif record != ABSENT:
        header[HEADER_KEY] = ekf_source_params(record)
    storage, frame, lever = header_geometry(log, run)
    sv = survey_from_samples(log.samples, header, storage, frame, lever, ReportOptions(plots=False))
    truth = json.loads((run / TRUTH_FILE).read_text())
    tv = truth["true_volume_m3"]
    ve = 100.0 * (FLOOR_BASE.volume_m3(sv.heights, sv.grid) - tv) / tv
    _, after = trajectory_rms_m(truth, sv.pose.as_dict() if sv.pose is not None else None,
                                sv.rangefinder.as_dict() if sv.rangefinder is not None else None)
    return ve, after


def _one(args: tuple[str, str, str | None]) -> tuple[str, float, float, float, float]:
    run, profile, forced = args
    record = forced or profile
    off_ve, off_traj = _survey(Path(run), BARO)
    on_ve, on_traj = _survey(Path(run), record)
    return run, off_ve, off_traj, on_ve, on_traj


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", nargs="+", required=True, help="folders of kept flights (pose campaigns' --keep)")
    ap.add_argument("--profiles", nargs="+", default=["flow"], help="the drifting profiles to survey again")
    ap.add_argument("--record", default="own",
                    help="own: each flight's profile's record; absent: no record; or a profile's name")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--write", type=Path, help="page whose section to rewrite with the table")
    ap.add_argument("--section", default="rangefinder-share-table", help="the page's section (default %(default)s)")
    args = ap.parse_args(argv)
    forced = None if args.record == "own" else args.record
    flights, twins = [], {}
    for folder in map(Path, args.runs):
        for run in sorted(p for p in folder.iterdir() if (p / TRUTH_FILE).is_file() and "--" not in p.name):
            m = FLIGHT.match(run.name)
            if m is None:
                continue
            key = (folder.name, m.group(2), m.group(3), m.group(4), m.group(5))
            if m.group(1) == "none":
                twins[key] = run
            elif m.group(1) in args.profiles:
                flights.append((key, run, m.group(1)))
    needed = sorted({twins[k] for k, _, _ in flights if k in twins})
    with worker_pool(args.jobs) as ex:
        done = {r: row for r, *row in progress_map(ex, _one, [(str(r), p, forced) for _, r, p in flights],
                                                    desc="rangefinder_share_check", unit="flight")}
        ref = {r: ve for r, ve, _ in progress_map(ex, _twin, [str(r) for r in needed],
                                                  desc="rangefinder_share_check twins", unit="flight")}
    lines = [f"| folder | flights | mean \\|dVe\\| step off / on (pp) | within {VE_TARGET_PP} pp | "
             f"trajectory <= {TRAJ_TARGET_M * 100:.0f} cm |", "|---|---|---|---|---|"]
    for folder in dict.fromkeys(k[0] for k, _, _ in flights):
        rows = [(done[str(r)], ref[str(twins[k])]) for k, r, _ in flights if k[0] == folder and k in twins]
        if not rows:
            continue
        off = [abs(d[0] - e) for d, e in rows]
        on = [abs(d[2] - e) for d, e in rows]
        lines.append(f"| {folder} | {len(rows)} | {np.mean(off):.2f} / {np.mean(on):.2f} | "
                     f"{sum(v <= VE_TARGET_PP for v in off)} / {sum(v <= VE_TARGET_PP for v in on)} | "
                     f"{sum(d[1] <= TRAJ_TARGET_M for d, _ in rows)} / {sum(d[3] <= TRAJ_TARGET_M for d, _ in rows)} |")
    print("\n".join(lines))
    if args.write:
        cmd = "python -m tools.rangefinder_share_check " + " ".join(argv if argv is not None else sys.argv[1:])
        write_section(args.write, args.section, f"Regenerated by `{cmd}` ({len(flights)} {', '.join(args.profiles)} "
                      f"flights, record: {args.record}).\n\n" + "\n".join(lines))
    return 0


def _twin(run: str) -> tuple[str, float, float]:
    ve, traj = _survey(Path(run), BARO)  # an error-free flight's height never followed the pile
    return run, ve, traj


if __name__ == "__main__":
    sys.exit(main())
