"""Two-flight surveys: a short first flight, then `--fill-gaps` over what its report could not see; R_a and Ve
after each flight (the merged report of both logs after the second), flight time and energy of each; writes its
section of docs/coverage.md.

    python -m tools.gap_campaign [--piles 1 2 corner] [--first rect-30 coverage-95] [--phase 0]
                                 [--gap-coverage 95] [--plant jsbsim|ideal] [--out runs/gap-campaign]
                                 [--write docs/coverage.md]

Each flight is `pilescan-sitl fly --payload batch` on --plant (JSBSim F450 by default: its flight time and
energy are measured; the ideal plant has no energy, the fitted model's figure is given for both); the re-flight
is planned as `pilescan-sitl plan --fill-gaps REPORT` plans it (`sitl.missions.gaps`), for the flight's servo
start position; every report is `pilescan-ground report` with its defaults, the second on both logs
(`report RUN1 RUN2`). First flights: `rect-P` is the paper's rectangle at P_traj P %, `coverage-PCT` the
coverage planner's loop for PCT % (both from `tools.coverage_campaign`).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.waveform import N_PHASES, named_waveform
from ground import cli as ground_cli
from sitl.missions.coverage import CoverageTarget, mission_energy_j
from sitl.missions.gaps import DEFAULT_GAP_TARGET_PCT, load_gaps, plan_fill_gaps
from sitl.missions.range_check import planning_limit
from tools.coverage_campaign import DOC, STORAGE, fly_and_report, mission_for, pile_arg
from tools.doc_sections import write_section

SECTION = "gap-campaign"


@dataclass(frozen=True)
class Flight:
    pile: str
    first: str  # the first flight's mission kind
    flight: int  # 1 or 2
    mission: str
    path_m: float
    flight_s: float
    energy_j: float | None  # measured (JSBSim); None on the ideal plant
    model_energy_j: float
    predicted_pct: float | None  # the re-flight: predicted share of the gap cells
    predicted_ra_pct: float | None  # the re-flight: predicted merged R_a
    gap_cells: int | None
    ra_pct: float  # after this flight (the merged report's after the second)
    ve_pct: float
    bridged_cells: int | None = None  # of the gap cells, those inside the first report's hull far from its points


def _report(runs: list[Path], out: Path) -> dict:
    code = ground_cli.main(["report", *map(str, runs), "--out", str(out), "--force", "--no-plots", "-q"])
    if code != 0:
        raise RuntimeError(f"pilescan-ground report {' '.join(map(str, runs))} exited {code}")
    return json.loads((out / "report.json").read_text())


def two_flights(pile: str, first: str, phase: int, gap_pct: float, plant: str, out: Path) -> list[Flight]:
    """The first flight and its report, the fill-gaps plan from that report, its flight, the merged report."""
    stockpile = pile_arg(pile, out)
    run1, run2 = out / f"{pile}-{first}-k{phase}-1", out / f"{pile}-{first}-k{phase}-2-fill-gaps"
    m1 = mission_for(first, phase)
    truth1, rep1 = fly_and_report(m1, stockpile, phase, run1, plant=plant)
    wf = named_waveform("semi-triangular", 5.0, phase)
    target = CoverageTarget(gap_pct, wf, planning_limit(LIDARLITE_V3), LIDARLITE_V3.rate_hz)
    gaps = load_gaps(run1 / "report", STORAGE)
    first_row = Flight(pile, first, 1, first, m1.path_length_m(), truth1["flight_time_s"], truth1.get("energy_j"),
                       mission_energy_j(m1), None, None, None, rep1["coverage_ratio_pct"], rep1["volume_error_pct"])
    try:
        planned = plan_fill_gaps(STORAGE, gaps, target)
    except ValueError as exc:  # the planner refused: said in the table, not hidden
        return [first_row, Flight(pile, first, 2, f"fill-gaps refused: {exc}", 0.0, 0.0, None, 0.0, None, None,
                                  int(gaps.unseen.sum()), rep1["coverage_ratio_pct"], rep1["volume_error_pct"],
                                  None if gaps.bridged is None else int(gaps.bridged.sum()))]
    truth2, _ = fly_and_report(planned.mission, stockpile, phase, run2, plant=plant)
    merged = _report([run1, run2], out / f"{pile}-{first}-k{phase}-merged")
    rec = planned.mission.plan
    return [first_row,
            Flight(pile, first, 2, "fill-gaps", planned.mission.path_length_m(), truth2["flight_time_s"],
                   truth2.get("energy_j"), planned.energy_j, planned.coverage.gap_pct, planned.coverage.merged_ra_pct,
                   rec["gap_cells"], merged["coverage_ratio_pct"], merged["volume_error_pct"], rec["bridged_cells"])]


def _cells(r: Flight) -> str:
    if r.gap_cells is None:
        return "-"
    return f"{r.gap_cells}" + ("" if r.bridged_cells is None else f" ({r.bridged_cells})")


def _kj(v: float | None) -> str:
    return "-" if v is None else f"{v / 1000:.2f}"


def page(rows: list[Flight], args) -> str:
    out = [f"Generated by `python -m tools.gap_campaign --piles {' '.join(args.piles)} --first "
           f"{' '.join(args.first)} --phase {args.phase} --gap-coverage {args.gap_coverage:g} --plant {args.plant}`: "
           f"{'the JSBSim F450' if args.plant == 'jsbsim' else 'the ideal plant'}, batch payload, ideal sensing, servo "
           f"start position {args.phase}, `pilescan-ground report` defaults. Flight 1 is the first flight alone; "
           "flight 2 is `--fill-gaps` planned from flight 1's report, and its R_a and Ve are the merged report's "
           "(`pilescan-ground report RUN1 RUN2`). Predicted: the share of flight 1's unseen cells the re-flight "
           "covers, and the merged R_a, by the coverage model on flight 1's surface. Unseen cells: those flight 1's "
           "report filled, and (bridged) those inside its points' hull with no point within the seen radius (1 m).",
           "",
           "| pile | flight | mission | path [m] | flight [s] | energy [kJ] | model energy [kJ] | "
           "unseen cells (bridged) | predicted: gaps covered [%] / R_a [%] | R_a after [%] | Ve after [%] |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        pred = "-" if r.predicted_pct is None else f"{r.predicted_pct:.1f} / {r.predicted_ra_pct:.2f}"
        out.append(f"| {r.pile} | {r.flight} | {r.mission} | {r.path_m:.0f} | {r.flight_s:.1f} | {_kj(r.energy_j)} | "
                   f"{_kj(r.model_energy_j)} | {_cells(r)} | {pred} | "
                   f"{r.ra_pct:.2f} | {r.ve_pct:.3f} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.gap_campaign", description=__doc__.split("\n")[0])
    ap.add_argument("--piles", nargs="+", default=["1", "2", "corner"])
    ap.add_argument("--first", nargs="+", default=["rect-30"], metavar="KIND",
                    help="first flights: rect-P (P_traj P %%) or coverage-PCT (default rect-30)")
    ap.add_argument("--phase", type=int, default=0, metavar="K", help="servo start position of both flights")
    ap.add_argument("--gap-coverage", type=float, default=DEFAULT_GAP_TARGET_PCT, metavar="PCT",
                    help=f"the re-flight's target share of the unseen cells (default {DEFAULT_GAP_TARGET_PCT:g})")
    ap.add_argument("--plant", choices=("jsbsim", "ideal"), default="jsbsim")
    ap.add_argument("--out", type=Path, default=Path("runs/gap-campaign"))
    ap.add_argument("--write", type=Path, default=DOC)
    args = ap.parse_args(argv)
    if not 0 <= args.phase < 2 * N_PHASES:
        ap.error(f"servo start positions are 0..{2 * N_PHASES - 1}, got {args.phase}")
    bad = [k for k in args.first if not (k.startswith("rect-") or k.startswith("coverage-"))]
    if bad:
        ap.error(f"first flights are rect-P or coverage-PCT, got {bad[0]}")
    rows = []
    for pile in args.piles:
        for first in args.first:
            rows += two_flights(pile, first, args.phase, args.gap_coverage, args.plant, args.out)
            a, b = rows[-2:]
            print(f"{pile} {first}: R_a {a.ra_pct:.2f} -> {b.ra_pct:.2f}, Ve {a.ve_pct:.3f} -> {b.ve_pct:.3f} "
                  f"({b.mission}, predicted gaps {b.predicted_pct} %)", file=sys.stderr)
    write_section(args.write, SECTION, page(rows, args))
    print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
