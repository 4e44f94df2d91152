"""How far off the LiDAR's lever arm may be entered: stored evaluation runs reported as the report does (its defaults:
self-calibration, pose correction, the interval and its warnings), once with the lever arm they were flown with and
once with it moved by each offset along the body's x (forward), y (right) or z (down).

What a drone engineer needs from it is the tolerance to measure the mounting to: the change of Ve against the same
run reported with the right lever arm (the survey's own error taken out), whether the truth is still inside the 90 %
interval, and whether the report said anything it did not say before (a warning that names the pose correction, the
floor, the mount). The evaluation set's poses are the truth, so every change is the lever arm's.

Usage: python -m tools.lever_arm_check [--root runs/evalset] [--offsets 0.05,0.1,0.2] [--stride 43] [--jobs 2]
           [--write docs/pose_error.md]  (the table into the page's section lever-arm)
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from firmware_py.core.samplelog import SampleLog
from tools.doc_sections import write_section
from tools.evalset import DEFAULT_ROOT, load_run, stored_runs_or_say
from tools.workers import progress_map, worker_pool

AXES = ("x", "y", "z")
"""The body axes, as the log header's lever arm is written: forward, right, down."""
DEFAULT_OFFSETS_M = (0.05, 0.1, 0.2)
"""Each taken with both signs: a ruler's slip, a mount moved without the configuration, a lever arm measured to the
wrong end of the part."""
WARNING_KEY_CHARS = 30
"""A warning is told from another by its first words, its figures as "#": they change with the lever arm, its
subject does not."""


def _warning_kinds(report: dict) -> set[str]:
    return {re.sub(r"\d[\d.,]*", "#", w)[:WARNING_KEY_CHARS] for w in report.get("warnings", [])}


def lever_rows(run_dir: str, offsets_m: Sequence[float], axes: Sequence[str] = AXES) -> list[dict]:
    """One run reported with its own lever arm and with it moved by each offset (both signs) along each of axes."""
    from ground.report import ReportOptions, summarise, survey_from_samples

    r = load_run(run_dir)
    opts = ReportOptions(plots=False)
    log = SampleLog(r.header, r.samples, 1, 0, 0, 0)
    truth = r.true_volume_m3

    def report(lever: np.ndarray) -> dict:
        sv = survey_from_samples(r.samples, r.header, r.storage, r.frame, lever, opts)
        return summarise(sv, log, opts, truth)

    base = report(r.lever_arm_body_m)
    rows = []
    for axis, name in enumerate(AXES):
        if name not in axes:
            continue
        for off in sorted({s * abs(float(o)) for o in offsets_m for s in (-1.0, 1.0)}):
            lever = r.lever_arm_body_m.astype(float)
            lever[axis] += off
            rep = report(lever)
            lo, hi = rep["volume_interval_m3"] or (math.nan, math.nan)
            rows.append({"run": r.run_id, "family": r.truth["family"], "noise": r.truth["noise"], "axis": name,
                         "offset_m": off, "volume_m3": rep["volume_m3"], "base_volume_m3": base["volume_m3"],
                         "true_volume_m3": truth, "covered": bool(lo <= truth <= hi),
                         "new_warnings": sorted(_warning_kinds(rep) - _warning_kinds(base))})
    return rows


def _dve_pp(row: dict) -> float | None:
    t = row["true_volume_m3"]
    return None if t <= 0 else 100.0 * (row["volume_m3"] - row["base_volume_m3"]) / t


def summary(rows: Sequence[dict]) -> list[str]:
    """The table's lines: per axis and offset, the change of Ve against the right lever arm by noise model (median and
    90th percentile), the interval's coverage and the new warnings over every run (runs of an empty building count
    in the last two columns only: their Ve is undefined)."""
    noises = sorted({r["noise"] for r in rows})
    lines = ["| lever arm entered off by | " + " | ".join(f"\\|ΔVe\\|, {n}: median / 90th pct" for n in noises)
             + " | truth inside the 90 % interval | a new warning |",
             "|---|" + "---:|" * len(noises) + "---:|---:|"]
    for axis in AXES:
        for off in sorted({r["offset_m"] for r in rows if r["axis"] == axis}):
            rr = [r for r in rows if r["axis"] == axis and r["offset_m"] == off]
            cells = []
            for noise in noises:
                d = np.abs([v for r in rr if r["noise"] == noise and (v := _dve_pp(r)) is not None])
                cells.append(f"{np.median(d):.2f} / {np.percentile(d, 90):.2f} pp ({len(d)})" if len(d) else "-")
            covered = sum(r["covered"] for r in rr)
            warned = sum(bool(r["new_warnings"]) for r in rr)
            lines.append(f"| {axis} {off * 100:+.0f} cm | " + " | ".join(cells)
                         + f" | {covered} of {len(rr)} | {warned} of {len(rr)} |")
    return lines


def warning_lines(rows: Sequence[dict]) -> list[str]:
    """Which new warnings the moved lever arms set off, by their first words, with how many rows each."""
    count: dict[str, int] = {}
    for r in rows:
        for w in r["new_warnings"]:
            count[w] = count.get(w, 0) + 1
    return [f"- \"{w}...\": {n} of {len(rows)}" for w, n in sorted(count.items(), key=lambda kv: -kv[1])]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.lever_arm_check", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="the evaluation set (tools.evalset)")
    ap.add_argument("--offsets", default=",".join(f"{o:g}" for o in DEFAULT_OFFSETS_M), metavar="M,M,...",
                    help="the lever arm's errors tried, m, each with both signs (default %(default)s)")
    ap.add_argument("--axes", default=",".join(AXES), metavar="A,...",
                    help="the body axes moved: x (forward), y (right), z (down); default %(default)s")
    ap.add_argument("--stride", type=int, default=43,
                    help="every Nth run (default %(default)s: 36 of the 1,512, the three noise models alike)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--write", type=Path, default=None, metavar="PAGE",
                    help="also write the table into this page's section lever-arm")
    ap.add_argument("--rows", type=Path, default=None, metavar="JSON", help="also keep every row in this file")
    args = ap.parse_args(argv)
    try:
        offsets = [float(v) for v in args.offsets.split(",")]
    except ValueError:
        offsets = []
    axes = args.axes.split(",")
    if (args.stride < 1 or args.jobs < 1 or not offsets or not set(axes) <= set(AXES)
            or not all(math.isfinite(o) and 0.0 < abs(o) <= 1.0 for o in offsets)):
        print("lever_arm_check: --stride and --jobs must be >= 1, --offsets numbers within 0-1 m (not 0), --axes "
              "of x, y, z", file=sys.stderr)
        return 2
    dirs = stored_runs_or_say(args.root, args.stride, "lever_arm_check")
    if not dirs:
        return 2
    with worker_pool(args.jobs) as pool:
        done = progress_map(pool, lever_rows, dirs, [offsets] * len(dirs), [axes] * len(dirs), desc="lever_arm_check",
                            unit="run")
    rows = [row for rs in done for row in rs]
    if args.rows is not None:
        args.rows.write_text(json.dumps(rows, indent=0))
    table = "\n".join([*summary(rows), "", "New warnings, by their first words:", *warning_lines(rows)])
    print(table)
    if args.write is not None:
        cmd = "python -m tools.lever_arm_check" + (f" --offsets {args.offsets}" if args.offsets != ap.get_default(
            "offsets") else "") + (f" --stride {args.stride}" if args.stride != ap.get_default("stride") else "") + (
            f" --axes {args.axes}" if args.axes != ap.get_default("axes") else "")
        write_section(args.write, "lever-arm", f"Regenerated by `{cmd}` ({len(dirs):,} run"
                                               f"{'s' if len(dirs) != 1 else ''} of the evaluation set):\n\n{table}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
