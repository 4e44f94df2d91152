"""The TFMini in the loop, measured on a mission chosen for its range: Ve on the paper's pile 1 and on the
two-lobe test pile, both at half height, lockstep over servo phases and networked over a pseudo-terminal,
each with ideal returns and with the datasheet noise. Writes its section of docs/tfmini.md.

    python -m tools.tfmini_campaign [--phases 0 2 4 ...] [--networked] [--out runs/tfmini-campaign]
    python -m tools.tfmini_campaign --piles-only    # just write the two piles (runs/tfmini-campaign/piles)

The mission (`mission()`): the TFmini-S's 12 m is rated on a 90 % reflective board; on the 30 %
reflective surfaces the datasheet noise assumes, it echoes for certain out to 6.2 m at normal incidence
and less obliquely (`sitl.missions.range_check.planning_limit`). So the flight is low, ALTITUDE_M over the
floor, over piles half the paper's height (their tops TOP_CLEARANCE_M below it at least), and P_traj is
the largest that keeps the legs within the bare floor's reach of the walls, where a pile's foot lies
(`p_traj_pct`). The piles are written as STL meshes into the output folder (deterministic): pile 1 is
the paper's generator with its control heights halved (`PileSpec(height_min_m=0.5, height_max_m=3.5)`,
the same pile at half height), the two-lobe pile is `tools.make_two_lobe_pile`'s mesh with its heights
halved.

Noise: "datasheet" is `--sensor-noise datasheet` for the TFmini-S (docs/sensor_noise.md: the manual's
6 cm / 1 % range noise, its 1 cm quantum, and no-returns near its rated range at low reflectance and
grazing incidence).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from firmware_py.core.samplelog import read_samplelog
from firmware_py.core.sensor import TFMINI_S, Rangefinder
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from ground.report import ReportOptions, make_report
from sitl.missions.range_check import check_range, planning_limit, range_coverage
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from sitl.world.stockpile import PAPER_PILES, PileSpec, generate, load_mesh
from tools.doc_sections import write_section
from tools.fly_networked import fly_networked
from tools.make_two_lobe_pile import two_lobe_mesh

STORAGE = "30x20x10"
ALTITUDE_M = 5.0
"""Low enough that the bare floor is reached 3 m either side of the track (the legs then run 2-3 m from
the walls), high enough over half-height piles (top 3.6 m) to keep TOP_CLEARANCE_M."""
TOP_CLEARANCE_M = 1.0
"""The least gap between the flight and a pile's top the campaign accepts (the mission's own minimum is
0.5 m; the autopilot holds its altitude within centimetres here, the lowest flown is in the doc)."""
PILE_SCALE = 0.5
SPEED_M_S = 1.0
NOISES = ("none", "datasheet")
DEFAULT_PHASES = list(range(0, 20, 2))  # both sweep directions (Fig. 9: K >= 10 sweeps the other way)
DOC = Path(__file__).resolve().parents[1] / "docs" / "tfmini.md"
WF = named_waveform("semi-triangular", 5.0, 0)
LEVER_ARM_Z_M = FlyConfig.__dataclass_fields__["lever_arm_body_m"].default[2]


def p_traj_pct(altitude_m: float = ALTITUDE_M) -> int:
    """The largest whole P_traj that keeps every leg within the bare floor's reach of its wall at this
    altitude, with the datasheet noise's planning range (range_check's remedy)."""
    s = Storage.parse(STORAGE)
    reach = planning_limit(TFMINI_S, "datasheet").floor_reach_m(altitude_m - LEVER_ARM_Z_M)
    return math.floor(100.0 * reach / max(s.length_m, s.width_m))


def mission() -> Mission:
    return Mission(storage=Storage.parse(STORAGE), p_traj=p_traj_pct() / 100, altitude_m=ALTITUDE_M,
                   speed_m_s=SPEED_M_S)


def make_piles(folder: Path) -> dict[str, Path]:
    """Write the two half-height piles as STL meshes in folder; {name: path}."""
    folder.mkdir(parents=True, exist_ok=True)
    storage = Storage.parse(STORAGE)
    base = PileSpec()
    p1 = PAPER_PILES["1"]
    pile1 = generate(PileSpec(seed=p1["seed"], zero_edges=p1["zero_edges"],
                              height_min_m=base.height_min_m * PILE_SCALE,
                              height_max_m=base.height_max_m * PILE_SCALE), storage).mesh
    lobes = two_lobe_mesh()
    lobes.vertices = lobes.vertices * np.array([1.0, 1.0, PILE_SCALE])
    out = {"pile 1, half height": folder / "pile1_half.stl", "two-lobe, half height": folder / "two_lobe_half.stl"}
    for mesh, path in zip((pile1, lobes), out.values(), strict=True):
        mesh.export(path)
    return out


def lockstep(pile: Path, noise: str, phase: int, out: Path) -> dict:
    cfg = FlyConfig(mission=mission(), stockpile=str(pile), payload="firmware", initial_position=phase, seed=phase,
                    rangefinder=Rangefinder.TFMINI, sensor_noise=noise)
    fly(cfg, out, force=True, progress=lambda _m: None)
    rep = make_report(out, out / "report", ReportOptions(plots=False), force=True)
    return {"ve_pct": rep["volume_error_pct"], "ra_pct": rep["coverage_ratio_pct"], "samples": rep["n_samples"],
            "points": rep["n_points_used"], "lowest_m": lowest_altitude_m(out)}


def networked(pile: Path, noise: str, out: Path) -> dict:
    m = mission()
    run = fly_networked(["--p-traj", f"{100 * m.p_traj:g}", "--altitude", f"{m.altitude_m:g}", "--speed",
                         f"{m.speed_m_s:g}"], STORAGE, str(pile), out, say=lambda _m: None, rangefinder="tfmini",
                        serve_args=["--sensor-noise", noise])
    if run.report is None:
        return {"ve_pct": None, "no_volume": run.no_volume, "payload_exit": run.payload_exit}
    return {"ve_pct": run.report["volume_error_pct"], "ra_pct": run.report["coverage_ratio_pct"],
            "samples": run.report["n_samples"], "points": run.report["n_points_used"], "wall_s": run.wall_s,
            "payload_exit": run.payload_exit}


def lowest_altitude_m(run_dir: Path) -> float:
    """The lowest the vehicle flew while the payload logged (NED z is down)."""
    return float(-np.max(read_samplelog(run_dir / "samples.pslog").samples["z_m"]))


def _stats(values: list[float]) -> str:
    return (f"{statistics.fmean(values):.2f} ({min(values):.2f}-{max(values):.2f})" if len(values) > 1
            else f"{values[0]:.2f}")


def _net(r: dict | None) -> str:
    if r is None:
        return "-"
    if r.get("ve_pct") is None:
        return f"no volume ({r.get('no_volume')}, payload exit {r.get('payload_exit')})"
    return f"{r['ve_pct']:.2f} ({r['samples']:,} samples)"


def page(results: dict, phases: list[int]) -> str:
    m = mission()
    limit = planning_limit(TFMINI_S, "datasheet")
    c = range_coverage(m, limit, WF)
    old = replace(m, altitude_m=9.0, p_traj=0.20)
    try:
        check_range(old, limit, WF)
        old_verdict = "flown"
    except ValueError:
        old_verdict = "refused"
    warning = check_range(m, limit, WF)
    tops = ", ".join(f"{name}: {r['top_m']:.2f} m" for name, r in results.items())
    lowest = min(x["lowest_m"] for r in results.values() for runs in r["lockstep"].values() for x in runs)
    lines = [
        "## TFMini in the loop (`python -m tools.tfmini_campaign`)",
        "",
        f"Mission: a {STORAGE} m bay, {m.altitude_m:g} m altitude, P_traj {100 * m.p_traj:g} %, "
        f"{m.speed_m_s:g} m/s, semi-triangular sweep (+-90 deg) at 5 rad/s; the payload's TFMini driver reads the "
        "emulated TFmini-S (100 Hz, 12 m).",
        "",
        f"Why: planning range {limit.describe()}. From {c.sensor_height_m:.1f} m the bare floor is reached "
        f"{c.floor_reach_m:.1f} m either side of the track (out to +-{c.floor_reach_deg:.0f} deg of the sweep; "
        f"the walls {c.near_wall_m:.1f} m or nearer are met square at its ends), so P_traj "
        f"{100 * m.p_traj:g} % is the largest that keeps the legs within that of the walls, where a pile's foot "
        f"lies (`tools.tfmini_campaign.p_traj_pct`). The floor's reach is widest, "
        f"{limit.floor_reach_m(limit.widest_floor_height_m):.1f} m, from {limit.widest_floor_height_m:.1f} m: "
        f"lower buys little and costs the clearance. The piles' tops ({tops}) "
        f"stay at least {TOP_CLEARANCE_M:g} m under the flight; the lowest the vehicle flew while logging, in any "
        f"lockstep run, was {lowest:.2f} m. The old mission (9 m, P_traj 20 %) is {old_verdict} by the "
        "mission check with the datasheet noise; this one is flown with its warning:",
        "",
        f"> {warning}" if warning else "> (no warning)",
        "",
        "The bare floor in the middle of an empty bay is out of reach from any height (it would need a bay at "
        f"most {4 * c.floor_reach_m:.0f} m wide); here the piles cover it, and their surfaces are nearer. The "
        "full +-90 deg sweep stays: beyond the floor's reach it still meets the piles' flanks and, at its ends, "
        "the walls, which the ground station's self-calibration uses; a narrower sweep reaches no farther.",
        "",
        "Noise \"datasheet\": `--sensor-noise datasheet` for the TFmini-S (range sigma the larger of 6 cm and 1 % "
        "of the range, the 1 cm quantum, no-returns near its rated range at low reflectance and grazing "
        "incidence: docs/sensor_noise.md).",
        "",
        f"Lockstep: servo phases {', '.join(map(str, phases))} (noise seeded by the phase); Ve in % as mean "
        "(min-max). Networked: `pilescan-sitl serve --rangefinder tfmini --sensor-noise ...` + `pilescan-payload "
        "--uart serial:/dev/pts/N` + a scripted ground station, phase 0, one flight each.",
        "",
        "| pile | top m | true volume m^3 | lockstep Ve, no noise | lockstep Ve, datasheet | lockstep R_a %, "
        "datasheet | networked Ve, no noise | networked Ve, datasheet |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        none = [x["ve_pct"] for x in r["lockstep"]["none"]]
        ds = [x["ve_pct"] for x in r["lockstep"]["datasheet"]]
        ra = [x["ra_pct"] for x in r["lockstep"]["datasheet"]]
        net = r.get("networked") or {}
        lines.append(f"| {name} | {r['top_m']:.2f} | {r['true_volume_m3']:.1f} | {_stats(none)} | {_stats(ds)} | "
                     f"{_stats(ra)} | {_net(net.get('none'))} | {_net(net.get('datasheet'))} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--phases", type=int, nargs="+", default=DEFAULT_PHASES)
    ap.add_argument("--networked", action="store_true",
                    help="also fly each pile networked over a pty, without and with noise (real time)")
    ap.add_argument("--out", type=Path, default=Path("runs/tfmini-campaign"))
    ap.add_argument("--doc", type=Path, default=DOC, help="page whose tfmini-campaign section is rewritten")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--piles-only", action="store_true", help="write the half-height piles to OUT/piles and stop")
    args = ap.parse_args(argv)
    if any(not 0 <= k < 20 for k in args.phases):
        ap.error("--phases: each servo phase must be 0..19")
    storage = Storage.parse(STORAGE)
    piles = make_piles(args.out / "piles")
    if args.piles_only:
        for name, path in piles.items():
            print(f"{name}: {path}")
        return 0
    results: dict = {}
    for name, path in piles.items():
        pile = load_mesh(path, storage)
        if mission().altitude_m - pile.max_height_m < TOP_CLEARANCE_M:
            print(f"{name}: top {pile.max_height_m:.2f} m is within {TOP_CLEARANCE_M:g} m of the "
                  f"{mission().altitude_m:g} m flight", file=sys.stderr)
            return 2
        r: dict = {"lockstep": {n: [] for n in NOISES}, "true_volume_m3": pile.volume_m3, "top_m": pile.max_height_m}
        key = path.stem
        for noise in NOISES:
            for phase in args.phases:
                got = lockstep(path, noise, phase, args.out / key / f"{noise}-{phase}")
                r["lockstep"][noise].append(got)
                print(f"{name}, {noise}, phase {phase}: Ve {got['ve_pct']:.2f} %, R_a {got['ra_pct']:.1f} %",
                      file=sys.stderr)
        if args.networked:
            r["networked"] = {}
            for noise in NOISES:
                r["networked"][noise] = networked(path, noise, args.out / key / f"networked-{noise}")
                print(f"{name}, networked, {noise}: {r['networked'][noise]}", file=sys.stderr)
        results[name] = r
    text = page(results, args.phases)
    write_section(args.doc, "tfmini-campaign", text)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
