"""The coverage planner against the paper's rectangles: R_a, Ve, flight time and energy per pile, and the
coverage model's predicted R_a against the reported one; writes its section of docs/coverage.md.

    python -m tools.coverage_campaign [--piles 1 2 corner] [--phases 0 5 10 15] [--coverage 99 99.8]
                                      [--jsbsim] [--out runs/coverage-campaign] [--write docs/coverage.md]
    python -m tools.coverage_campaign --spread [--plan-phase 0] --phases 0 1 ... 19 --coverage 99.8
    python -m tools.coverage_campaign --compare [--piles 1 2 corner wall] [--coverage 99.8] [--yaw-p-traj 20]

With --spread, each coverage target is planned once (for the servo start position --plan-phase, as
`pilescan-sitl plan` plans for position 0) and that one plan is flown at every --phases: the spread of Ve
over the servo's start position for the plan a user would fly (its own section of docs/coverage.md).

Every flight is `pilescan-sitl fly --plant ideal --payload batch` (the ideal plant, exact sampling) and every
report `pilescan-ground report` with its defaults. The ideal plant has no energy: the table gives the fitted
energy model's figure (`sitl.missions.coverage.EnergyModel`), and with --jsbsim each mission is also flown
once on the JSBSim F450 (pile 1, phase 0) for its measured flight time and energy.
`corner` is `sitl.world.shapes.make_shape("corner", ..., seed=0)`: a pile leaning into a building corner;
`wall` likewise a pile against one wall.

With --compare (issue 17's Must-show), every mission is flown once on the JSBSim F450 (the flight does not
depend on the pile or the servo: cached in --cache like `tools.experiments`' flights, and shared with them
for the rectangles) and surveyed on every pile at every --phases through the ground station's batch path
(`survey_from_samples`, the report's defaults): the coverage plan (planned for servo position 0, as
`pilescan-sitl plan` does) against the P_traj 5 % and 20 % rectangles and the paper's 1 deg/s yaw-rate case.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.frames import StorageFrame
from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import N_PHASES, named_waveform
from ground import cli as ground_cli
from ground.report import ReportOptions, survey_from_samples
from ground.surface import grid_volume, reconstructed_ratio_pct, volume_error_pct
from sitl.missions.coverage import CoverageTarget, WallBand, mission_energy_j, plan_coverage, predict_coverage
from sitl.missions.range_check import planning_limit
from sitl.missions.rectangle import Mission
from sitl.missions.surveyed_surface import load_height_field
from sitl.runners.flight import PAYLOAD_1D_KG, FlownMission, fly_mission
from sitl.runners.fly import FlyConfig, check_clearance, fly, log_header
from sitl.sensing.batch_sampler import sample_flight
from sitl.world import stockpile as piles
from sitl.world.raycast import World
from sitl.world.shapes import make_shape
from tools.doc_sections import write_section
from tools.experiments import ALL_EXPERIMENTS, FLIGHT_VERSION
from tools.sweep import cached

STORAGE = Storage()
DOC = Path(__file__).resolve().parents[1] / "docs" / "coverage.md"
SECTION = "coverage-campaign"
SPREAD_SECTION = "coverage-spread"
RECTANGLES_PCT = (5, 20)
VALIDATION_PCT = (5, 20, 30)
COMPARE_SECTION = "coverage-compare"
PAPER_YAW_RATE_DPS = 1.0
"""The paper's best-accuracy case (Table 2: R_a and Ve averaged over P_traj 5-30 %, +195 % energy)."""


@dataclass(frozen=True)
class Row:
    pile: str
    mission: str
    phase: int
    predicted_ra_pct: float
    hull_pct: float
    ra_pct: float
    ve_pct: float
    flight_s: float
    model_energy_j: float
    path_m: float


def pile_arg(name: str, out: Path) -> str:
    """--stockpile for a pile name: the paper's 1 and 2, or a generated shape written as STL once."""
    if name in ("1", "2"):
        return name
    path = out / f"{name}.stl"
    if not path.exists():
        out.mkdir(parents=True, exist_ok=True)
        make_shape(name, STORAGE, 9.0, seed=0).pile.mesh.export(path)
    return str(path)


def kinds(coverages: list[float]) -> list[str]:
    """The missions compared: the rectangles ('rect-5' ...) and the coverage plans ('coverage-99' ...)."""
    return [f"rect-{p}" for p in RECTANGLES_PCT] + [f"coverage-{c:g}" for c in coverages]


def mission_for(kind: str, phase: int, surface=None):
    """The rectangle at P_traj (kind 'rect-5' ...) or the coverage plan ('coverage-99') for this servo phase
    ('coverage-99-all': for the worst of all servo start positions; '-surface': on the given surface; '-bare':
    with the floor counted up to the walls, `--bare-walls`)."""
    if kind.startswith("rect-"):
        return Mission(STORAGE, p_traj=int(kind[5:]) / 100)
    wf = named_waveform("semi-triangular", 5.0, phase)
    pct, *flags = kind.split("-")[1:]
    also = tuple(named_waveform("semi-triangular", 5.0, k) for k in range(2 * N_PHASES) if k != phase) \
        if "all" in flags else ()
    target = CoverageTarget(float(pct), wf, planning_limit(LIDARLITE_V3), LIDARLITE_V3.rate_hz, also_waveforms=also,
                            surface=surface if "surface" in flags else None,
                            walls=None if "bare" in flags else WallBand.of(LIDARLITE_V3))
    return plan_coverage(STORAGE, target).mission


def fly_and_report(mission, stockpile: str, phase: int, out: Path, plant: str = "ideal") -> tuple[dict, dict]:
    fly(FlyConfig(mission=mission, stockpile=stockpile, initial_position=phase, plant=plant, payload="batch"),
        out, force=True, progress=lambda _m: None)
    code = ground_cli.main(["report", str(out), "--out", str(out / "report"), "--force", "--no-plots", "-q"])
    if code != 0:
        raise RuntimeError(f"pilescan-ground report {out} exited {code}")
    return (json.loads((out / "truth.json").read_text()), json.loads((out / "report" / "report.json").read_text()))


def run_case(pile: str, kind: str, phase: int, out: Path, mission=None, surface=None) -> Row:
    """One flight and its report; `mission` (default: planned for this phase) lets one plan fly at every phase;
    the prediction is on `surface` (an earlier survey's) when given."""
    m = mission if mission is not None else mission_for(kind, phase)
    wf = named_waveform("semi-triangular", 5.0, phase)
    pred = predict_coverage(m, wf, planning_limit(LIDARLITE_V3), LIDARLITE_V3.rate_hz, surface=surface)
    truth, rep = fly_and_report(m, pile_arg(pile, out), phase, out / f"{pile}-{kind}-k{phase}")
    return Row(pile, kind, phase, pred.predicted_ra_pct, pred.hull_pct, rep["coverage_ratio_pct"],
               rep["volume_error_pct"], truth["flight_time_s"], mission_energy_j(m), m.path_length_m())


def _ms(xs: list[float], fmt: str = ".2f") -> str:
    return f"{statistics.fmean(xs):{fmt}}" + (f" (max {max(xs):{fmt}})" if len(xs) > 1 else "")


def page(rows: list[Row], validation: list[Row], jsbsim: dict, args) -> str:
    out = [f"Generated by `python -m tools.coverage_campaign --piles {' '.join(args.piles)} --phases "
           f"{' '.join(map(str, args.phases))} --coverage {' '.join(f'{c:g}' for c in args.coverage)}"
           + (" --jsbsim" if args.jsbsim else "") + "`: ideal plant, batch payload, ideal sensing, "
           "`pilescan-ground report` defaults; means over the servo phases (max in brackets).", "",
           "| pile | mission | predicted R_a [%] | R_a [%] | Ve [%] | path [m] | flight [s] | model energy [kJ] |",
           "|---|---|---|---|---|---|---|---|"]
    for pile in args.piles:
        for kind in kinds(args.coverage):
            rs = [r for r in rows if r.pile == pile and r.mission == kind]
            if not rs:
                continue
            out.append(f"| {pile} | {kind} | {_ms([r.predicted_ra_pct for r in rs])} | "
                       f"{statistics.fmean(r.ra_pct for r in rs):.2f} (min {min(r.ra_pct for r in rs):.2f}) | "
                       f"{_ms([r.ve_pct for r in rs])} | {_ms([r.path_m for r in rs], '.0f')} | "
                       f"{_ms([r.flight_s for r in rs], '.0f')} | "
                       f"{_ms([r.model_energy_j / 1000 for r in rs], '.1f')} |")
    out += ["", "Model against flight (pile 1, the rectangle; the model sees a flat floor, the flight the pile):", "",
            "| P_traj | phase | predicted R_a [%] | of it, the hull alone [%] | reported R_a [%] | reported - hull "
            "[points] |", "|---|---|---|---|---|---|"]
    out += [f"| {r.mission[5:]} % | {r.phase} | {r.predicted_ra_pct:.2f} | {r.hull_pct:.2f} | {r.ra_pct:.2f} | "
            f"{r.ra_pct - r.hull_pct:+.2f} |" for r in validation]
    if jsbsim:
        out += ["", "JSBSim F450 (pile 1, phase 0, batch payload): measured against the energy model:", "",
                "| mission | flight [s] | energy [kJ] | model [kJ] | R_a [%] | Ve [%] |", "|---|---|---|---|---|---|"]
        out += [f"| {k} | {v['flight_s']:.1f} | {v['energy_j'] / 1000:.2f} | {v['model_j'] / 1000:.2f} | "
                f"{v['ra_pct']:.2f} | {v['ve_pct']:.3f} |" for k, v in jsbsim.items()]
    return "\n".join(out)


def spread_page(rows: list[Row], args) -> str:
    """One plan per target flown at every phase: R_a and Ve over the servo's start position."""
    out = [f"Generated by `python -m tools.coverage_campaign --spread --plan-phase {args.plan_phase} "
           + ("--plan-all-phases " if args.plan_all_phases else "")
           + (f"--surface {args.surface} " if getattr(args, "surface", None) else "") + "--piles "
           f"{' '.join(args.piles)} --phases {' '.join(map(str, args.phases))} --coverage "
           f"{' '.join(f'{c:g}' for c in args.coverage)} --spread-rect {' '.join(map(str, args.spread_rect))}`: "
           "each target planned once, for servo start position "
           f"{args.plan_phase}, and that one plan flown at all {len(args.phases)} start positions (ideal plant, batch "
           "payload, ideal sensing, `pilescan-ground report` defaults). Ve is |V - V_true| / V_true (eq. 8); the "
           "model's predicted R_a is for the plan at each flown position (on the --surface when given); "
           "coverage-PCT-all is planned for the worst of all 20 start positions (`--all-phases`), "
           "coverage-PCT-surface on the earlier survey's surface (`--surface`); "
           "rect-P is the paper's rectangle at P_traj P %.", "",
           "| pile | mission | phases | predicted R_a min [%] | R_a mean [%] | R_a min [%] | Ve mean [%] | Ve sd [%] "
           "| Ve max [%] (phase) | model energy [kJ] |", "|---|---|---|---|---|---|---|---|---|---|"]
    for pile in args.piles:
        for kind in dict.fromkeys(r.mission for r in rows):
            rs = [r for r in rows if r.pile == pile and r.mission == kind]
            if not rs:
                continue
            ve = [r.ve_pct for r in rs]
            worst = max(rs, key=lambda r: r.ve_pct)
            out.append(f"| {pile} | {kind} | {len(rs)} | {min(r.predicted_ra_pct for r in rs):.2f} | "
                       f"{statistics.fmean(r.ra_pct for r in rs):.2f} | {min(r.ra_pct for r in rs):.2f} | "
                       f"{statistics.fmean(ve):.3f} | {statistics.pstdev(ve):.3f} | {worst.ve_pct:.3f} "
                       f"({worst.phase}) | {rs[0].model_energy_j / 1000:.2f} |")
    return "\n".join(out)


def run_spread(args) -> int:
    rows = []
    surface = load_height_field(args.surface, STORAGE) if args.surface else None
    tag = "-surface" if surface is not None else ""
    kinds_flown = [f"coverage-{c:g}{tag}" for c in args.coverage]
    if args.plan_all_phases:
        kinds_flown += [f"coverage-{c:g}-all{tag}" for c in args.coverage]
    for kind in kinds_flown + [f"rect-{p}" for p in args.spread_rect]:
        m = mission_for(kind, args.plan_phase, surface)
        for pile in args.piles:
            for k in args.phases:
                rows.append(run_case(pile, kind, k, args.out / "spread", mission=m, surface=surface))
                r = rows[-1]
                print(f"{pile} {kind} (plan k{args.plan_phase}) k{k}: predicted {r.predicted_ra_pct:.2f} "
                      f"R_a {r.ra_pct:.2f} Ve {r.ve_pct:.3f}", file=sys.stderr)
    write_section(args.write, SPREAD_SECTION + ("-surface" if surface is not None else ""), spread_page(rows, args))
    print(f"wrote {args.write}")
    return 0


# ----- --compare: the Must-show on the JSBSim F450 -----------------------------------------------

@dataclass(frozen=True)
class Survey1:
    """One JSBSim flight surveyed on one pile at one servo start position."""

    pile: str
    mission: str
    phase: int
    ra_pct: float
    ve_pct: float
    flight_s: float
    energy_j: float
    model_energy_j: float
    path_m: float


def compare_missions(coverages: list[float], yaw_p_traj_pct: int, surface=None) -> dict[str, object]:
    """The missions of the comparison by name: the rectangles at P_traj 5 and 20 % (30 deg/s), the paper's
    1 deg/s case (the rectangle at yaw_p_traj_pct) and the coverage plans (servo position 0)."""
    out: dict[str, object] = {f"rect-{p}": ALL_EXPERIMENTS["baseline"].mission(p) for p in RECTANGLES_PCT}
    out[f"rect-{yaw_p_traj_pct}-yaw{PAPER_YAW_RATE_DPS:g}"] = Mission(
        STORAGE, p_traj=yaw_p_traj_pct / 100, yaw_rate_max_rad_s=math.radians(PAPER_YAW_RATE_DPS))
    for c in coverages:
        kind = f"coverage-{c:g}" + ("-surface" if surface is not None else "")
        out[kind] = mission_for(kind, 0, surface)
    return out


def flight_key(mission) -> str:
    """The JSBSim flight's cache key: a rectangle's is `tools.experiments`' (the sweeps share the file), any
    other mission's its content (`mission_id`)."""
    if isinstance(mission, Mission):
        e = ALL_EXPERIMENTS["baseline"]
        return (f"flight-v{FLIGHT_VERSION}-jsbsim-p{mission.p_traj * 100:g}-v{mission.speed_m_s:g}"
                f"-yaw{math.degrees(mission.yaw_rate_max_rad_s):g}-{mission.turn}-m{e.payload_kg:g}")
    return f"flight-v{FLIGHT_VERSION}-jsbsim-{mission.mission_id}-m{PAYLOAD_1D_KG:g}"


def flown_jsbsim(mission, cache_dir: Path) -> FlownMission:
    """The mission flown on the JSBSim F450 (40 g payload), from the cache when it was flown before."""
    flown = cached(cache_dir, flight_key(mission),
                   lambda: fly_mission(mission, StorageFrame(), payload_kg=PAYLOAD_1D_KG))
    if not flown.completed:
        raise RuntimeError(f"the JSBSim vehicle did not complete {flight_key(mission)}")
    return flown


COMPARE_VERSION = "4"
"""Bump when the survey of a cached flight changes (the ground station's defaults, the sampler). 2: the `carry-down`
fill is the default; 3: the `wall-strip` fill is the default; 4: `--surface-slopes gp-bridges` is
the default."""


def cached_survey(cache_dir: Path, flown: FlownMission, mission, pile: str, stockpile: str,
                  phase: int) -> tuple[float, float]:
    """survey_of_flight, cached beside the flight (key: the flight's, the pile's name and the servo position)."""
    key = f"survey-v{COMPARE_VERSION}-{flight_key(mission)}-{pile}-k{phase}"
    ra, ve = cached(cache_dir, key, lambda: list(survey_of_flight(flown, mission, stockpile, phase)), kind="json")
    return float(ra), float(ve)


def survey_of_flight(flown: FlownMission, mission, stockpile: str, phase: int) -> tuple[float, float]:
    """(R_a, Ve) of the flown trajectory on a pile at a servo start position: the batch sampler and the
    ground station's computation with the report's defaults (what `fly` + `pilescan-ground report` give)."""
    cfg = FlyConfig(mission=mission, stockpile=stockpile, initial_position=phase, plant="jsbsim", payload="batch")
    pile = piles.resolve(stockpile, STORAGE)
    check_clearance(mission, pile, cfg.pose_error)
    world = World(STORAGE, pile, max_range_m=cfg.lidar.max_range_m)
    t = np.arange(int(flown.duration_s * cfg.lidar.rate_hz) + 1) / cfg.lidar.rate_hz
    wf = cfg.servo_waveform()
    samples = sample_flight(flown.trajectory_at(t), wf, world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame,
                            noise=cfg.noise(), seed=cfg.seed)
    sv = survey_from_samples(samples, log_header(cfg, wf), STORAGE, cfg.frame, np.array(cfg.lever_arm_body_m),
                             ReportOptions(plots=False))
    return reconstructed_ratio_pct(sv.heights_fit), volume_error_pct(grid_volume(sv.heights, sv.grid), pile.volume_m3)


def _groups(rows: list[Survey1], piles, names):
    """(pile, mission, its rows) for each pile and mission that has rows, in the order given."""
    for pile in piles:
        for name in names:
            rs = [r for r in rows if r.pile == pile and r.mission == name]
            if rs:
                yield pile, name, rs


def compare_page(rows: list[Survey1], args) -> str:
    """The issue's Must-show table, and the coverage plan's spread over the servo start positions."""
    names = list(dict.fromkeys(r.mission for r in rows))
    n = len(args.phases)
    out = [f"Generated by `python -m tools.coverage_campaign --compare --piles {' '.join(args.piles)} --phases "
           f"{' '.join(map(str, args.phases))} --coverage {' '.join(f'{c:g}' for c in args.coverage)} --yaw-p-traj "
           f"{args.yaw_p_traj}`: every mission flown once on the JSBSim F450 (batch payload, 40 g) and surveyed "
           f"on every pile at {n} servo start positions (ideal sensing, the report's defaults). rect-P: the paper's "
           f"rectangle at P_traj P % (30 deg/s); rect-{args.yaw_p_traj}-yaw1: the paper's 1 deg/s case (Table 2 "
           f"averages it over P_traj 5-30 %; flown here at {args.yaw_p_traj} %); coverage-PCT: `pilescan-sitl plan "
           "--coverage PCT` (planned for servo position 0, flown at every position). R_a and Ve: mean over the "
           "positions, worst in brackets; flight time and energy: the JSBSim flight's (one flight per mission), model "
           "energy `EnergyModel`'s. Targets (issue 17), met when the worst position meets them: R_a >= 99 %, "
           "Ve <= 0.3 % on every pile, energy <= the P_traj 20 % rectangle's.", "",
           "| pile | mission | R_a [%] (min) | Ve [%] (max) | flight [s] | energy [kJ] | model energy [kJ] | "
           "path [m] | targets |", "|---|---|---|---|---|---|---|---|---|"]
    e20 = next((r.energy_j for r in rows if r.mission == "rect-20"), None)
    for pile, name, rs in _groups(rows, args.piles, names):
        ra = [r.ra_pct for r in rs]
        ve = [r.ve_pct for r in rs]
        met = [min(ra) >= 99.0, max(ve) <= 0.3, e20 is None or rs[0].energy_j <= e20 * (1 + 1e-9)]
        tags = "met" if all(met) else "missed: " + ", ".join(
            w for w, ok in zip(("R_a", "Ve", "energy"), met, strict=True) if not ok)
        out.append(f"| {pile} | {name} | {statistics.fmean(ra):.2f} ({min(ra):.2f}) | "
                   f"{statistics.fmean(ve):.3f} ({max(ve):.3f}) | {rs[0].flight_s:.1f} | "
                   f"{rs[0].energy_j / 1000:.2f} | {rs[0].model_energy_j / 1000:.2f} | {rs[0].path_m:.0f} | "
                   f"{tags} |")
    cov = [nm for nm in names if nm.startswith("coverage-")]
    if cov and n > 1:
        out += ["", f"Ve over the {n} servo start positions (target: max <= 0.5 %), JSBSim flights as above:", "",
                "| pile | mission | Ve mean [%] | Ve sd [%] | Ve max [%] (position) | R_a min [%] |",
                "|---|---|---|---|---|---|"]
        for pile, name, rs in _groups(rows, args.piles, names):
            ve = [r.ve_pct for r in rs]
            worst = max(rs, key=lambda r: r.ve_pct)
            out.append(f"| {pile} | {name} | {statistics.fmean(ve):.3f} | {statistics.pstdev(ve):.3f} | "
                       f"{worst.ve_pct:.3f} ({worst.phase}) | {min(r.ra_pct for r in rs):.2f} |")
    return "\n".join(out)


def run_compare(args) -> int:
    surface = load_height_field(args.surface, STORAGE) if args.surface else None
    missions = compare_missions(args.coverage, args.yaw_p_traj, surface)
    rows: list[Survey1] = []
    for name, m in missions.items():
        flown = flown_jsbsim(m, args.cache)
        model = mission_energy_j(m)
        print(f"{name}: JSBSim {flown.duration_s:.1f} s, {flown.energy_j / 1000:.2f} kJ (model {model / 1000:.2f})",
              file=sys.stderr)
        for pile in args.piles:
            stockpile = pile_arg(pile, args.out)
            for k in args.phases:
                ra, ve = cached_survey(args.cache, flown, m, pile, stockpile, k)
                rows.append(Survey1(pile, name, k, ra, ve, flown.duration_s, flown.energy_j, model,
                                    m.path_length_m()))
                print(f"  {pile} k{k}: R_a {ra:.2f} Ve {ve:.3f}", file=sys.stderr)
    write_section(args.write, COMPARE_SECTION + ("-surface" if surface is not None else ""), compare_page(rows, args))
    print(f"wrote {args.write}")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.coverage_campaign", description=__doc__.split("\n")[0])
    ap.add_argument("--piles", nargs="+", default=["1", "2", "corner"])
    ap.add_argument("--phases", nargs="+", type=int, default=[0, 5, 10, 15])
    ap.add_argument("--coverage", type=float, nargs="+", default=[99.0, 99.8])
    ap.add_argument("--jsbsim", action="store_true", help="also fly each mission once on JSBSim for its energy")
    ap.add_argument("--spread", action="store_true",
                    help="plan each target once (for --plan-phase) and fly that plan at every --phases")
    ap.add_argument("--plan-phase", type=int, default=0, metavar="K",
                    help=f"with --spread: the servo start position the plan is made for (0..{2 * N_PHASES - 1})")
    ap.add_argument("--plan-all-phases", action="store_true",
                    help="with --spread: also plan each target for the worst of all servo start positions "
                         "('coverage-PCT-all') and fly that plan at every --phases")
    ap.add_argument("--surface", default=None, metavar="REPORT_DIR",
                    help="with --spread: plan the coverage targets on this earlier survey's surface "
                         "('coverage-PCT-surface'; its own section)")
    ap.add_argument("--spread-rect", type=int, nargs="*", default=[20], metavar="PCT",
                    help="with --spread: also fly these P_traj rectangles at every phase (default 20)")
    ap.add_argument("--compare", action="store_true",
                    help="fly each mission once on JSBSim and survey it on every pile at every --phases "
                         "(the coverage plan against the rectangles and the paper's 1 deg/s case)")
    ap.add_argument("--yaw-p-traj", type=int, default=20, metavar="PCT",
                    help="with --compare: the P_traj of the paper's 1 deg/s rectangle (default 20)")
    ap.add_argument("--cache", type=Path, default=Path("runs/sweep-cache"),
                    help="with --compare: where JSBSim flights are cached (shared with tools.experiments)")
    ap.add_argument("--out", type=Path, default=Path("runs/coverage-campaign"))
    ap.add_argument("--write", type=Path, default=DOC)
    args = ap.parse_args(argv)
    bad = [k for k in [*args.phases, args.plan_phase] if not 0 <= k < 2 * N_PHASES]
    if bad:
        ap.error(f"servo start positions are 0..{2 * N_PHASES - 1}, got {bad[0]}")
    if args.spread:
        return run_spread(args)
    if args.compare:
        return run_compare(args)
    rows = []
    for pile in args.piles:
        for kind in kinds(args.coverage):
            for k in args.phases:
                rows.append(run_case(pile, kind, k, args.out))
                r = rows[-1]
                print(f"{pile} {kind} k{k}: predicted {r.predicted_ra_pct:.2f} R_a {r.ra_pct:.2f} Ve {r.ve_pct:.3f} "
                      f"{r.flight_s:.0f} s", file=sys.stderr)
    validation = [r for r in rows if r.pile == "1" and r.mission.startswith("rect-")]
    validation += [run_case("1", "rect-30", k, args.out) for k in args.phases]
    validation.sort(key=lambda r: (int(r.mission[5:]), r.phase))
    jsbsim = {}
    if args.jsbsim:
        for kind in kinds(args.coverage):
            m = mission_for(kind, 0)
            truth, rep = fly_and_report(m, "1", 0, args.out / f"jsbsim-{kind}", plant="jsbsim")
            jsbsim[kind] = {"flight_s": truth["flight_time_s"], "energy_j": truth["energy_j"],
                            "model_j": mission_energy_j(m),
                            "ra_pct": rep["coverage_ratio_pct"], "ve_pct": rep["volume_error_pct"]}
            print(f"jsbsim {kind}: {jsbsim[kind]}", file=sys.stderr)
    write_section(args.write, SECTION, page(rows, validation, jsbsim, args))
    print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
