"""The floor's level (`ground.floor_check.measure_floor`) over the stored evaluation set, as logged or with every
point moved down by a lever arm's z entered too far down (--lever-dz).

What the floor check rests on: on error-free runs the floor never lies much below z = 0 (so a floor below it is a
height error, never a pile), and with a lever arm off it is measured at the offset. Each run's cloud is placed from
its samples with its header's geometry (no despike, self-calibration or pose correction: the evaluation set's pose
is the truth), its structure masked as the report masks it. Runs of piles that hide the floor give the height of
the lowest flat surface of material instead, above z = 0; they are counted apart (`--hidden` families).

Usage: python -m tools.floor_level_check [--root runs/evalset] [--lever-dz 0.1] [--stride 1] [--jobs 2]
           [--write docs/pose_error.md]  (the table into the page's section floor-level, or floor-level-dz<cm>)
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ground.base import FLOOR_FALL_SHOWN_PCT
from ground.floor_check import N_SIGNIFICANT, measure_floor
from ground.pointcloud import SensorErrorModel, cloud_from_samples, structure_mask
from ground.surface import DEFAULT_CELL_M, Grid
from tools.doc_sections import write_section
from tools.evalset import DEFAULT_ROOT, load_run, stored_runs_or_say
from tools.workers import progress_map, worker_pool

HIDING_FAMILIES = ("irregular", "flat")
"""The evaluation set's families whose piles cover the floor wall to wall on some runs: their lowest flat surface is
material (measured up to 4.3 m up), so their levels are reported apart."""


def floor_row(run_dir: str, lever_dz_m: float) -> dict:
    """One run's floor level, with the lever arm's z moved by lever_dz_m (every point that much lower)."""
    r = load_run(run_dir)
    err = SensorErrorModel.from_header(r.header)
    cloud = cloud_from_samples(r.samples, r.lever_arm_body_m + np.array([0.0, 0.0, lever_dz_m]), r.frame)
    grid = Grid(r.storage.length_m, r.storage.width_m, DEFAULT_CELL_M)
    f = measure_floor(cloud, structure_mask(cloud, r.storage, err), r.storage, err, grid)
    return {"run": r.run_id, "family": r.truth["family"], "noise": r.truth["noise"],
            "floor_area_m2": r.storage.floor_area_m2, "floor": None if f is None else f.as_dict()}


def summary(rows: Sequence[dict], lever_dz_m: float) -> list[str]:
    """The table's lines: per noise model, the levels of the runs whose floor shows, and the hiding families'."""
    lines = [f"| runs | noise | no floor | level min | median | max | below z = 0 by > {N_SIGNIFICANT:g} SE "
             f"| fall median | max | named (>= {FLOOR_FALL_SHOWN_PCT:g} %) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for hiding in (False, True):
        for noise in sorted({r["noise"] for r in rows}):
            rr = [r for r in rows if r["noise"] == noise and (r["family"] in HIDING_FAMILIES) == hiding]
            seen = [r["floor"] for r in rr if r["floor"] is not None]
            if not rr:
                continue
            lv = np.array([f["level_m"] for f in seen])
            below = sum(f["level_m"] < -N_SIGNIFICANT * f["std_error_m"] for f in seen)
            what = "piles that may hide the floor" if hiding else "the rest"
            levels = " | ".join(f"{v * 100:+.2f} cm" if seen else "-" for v in (
                (lv.min(), np.median(lv), lv.max()) if seen else (0.0, 0.0, 0.0)))
            falls = np.array([f.get("fall_pct", 0.0) for f in seen])
            named = int(np.count_nonzero(falls >= FLOOR_FALL_SHOWN_PCT))
            fall = f"{np.median(falls):.2f} % | {falls.max():.2f} % | {named}" if seen else "- | - | 0"
            lines.append(f"| {what} ({len(rr)}) | {noise} | {len(rr) - len(seen)} | {levels} | {below} | {fall} |")
    lines.append(f"(every point moved {lever_dz_m * 100:+.0f} cm down by the lever arm's z)" if lever_dz_m else
                 "(as logged)")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.floor_level_check", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="the evaluation set (tools.evalset)")
    ap.add_argument("--lever-dz", type=float, default=0.0, metavar="M",
                    help="the lever arm's z entered this much too far down (every point that much low)")
    ap.add_argument("--stride", type=int, default=1, help="every Nth run only (a quick look)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--write", type=Path, default=None, metavar="PAGE",
                    help="also write the table into this page's section floor-level "
                         "(with --lever-dz: floor-level-dz<cm>)")
    args = ap.parse_args(argv)
    if args.stride < 1 or args.jobs < 1 or not np.isfinite(args.lever_dz) or abs(args.lever_dz) > 5.0:
        print("floor_level_check: --stride and --jobs must be >= 1, --lever-dz within +/-5 m", file=sys.stderr)
        return 2
    dirs = stored_runs_or_say(args.root, args.stride, "floor_level_check")
    if not dirs:
        return 2
    with worker_pool(args.jobs) as pool:
        rows = progress_map(pool, floor_row, dirs, [args.lever_dz] * len(dirs), desc="floor_level_check",
                            unit="run", chunksize=8)
    table = "\n".join(summary(rows, args.lever_dz))
    print(table)
    if args.write is not None:
        name = "floor-level" + (f"-dz{round(args.lever_dz * 100):d}" if args.lever_dz else "")
        cmd = "python -m tools.floor_level_check" + (f" --lever-dz {args.lever_dz:g}" if args.lever_dz else "")
        write_section(args.write, name, f"Regenerated by `{cmd}` ({len(rows):,} run{'s' if len(rows) != 1 else ''}"
                                        f"{f', every {args.stride}th' if args.stride > 1 else ''}):\n\n{table}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
