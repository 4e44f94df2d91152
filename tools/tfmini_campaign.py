"""The TFMini in the loop, measured: Ve on the paper's pile 1 and on the two-lobe test pile, lockstep over
several servo phases (with and without the datasheet noise) and networked over a pseudo-terminal
(datasheet noise), on the mission chosen for the TFMini's 12 m range. Writes its section of
docs/tfmini.md.

    python -m tools.tfmini_campaign [--phases 0 4 8 12 16] [--networked] [--out runs/tfmini-campaign]

Noise: "datasheet" is `--sensor-noise datasheet` for the TFmini-S (docs/sensor_noise.md: the manual's
6 cm / 1 % range noise, its 1 cm quantum, and no-returns near its rated range at low reflectance and
grazing incidence).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from firmware_py.core.sensor import TFMINI_S, Rangefinder
from firmware_py.core.storage import Storage
from ground.report import ReportOptions, make_report
from sitl.missions.range_check import range_coverage
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tools.doc_sections import write_section
from tools.fly_networked import fly_networked
from tools.make_two_lobe_pile import DEFAULT_OUT as TWO_LOBE

STORAGE = "30x20x10"
ALTITUDE_M = 9.0
P_TRAJ_PCT = 20.0
PILES = {"pile 1": "1", "two-lobe": str(TWO_LOBE)}
NOISES = ("none", "datasheet")
DOC = Path(__file__).resolve().parents[1] / "docs" / "tfmini.md"


def mission() -> Mission:
    return Mission(storage=Storage.parse(STORAGE), p_traj=P_TRAJ_PCT / 100, altitude_m=ALTITUDE_M)


def lockstep_ve(pile: str, noise: str, phase: int, out: Path) -> dict:
    cfg = FlyConfig(mission=mission(), stockpile=pile, payload="firmware", initial_position=phase, seed=phase,
                    rangefinder=Rangefinder.TFMINI, sensor_noise=noise)
    fly(cfg, out, force=True, progress=lambda _m: None)
    rep = make_report(out, out / "report", ReportOptions(plots=False), force=True)
    return {"ve_pct": rep["volume_error_pct"], "ra_pct": rep["coverage_ratio_pct"], "samples": rep["n_samples"],
            "points": rep["n_points_used"]}


def networked_ve(pile: str, out: Path) -> dict:
    run = fly_networked(["--p-traj", f"{P_TRAJ_PCT:g}", "--altitude", f"{ALTITUDE_M:g}"], STORAGE, pile, out,
                        say=lambda _m: None, rangefinder="tfmini", serve_args=["--sensor-noise", "datasheet"])
    if run.report is None:
        return {"ve_pct": None, "no_volume": run.no_volume, "payload_exit": run.payload_exit}
    return {"ve_pct": run.report["volume_error_pct"], "ra_pct": run.report["coverage_ratio_pct"],
            "samples": run.report["n_samples"], "points": run.report["n_points_used"], "wall_s": run.wall_s,
            "payload_exit": run.payload_exit}


def _stats(values: list[float]) -> str:
    return (f"{statistics.fmean(values):.2f} ({min(values):.2f}-{max(values):.2f})" if len(values) > 1
            else f"{values[0]:.2f}")


def page(results: dict, phases: list[int]) -> str:
    from firmware_py.core.waveform import named_waveform
    c = range_coverage(mission(), TFMINI_S.max_range_m, named_waveform("semi-triangular", 5.0, 0))
    lines = [
        "## TFMini in the loop (`python -m tools.tfmini_campaign`)",
        "",
        f"Mission: a {STORAGE} m bay, {ALTITUDE_M:g} m altitude, P_traj {P_TRAJ_PCT:g} %, 1 m/s, semi-triangular "
        f"sweep at 5 rad/s; the payload's TFMini driver reads the emulated TFmini-S (100 Hz, 12 m). "
        f"Geometry: {c.describe()} (README, \"Fly lower with a TFMini\").",
        "",
        "Noise \"datasheet\": `--sensor-noise datasheet` for the TFmini-S (range sigma the larger of 6 cm and 1 % "
        "of the range, the 1 cm quantum, no-returns near its rated range at low reflectance and grazing "
        "incidence: docs/sensor_noise.md).",
        "",
        f"Lockstep: servo phases {', '.join(map(str, phases))} (noise seeded by the phase); Ve in % as mean "
        "(min-max). Networked: `pilescan-sitl serve --rangefinder tfmini` + `pilescan-payload --uart "
        "serial:/dev/pts/N` + a scripted ground station, phase 0, one flight.",
        "",
        "| pile | true volume m^3 | lockstep Ve, no noise | lockstep Ve, datasheet | lockstep R_a % | "
        "networked Ve, datasheet | networked samples |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in results.items():
        none = [x["ve_pct"] for x in r["lockstep"]["none"]]
        ds = [x["ve_pct"] for x in r["lockstep"]["datasheet"]]
        ra = [x["ra_pct"] for x in r["lockstep"]["none"]]
        net = r.get("networked")
        net_ve = ("-" if net is None else f"{net['ve_pct']:.2f}" if net.get("ve_pct") is not None
                  else f"no volume ({net.get('no_volume')})")
        net_n = "-" if net is None or net.get("samples") is None else f"{net['samples']:,}"
        lines.append(f"| {name} | {r['true_volume_m3']:.1f} | {_stats(none)} | {_stats(ds)} | {_stats(ra)} | "
                     f"{net_ve} | {net_n} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--phases", type=int, nargs="+", default=[0, 4, 8, 12, 16])
    ap.add_argument("--networked", action="store_true", help="also fly each pile networked over a pty (real time)")
    ap.add_argument("--out", type=Path, default=Path("runs/tfmini-campaign"))
    ap.add_argument("--doc", type=Path, default=DOC, help="page whose tfmini-campaign section is rewritten")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    results: dict = {}
    for name, pile in PILES.items():
        r: dict = {"lockstep": {n: [] for n in NOISES}}
        for noise in NOISES:
            for phase in args.phases:
                got = lockstep_ve(pile, noise, phase, args.out / name.replace(" ", "") / f"{noise}-{phase}")
                r["lockstep"][noise].append(got)
                print(f"{name}, {noise}, phase {phase}: Ve {got['ve_pct']:.2f} %, R_a {got['ra_pct']:.1f} %",
                      file=sys.stderr)
        truth = json.loads((args.out / name.replace(" ", "") / f"none-{args.phases[0]}" / "truth.json").read_text())
        r["true_volume_m3"] = truth["true_volume_m3"]
        if args.networked:
            r["networked"] = networked_ve(pile, args.out / name.replace(" ", "") / "networked")
            print(f"{name}, networked: {r['networked']}", file=sys.stderr)
        results[name] = r
    text = page(results, args.phases)
    write_section(args.doc, "tfmini-campaign", text)
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
