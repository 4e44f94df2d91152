"""Calibrate the volume interval's pose factor on drifting flights and report the interval's coverage on them.

The evaluation set that calibrates the interval's other factors (tools/calibrate_interval.py) flies the true
pose. When the trajectory's height is corrected from the building (ground.pose_correction), the volume
carries that correction's error: the report's pose term (ground.uncertainty) is the formal standard error
of the corrected height's mean times the surfaced area, and its factor k_pose is fitted here, on the
corrected reports the pose campaigns keep (tools/pose_correction_campaign.py --keep):

- **calibration**: the paper's piles without sensor noise (`runs/pose`);
- **held out**: other piles in another building (`runs/pose-own`), the paper's piles with the datasheet's
  and Appendix A's noise (`runs/pose-noise-ds`, `runs/pose-noise-aa`), and the paper's pile 2 in a building it
  covers wall to wall (`runs/pose-hidden`: no floor at any wall).

Each corrected report.json gives the volume, the true volume and the error terms (k-free); the other factors
stay as calibrated. k_pose is the smallest factor that puts the truth inside the interval of 90 % of the
calibration flights with a pose error (a flight whose height was not corrected has no pose term and counts as
it is). The tables give the coverage without the term and with it, per set, P_traj and profile.

    python -m tools.calibrate_pose_interval --write docs/uncertainty.md --write-model
"""

from __future__ import annotations

import json
import math
import statistics
import sys
import time
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ArgumentParser
from ground.uncertainty import DEFAULT_INTERVAL_MODEL, INTERVAL_LEVEL, ErrorTerms, IntervalModel
from tools.doc_sections import write_block, write_section
from tools.pose_correction_campaign import kept_flight_crash

SECTION = "pose-interval-coverage"
CALIBRATION = (("paper piles", Path("runs/pose")),)
HELD_OUT = (("own piles, 40 x 25 x 10 m", Path("runs/pose-own")), ("paper piles, datasheet noise",
                                                                   Path("runs/pose-noise-ds")),
            ("paper piles, Appendix A noise", Path("runs/pose-noise-aa")),
            ("pile 2 hiding the floor, 24 x 16 x 10 m", Path("runs/pose-hidden")))
MODEL_FILE = Path("ground/uncertainty.py")
MODEL_BEGIN = "# --- calibrated pose factor (tools/calibrate_pose_interval.py --write-model) ---"
MODEL_END = "# --- end of calibrated pose factor ---"
REPORT_SUFFIX = "--pose-correction"


def flights(keep: Path, label: str) -> list[dict]:
    """The corrected reports of one campaign folder, one row each: set, run, profile, P_traj, volume, truth, terms.
    A run is named PROFILE-PILE-P_TRAJ-SEED[-NOISE] (tools/pose_correction_campaign.py)."""
    rows = []
    for rep in sorted(keep.glob(f"*{REPORT_SUFFIX}/report.json")):
        r = json.loads(rep.read_text())
        if r.get("true_volume_m3") is None or r.get("interval_terms_m3") is None:
            continue
        run = rep.parent.name.removesuffix(REPORT_SUFFIX)
        truth = keep / run / "truth.json"
        if not truth.is_file():
            continue
        flown = json.loads(truth.read_text())
        if kept_flight_crash(flown) is not None:  # as the campaign: a crash is no survey
            continue
        mission = flown["mission"]
        p_traj = round(100.0 * mission["p_traj"])
        rows.append({"set": label, "run": run, "profile": run.split("-")[0], "p_traj": p_traj,
                     "volume_m3": r["volume_m3"],
                     "true_volume_m3": r["true_volume_m3"], "terms": ErrorTerms(**r["interval_terms_m3"])})
    return rows


def inside(row: dict, model: IntervalModel) -> bool:
    lo, hi = model.interval_m3(row["volume_m3"], row["terms"])
    return lo <= row["true_volume_m3"] <= hi


def needed_k(row: dict, model: IntervalModel) -> float:
    """The smallest k_pose that puts this flight's truth inside (0: inside without the term; inf: no pose term and
    outside)."""
    without = replace(model, k_pose=0.0)
    if inside(row, without):
        return 0.0
    err = row["volume_m3"] - row["true_volume_m3"]
    below, above = without.half_widths_m3(row["terms"])
    side = below if err > 0 else above  # an over-estimate needs the interval to reach down
    p = row["terms"].pose_m3
    if p <= 0:
        return math.inf
    return math.sqrt(max(err * err - side * side, 0.0)) / p * (1.0 + 1e-9)


def fit(rows: list[dict], model: IntervalModel, level: float = INTERVAL_LEVEL) -> float:
    """The smallest k_pose with the truth inside for `level` of the drifting rows (a quantile of what each needs)."""
    need = np.array([needed_k(r, model) for r in rows if r["profile"] != "none"])
    if len(need) == 0:
        raise SystemExit("calibrate_pose_interval: no drifting flights to calibrate on")
    k = float(np.sort(need)[math.ceil(level * len(need) - 1e-9) - 1])  # the smallest with that share inside
    if not math.isfinite(k):
        raise SystemExit(f"calibrate_pose_interval: more than {100 * (1 - level):.0f} % of the calibration flights "
                         "miss the interval and have no pose term (their height was not corrected): no factor helps")
    return k


def table(rows: list[dict], model: IntervalModel) -> list[str]:
    """Per set, P_traj and profile: flights, truth inside without the pose term and with it, median half-width."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["set"], r["p_traj"], r["profile"])].append(r)
    without = replace(model, k_pose=0.0)
    out = ["| flights | P_traj | profile | n | truth inside, no pose term | truth inside | median half-width (% of "
           "the volume) |", "|---|---|---|---|---|---|---|"]
    for (label, p, prof), g in sorted(groups.items(), key=lambda kv: (kv[0][0], kv[0][1] or 0, kv[0][2])):
        half = [100.0 * sum(model.half_widths_m3(r["terms"])) / 2.0 / r["volume_m3"] for r in g if r["volume_m3"] > 0]
        med = f"{statistics.median(half):.2f}" if half else ""
        out.append(f"| {label} | {p} % | {prof} | {len(g)} | {sum(inside(r, without) for r in g)}/{len(g)} | "
                   f"{sum(inside(r, model) for r in g)}/{len(g)} | {med} |")
    return out


def summary(rows: list[dict], model: IntervalModel) -> str:
    drifting = [r for r in rows if r["profile"] != "none"]
    n_in = sum(inside(r, model) for r in drifting)
    n_before = sum(inside(r, replace(model, k_pose=0.0)) for r in drifting)
    return f"{n_in} of {len(drifting)} drifting flights inside ({n_before} without the pose term)"


def document(k: float, calib: list[dict], held: list[dict], model: IntervalModel, command: str) -> str:
    return "\n".join([
        f"k_pose = {k:.3g}, fitted on the corrected reports of {len(calib)} flights ({CALIBRATION[0][0]}, without "
        f"sensor noise: {sum(r['profile'] != 'none' for r in calib)} drifting). Regenerated by `{command}` after the "
        "campaigns that keep the flights (docs/pose_error.md), whose reports it reads.", "",
        f"- calibration: {summary(calib, model)};",
        f"- held out: {summary(held, model)}.", "",
        *table(calib + held, model)])


def write_model(k: float, source: str, path: Path = MODEL_FILE) -> None:
    """Replace the pose factor's block of ground/uncertainty.py (between MODEL_BEGIN and MODEL_END)."""
    # every digit: the flight that set the factor is inside by a hair, and a rounded factor put it outside
    write_block(path, MODEL_BEGIN, MODEL_END, f"POSE_FACTOR = {k!r}\nPOSE_FACTOR_SOURCE = {source!r}",
                "calibrate_pose_interval")


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.calibrate_pose_interval", description=__doc__.splitlines()[0])
    ap.add_argument("--write", type=Path, default=None, help="the Markdown page to (re)write the table in")
    ap.add_argument("--write-model", action="store_true", help="write the fitted factor into ground/uncertainty.py")
    args = ap.parse_args(argv)
    calib = [r for label, keep in CALIBRATION for r in flights(keep, label)]
    held = [r for label, keep in HELD_OUT for r in flights(keep, label)]
    if not calib:
        raise SystemExit("calibrate_pose_interval: no corrected reports under "
                         f"{', '.join(str(k) for _, k in CALIBRATION)}: run the pose campaigns first "
                         "(python -m tools.pose_correction_campaign --keep ..., docs/pose_error.md)")
    k = fit(calib, DEFAULT_INTERVAL_MODEL)
    model = replace(DEFAULT_INTERVAL_MODEL, k_pose=k)
    command = "python -m tools.calibrate_pose_interval " + " ".join(argv if argv is not None else sys.argv[1:])
    text = document(k, calib, held, model, command.strip())
    print(text)
    if args.write:
        write_section(args.write, SECTION, text)
    if args.write_model:
        n = sum(r["profile"] != "none" for r in calib)
        day = time.strftime("%Y-%m-%d")
        write_model(k, f"fitted on {n} drifting flights (tools/calibrate_pose_interval.py, {day})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
