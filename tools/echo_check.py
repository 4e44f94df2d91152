"""The echo diagnosis (`ground.echo_reach`) over the stored evaluation set: how often its warning speaks, and on which
surveys.

Each run is surveyed as the report surveys it (`ground.report.survey_from_samples`); its samples without an echo are
traced with its header's geometry, and the warning judged against its volume with the default 5 % tolerance. A
warning is wanted where the fill put material on floor the rangefinder could not reach and the volume is off for it:
the table counts, per noise model and P_traj, the runs it warned on, the runs reading more than 2 % high (the fill's
usual sign where the pile's flank is carried level to a wall) and how many of those it warned on, and the runs it
warned on whose volume was within 1 % (a warning a surveyor did not need).

Usage: python -m tools.echo_check [--root runs/evalset] [--noise datasheet none] [--stride 1] [--jobs 2]
           [--write docs/unseen.md]  (the table into the page's section echo-check)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from firmware_py.core.samplelog import SampleLog
from ground.echo_reach import echo_warning
from ground.report import ReportOptions, echo_of, survey_from_samples
from ground.surface import grid_volume
from ground.volume_warnings import DEFAULT_MAX_INTERVAL_PCT
from tools.evalset import load_run
from tools.evalset_check import EvalsetCheck, check_main

SECTION = "echo-check"
HIGH_PCT = 2.0
"""A run reading more than this high is one the fill may have over-filled (the table's wanted column)."""
CLOSE_PCT = 1.0
"""A run within this of the truth did not need a warning about its volume."""


def echo_row(run_dir: str) -> dict:
    """One run's survey volume, echo record and whether the warning spoke."""
    r = load_run(run_dir)
    sv = survey_from_samples(r.samples, r.header, r.storage, r.frame, r.lever_arm_body_m, ReportOptions(plots=False))
    rec = echo_of(sv, SampleLog(r.header, r.samples, 1, 0, 0, 0))  # the report's own record of the run
    volume = grid_volume(sv.heights, sv.grid)
    true = r.true_volume_m3
    return {"run": r.run_id, "noise": r.truth["noise"], "p_traj": int(r.truth["p_traj_pct"]),
            "family": r.truth["family"], "ve_pct": None if true <= 0 else 100.0 * (volume - true) / true,
            "echo": rec, "warned": echo_warning(rec, volume, DEFAULT_MAX_INTERVAL_PCT) is not None}


def summary(rows: Sequence[dict]) -> list[str]:
    """The table's lines: per noise model and P_traj."""
    lines = ["| noise | P_traj | runs | samples without an echo (median) | warned | read > 2 % high | of them warned | "
             "warned within 1 % |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for noise in sorted({r["noise"] for r in rows}):
        for p in sorted({r["p_traj"] for r in rows if r["noise"] == noise}):
            rr = [r for r in rows if r["noise"] == noise and r["p_traj"] == p]
            share = [r["echo"]["no_echo"] / r["echo"]["samples_aimed"] for r in rr if r["echo"]]
            high = [r for r in rr if r["ve_pct"] is not None and r["ve_pct"] > HIGH_PCT]
            close = [r for r in rr if r["warned"] and r["ve_pct"] is not None and abs(r["ve_pct"]) <= CLOSE_PCT]
            lines.append(f"| {noise} | {p} % | {len(rr)} | {100 * float(np.median(share)) if share else 0:.1f} % | "
                         f"{sum(r['warned'] for r in rr)} | {len(high)} | {sum(r['warned'] for r in high)} | "
                         f"{len(close)} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    return check_main(EvalsetCheck("echo_check", SECTION, echo_row, summary, ("datasheet", "none"),
                                   "noise models (default datasheet none)"), __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
