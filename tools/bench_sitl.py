"""SITL benchmark (medians; never asserted in tests): the baseline P_traj 5 % mission flown lockstep
by the JSBSim vehicle alone, and the whole `fly` (vehicle + LiDAR samples + run directory).
Usage: python -m tools.bench_sitl [--repeat 5] [--write docs/benchmarks-sitl.md] [--readme README.md]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from firmware_py.core.frames import StorageFrame
from sitl.missions.rectangle import Mission
from sitl.runners.flight import fly_mission
from sitl.runners.fly import FlyConfig, fly
from tools.doc_sections import write_dated_section


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--readme", type=Path,
                    help="also write the table into this page's marked section bench-sitl (README.md)")
    ap.add_argument("--write", type=Path)
    args = ap.parse_args(argv)
    mission = Mission(p_traj=0.05)
    walls, sim = [], 0.0
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        flown = fly_mission(mission, StorageFrame())
        walls.append(time.perf_counter() - t0)
        sim = flown.duration_s
    # the vehicle also hovers SETTLE_S before the survey; count only the survey against the target
    med = statistics.median(walls)
    rows = [f"| JSBSim vehicle only, baseline P_traj 5 % ({sim:.0f} s survey + 10 s settle) | {med:.3f} s | "
            f"{(sim + 10) / med:.0f}x real time | target >= 150x |"]
    with tempfile.TemporaryDirectory() as tmp:
        fw = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            fly(FlyConfig(mission=mission), Path(tmp) / "run", force=True)
            fw.append(time.perf_counter() - t0)
    fmed = statistics.median(fw)
    rows.append(f"| `fly --plant jsbsim`: vehicle + 500 Hz LiDAR samples + run directory | {fmed:.3f} s | "
                f"{(sim + 10) / fmed:.0f}x real time | |")
    text = "\n".join([f"Medians of {args.repeat} runs.", "", "| benchmark | median | ratio | note |",
                      "|---|---|---|---|", *rows])
    print(text)
    if args.write:
        args.write.write_text("# SITL benchmarks\n\nRegenerate with `python -m tools.bench_sitl --write "
                              f"{args.write}`.\n\n{text}\n")
    if args.readme:
        write_dated_section(args.readme, "tools.bench_sitl", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
