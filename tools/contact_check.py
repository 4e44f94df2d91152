"""The wall contacts (`ground.wall_contact`) scored against the true ground over the stored evaluation set.

A wall contact says how high the material meets a wall where a sweep saw it do so: the fill takes it as evidence at
the walls' feet and in the corners. Each run is surveyed as the report surveys it, its contacts made from the
survey's placed cloud and structure as the report makes them, and each contact's estimate compared with the true
ground at its place (the pile cast straight down, `World.heights_below_m`). The table counts, per noise model, the
contacts more than OFF_M off and those whose bounds miss the truth, split by the leaning test
(`WallContacts.leans_as_measured`): a pair whose material leans on the wall as measured, and one that passes only
within the test's noise allowance, which under a pointing error is where the wrong contacts are
(docs/design-notes.md, "Wall contacts under a pointing error").

Usage: python -m tools.contact_check [--root runs/evalset] [--noise none datasheet appendix-a] [--p-traj P ...]
           [--stride 1] [--jobs 2] [--write docs/unseen.md]  (the table into the page's section contact-check)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ground.pointcloud import SensorErrorModel
from ground.report import ReportOptions, survey_from_samples
from ground.wall_contact import wall_contacts
from tools.evalset import BUILDING_BY_NAME, EvalRun, Instance, load_run
from tools.evalset_check import EvalsetCheck, check_main

SECTION = "contact-check"
OFF_M = 1.0
"""A contact further than this from the true ground at its place is counted wrong (a metre of material at a wall)."""
NOISES = ("none", "datasheet", "appendix-a")
GROUPS = ("leaning", "allowance")
"""The contacts whose material leans on the wall as measured, and those that pass the leaning test only within its
noise allowance."""


def true_pile(run: EvalRun):
    """The run's true pile (`sitl.world.stockpile.Stockpile`): the evaluation set's generated pile (its building,
    family, seed and altitude in truth.json), or a named stockpile (`stockpile`); None when truth.json names neither."""
    from sitl.world.shapes import Family
    from sitl.world.stockpile import resolve

    t = run.truth
    if t.get("building") in BUILDING_BY_NAME and all(k in t for k in ("family", "seed", "altitude_m")):
        return Instance(str(t["building"]), Family(t["family"]), int(t["seed"]), float(t["altitude_m"])).shape().pile
    if "stockpile" in t:
        return resolve(str(t["stockpile"]), run.storage)
    return None


def contact_row(run_dir: str) -> dict | None:
    """One run's contacts against its true ground: counts and error sums per group (summable over runs); None for a
    run without a true surface to score against."""
    from sitl.world.raycast import World

    r = load_run(run_dir)
    pile = true_pile(r)
    if pile is None:
        return None
    sv = survey_from_samples(r.samples, r.header, r.storage, r.frame, r.lever_arm_body_m, ReportOptions(plots=False))
    err = SensorErrorModel.from_header(r.header)
    c = wall_contacts(sv.cloud, sv.structure, r.storage, err, sv.grid.cell_m)
    inside = np.clip(c.xy_m, 1e-3, [r.storage.length_m - 1e-3, r.storage.width_m - 1e-3])  # on the wall's inner side
    truth = World(r.storage, pile).heights_below_m(inside)
    miss = c.height_m - truth
    outside = (truth < c.low_m - 1e-6) | (truth > c.high_m + 1e-6)
    lean = np.ones(len(c), dtype=bool) if c.leans_as_measured is None else np.asarray(c.leans_as_measured, bool)
    row = {"run": r.run_id, "noise": r.truth.get("noise", "?"), "p_traj": int(r.truth.get("p_traj_pct", 0)),
           "family": r.truth.get("family", "?"), "contacts": len(c)}
    for group, k in zip(GROUPS, (lean, ~lean), strict=True):
        row.update({f"{group}_n": int(k.sum()), f"{group}_sum_m": float(miss[k].sum()),
                    f"{group}_sumsq_m2": float((miss[k] ** 2).sum()),
                    f"{group}_off": int((np.abs(miss[k]) > OFF_M).sum()), f"{group}_outside": int(outside[k].sum())})
    return row


def _group_cells(rows: Sequence[dict], group: str) -> str:
    n = sum(r[f"{group}_n"] for r in rows)
    if not n:
        return "0 | - | - | - | -"
    mean = sum(r[f"{group}_sum_m"] for r in rows) / n
    rms = (sum(r[f"{group}_sumsq_m2"] for r in rows) / n) ** 0.5
    off, out = sum(r[f"{group}_off"] for r in rows), sum(r[f"{group}_outside"] for r in rows)
    return f"{n:,} | {mean:+.2f} | {rms:.2f} | {100 * off / n:.1f} % | {100 * out / n:.1f} %"


def summary(rows: Sequence[dict]) -> list[str]:
    """The table's lines: per noise model, the contacts of each group, their mean and RMS error (estimate minus the
    true ground, m), the share more than OFF_M off and the share whose bounds miss the truth."""
    cols = f"mean (m) | RMS (m) | > {OFF_M:g} m off | truth outside bounds"
    lines = [f"| noise | runs | contacts | leaning as measured | {cols} | leaning only within the allowance | {cols} |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for noise in [n for n in NOISES if any(r["noise"] == n for r in rows)] + sorted(
            {r["noise"] for r in rows} - set(NOISES)):
        rr = [r for r in rows if r["noise"] == noise]
        lines.append(f"| {noise} | {len(rr)} | {sum(r['contacts'] for r in rr):,} | {_group_cells(rr, 'leaning')} | "
                     f"{_group_cells(rr, 'allowance')} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    return check_main(EvalsetCheck("contact_check", SECTION, contact_row, summary, NOISES,
                                   "noise models (default: all three)", chunksize=2, p_traj=True,
                                   no_rows="none of the chosen runs states a true surface to score against"),
                      __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
