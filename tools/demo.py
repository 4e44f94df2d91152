"""`make demo`: fly the default stockpile in the SITL, run the ground station, print a summary.

Pile 1 of the paper at P_traj = 20 %, the baseline mission of Table 1, JSBSim plant, with the
unchanged payload firmware in the loop (MAVLink pose tagging, emulated LIDAR-Lite and servo).
`--write-readme README.md` puts the printed summary into the README (its demo-summary section) and the report's
point-cloud figure beside it (README_FIGURE, under the README's folder), so both are the same flight's.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from ground.report import ReportOptions, make_report
from sitl.missions.rectangle import Mission
from sitl.runners.fly import PAYLOADS, FlyConfig, fly
from tools.doc_sections import write_section

README_FIGURE = Path("docs/figures/demo_cloud_top.png")
"""The README's picture of the demo flight (the report's point cloud, top view), relative to the README's folder."""
REPORT_FIGURE = "cloud_top.png"


def summary_table(rep: dict, fly_s: float, ground_s: float, flight: dict | None = None) -> str:
    def fmt(v, unit="", spec=".2f"):
        return "unknown" if v is None else f"{v:{spec}}{unit}"
    rows = [
        ("volume", fmt(rep["volume_m3"], " m³", ",.1f")),
        ("90 % interval", "unknown" if rep.get("volume_interval_m3") is None else
         f"{rep['volume_interval_m3'][0]:,.1f} - {rep['volume_interval_m3'][1]:,.1f} m³"),
        ("true volume", fmt(rep["true_volume_m3"], " m³", ",.1f")),
        ("Ve (eq. 8)", fmt(rep["volume_error_pct"], " %")),
        ("R_a (eq. 9)", fmt(rep["coverage_ratio_pct"], " %")),
        ("points used", f"{rep['n_points_used']:,} of {rep['n_samples']:,} samples"),
        *([("flight", f"{flight['flight_time_s']:.0f} s, {flight['energy_j'] / 1000:.1f} kJ ({flight['plant']} plant)")]
          if flight and flight.get("energy_j") is not None else []),
        ("wall time", f"{fly_s + ground_s:.2f} s (flight {fly_s:.2f} s, ground {ground_s:.2f} s)"),
    ]
    w = max(len(k) for k, _ in rows)
    lines = [f"{'-' * (w + 2)}+{'-' * 44}"] + [f" {k:<{w}} | {v}" for k, v in rows] + [f"{'-' * (w + 2)}+{'-' * 44}"]
    lines += [f" WARNING: {x}" for x in rep["warnings"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="runs/demo", help="where to put the run and the report")
    ap.add_argument("--stockpile", default="1")
    ap.add_argument("--p-traj", type=float, default=20.0, help="percent")
    ap.add_argument("--payload", choices=PAYLOADS, default="firmware",
                    help="firmware in the loop (default) or the fast vectorised batch sampler")
    ap.add_argument("--write-readme", type=Path, default=None, metavar="README.md",
                    help="also (re)write the summary block of this page (its demo-summary section)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    print(f"pilescan demo: stockpile {args.stockpile}, P_traj {args.p_traj:g} %, 60x40x15 m building, JSBSim F450 "
          f"at 1 m/s and 12 m, 30 deg/s yaw, semi-triangular servo at 5 rad/s, LiDAR 500 Hz, {args.payload} payload")
    t0 = time.perf_counter()
    fly(FlyConfig(mission=Mission(p_traj=args.p_traj / 100), stockpile=args.stockpile, payload=args.payload),
        out / "run", force=True,
        progress=lambda m: print(f"  sitl: {m}"))
    t1 = time.perf_counter()
    rep = make_report(out / "run", out / "report", ReportOptions(), force=True)
    t2 = time.perf_counter()
    truth = json.loads((out / "run" / "truth.json").read_text())
    table = summary_table(rep, t1 - t0, t2 - t1, truth)
    print(table)
    if args.write_readme:
        write_section(args.write_readme, "demo-summary", f"```\n{table}\n```")
        figure = args.write_readme.resolve().parent / README_FIGURE
        figure.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(out / "report" / REPORT_FIGURE, figure)
    print(f"report: {(out / 'report' / 'report.html').resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
