"""The surface's slopes weighed on the evaluation set: the report's default, `--surface-slopes gp-bridges` (through
the heights a Gaussian process freed of their noise predicts where the cubic spans further than the smoothing windows
reach, `ground.gp_slopes`), against `--surface-slopes curvature` (scipy's least-curvature slopes through the node
heights as they are) and `--surface-slopes gp` (the process's heights at every node), each run surveyed once with
each by the whole report pipeline (fill, wall contacts, strip) and each noisy run held against its own noise-free twin
(the same pile, flight and servo phase; tools/evalset.py draws the three noise models on the same samples' flight).

The twin is the measure issue 14 sets for noise ("Ve with noise within 0.2 pp of the clean Ve"): what the noise did
to the volume, apart from what the flight's own gaps did to it. `tools.estimator_evalset` compares estimators refitted
to one survey's points with the `nearest` fill; this is the report as a user runs it, which a change of the default
must be measured on (docs/design-notes.md).

    python -m tools.slopes_evalset --jobs 2 --rows runs/slopes-evalset.csv --write docs/surface_estimators.md
    python -m tools.slopes_evalset --from-rows runs/slopes-evalset.csv
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Sequence

from firmware_py.core.cli import ArgumentParser
from tools.calibrate_interval import FACES_FAMILIES
from tools.doc_sections import write_section
from tools.evalset import add_rows_options, load_run, rows_of_options, survey_of

SECTION = "slopes-evalset"
NOISES = ("none", "datasheet", "appendix-a")
NOISY = ("datasheet", "appendix-a")
SLOPES = ("gp-bridges", "curvature", "gp")
"""The slopes compared, by their `--surface-slopes` names (ground.smoothing.NodeSlopes), the default first."""
COLUMNS = "gp-bridges (default) / curvature / gp"
"""How a table's cells list them."""
WITHIN_PP = 0.2
"""Issue 14's target for the noise's share: Ve with noise within this of the noise-free Ve (pp)."""


def run_row(path: str) -> dict | None:
    """One stored run surveyed with each slopes: its parameters, signed Ve [%] and seconds per survey; None for an
    empty building (no volume to be relative to)."""
    from ground.report import ReportOptions
    from ground.smoothing import NodeSlopes
    from ground.surface import grid_volume

    run = load_run(path)
    true_m3 = run.true_volume_m3
    if not true_m3 > 0:
        return None
    t = run.truth
    row = {"run_id": run.run_id, "family": t["family"], "building": t["building"], "p_traj_pct": int(t["p_traj_pct"]),
           "noise": t["noise"], "split": t["split"]}
    for name in SLOPES:
        t0 = time.perf_counter()
        sv = survey_of(run, ReportOptions(plots=False, surface_slopes=NodeSlopes(name)))
        row[f"{name}_s"] = time.perf_counter() - t0
        row[name] = 100.0 * (grid_volume(sv.heights, sv.grid) - true_m3) / true_m3
    return row


def twin_id(run_id: str, noise: str) -> str:
    """The noise-free twin's run id: the same id with the noise model's suffix replaced (tools.evalset's ids end in
    the noise model)."""
    if not run_id.endswith(noise):
        raise ValueError(f"run id {run_id!r} does not end in its noise model {noise!r}")
    return run_id[: -len(noise)] + "none"


def noise_shares(rows: Sequence[dict]) -> list[dict]:
    """Each noisy run with its twin found: its parameters and, per slopes, |Ve - the twin's Ve| (pp)."""
    by_id = {r["run_id"]: r for r in rows}
    out = []
    for r in rows:
        if r["noise"] == "none":
            continue
        twin = by_id.get(twin_id(r["run_id"], r["noise"]))
        if twin is None:
            continue
        out.append({"noise": r["noise"], "family": r["family"], "p_traj_pct": int(r["p_traj_pct"]),
                    **{n: abs(float(r[n]) - float(twin[n])) for n in SLOPES}})
    return out


def _cmp(values: Sequence[dict], key: str, fmt: str = "{:.2f}") -> str:
    means = (statistics.fmean(abs(float(v[n])) if key == "abs" else float(v[n]) for v in values) for n in SLOPES)
    return " / ".join(fmt.format(m) for m in means)


def table(rows: Sequence[dict], by: str) -> str:
    """Per group of `by`: runs, mean |Ve| and mean signed Ve (each of SLOPES); the height-map families only (a box's
    faces and a sphere's undercut are no slope's to get right: tools.calibrate_interval.FACES_FAMILIES)."""
    rows = [r for r in rows if r["family"] not in FACES_FAMILIES]
    out = [f"| {by} | runs | mean \\|Ve\\| [%], {COLUMNS} | mean signed Ve [%], {COLUMNS} |",
           "|---|---|---|---|"]
    for key in sorted({r[by] for r in rows}, key=lambda k: (str(type(k)), k)):
        rs = [r for r in rows if r[by] == key]
        out.append(f"| {key} | {len(rs)} | {_cmp(rs, 'abs')} | {_cmp(rs, 'signed', '{:+.2f}')} |")
    return "\n".join(out)


def share_table(shares: Sequence[dict], by: str) -> str:
    """Per noise model and group of `by`: the noisy runs' mean and median |Ve - twin's|, and how many are within
    WITHIN_PP of their twin, each of SLOPES (height-map families only, as `table`)."""
    shares = [s for s in shares if s["family"] not in FACES_FAMILIES]
    out = [f"| noise | {by} | runs | mean \\|Ve - twin's\\| [pp], {COLUMNS} | median | within {WITHIN_PP:g} pp |",
           "|---|---|---|---|---|---|"]
    for noise in NOISY:
        for key in sorted({s[by] for s in shares if s["noise"] == noise}, key=lambda k: (str(type(k)), k)):
            ss = [s for s in shares if s["noise"] == noise and s[by] == key]
            med = " / ".join(f"{statistics.median(float(s[n]) for s in ss):.2f}" for n in SLOPES)
            within = " / ".join(str(sum(float(s[n]) <= WITHIN_PP for s in ss)) for n in SLOPES)
            out.append(f"| {noise} | {key} | {len(ss)} | {_cmp(ss, 'signed')} | {med} | {within} |")
    return "\n".join(out)


def page_text(rows: Sequence[dict], cmd: str, made: str) -> str:
    """The page's section: how it was made, the noise's share by P_traj and by family, and the error against the
    truth (ValueError, KeyError or TypeError on rows that are not this tool's)."""
    rows = [{**r, "p_traj_pct": int(r["p_traj_pct"])} for r in rows]
    seconds = " / ".join(f"{statistics.median(float(r[f'{n}_s']) for r in rows):.2f}" for n in SLOPES)
    shares = noise_shares(rows)
    return (f"Regenerated by `{cmd}` ({len(rows)} stored runs; {made}). Each run of the evaluation set "
            "(docs/evaluation_set.md) reported by the whole pipeline three times, with the default slopes "
            "(`--surface-slopes gp-bridges`), `--surface-slopes curvature` and `--surface-slopes gp`; the box and "
            "sphere piles left out (faces and undercuts no slope holds). Median seconds a survey as the rows were "
            f"made, {COLUMNS}: {seconds}.\n\n"
            "What the noise did, each noisy run against its noise-free twin (same pile, flight and servo phase):\n\n"
            + share_table(shares, "p_traj_pct") + "\n\nBy pile family:\n\n" + share_table(shares, "family")
            + "\n\nAgainst the truth, by sensor-noise model:\n\n" + table(rows, "noise"))


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.slopes_evalset", description=__doc__.split("\n\n")[0])
    add_rows_options(ap)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = rows_of_options(ap, args, run_row, NOISES, chunksize=2)
    if rows is None:
        return 2
    if not rows:
        print("no runs with a volume to compare", file=sys.stderr)
        return 2
    minutes = (time.perf_counter() - t0) / 60.0
    cmd = " ".join(["python -m tools.slopes_evalset", *(sys.argv[1:] if argv is None else argv)])
    made = (f"the rows of {args.from_rows}" if args.from_rows is not None
            else f"{minutes:.1f} min with {args.jobs} worker(s)")
    try:
        text = page_text(rows, cmd, made)
    except (KeyError, TypeError, ValueError) as exc:  # a rows file of another tool, or edited by hand
        print(f"{args.from_rows}: not the rows of tools.slopes_evalset ({type(exc).__name__}: {exc})"[:300],
              file=sys.stderr)
        return 2
    if args.write is not None:
        write_section(args.write, SECTION, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
