"""Benchmarks (medians; never asserted in tests): ground report with and without plots, and with plots and every
export (`--export all`), on a ~100k-sample run, a pose-corrected one and one whose servo is re-timed, batch ray
casting, SITL flight.
Usage: python -m tools.bench_ground [--write docs/benchmarks.md] [--readme README.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from firmware_py.core.rundir import SAMPLES_FILE
from firmware_py.core.samplelog import read_samplelog
from firmware_py.core.storage import Storage
from ground.exports.formats import ExportFormat
from ground.exports.write import write_exports
from ground.gp_slopes import forget_fits
from ground.report import ReportOptions, header_geometry, make_report, survey_from_samples
from ground.self_calibration import forget_sims
from ground.smoothing import NodeSlopes
from sitl.faults.injector import FaultSpec
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from sitl.world.raycast import World
from sitl.world.stockpile import paper_pile
from tools.doc_sections import write_dated_section


def median_time(fn, repeat: int, before=None) -> tuple[float, list[float]]:
    """The median of `repeat` timed calls of fn; `before` (not timed) runs before each."""
    times = []
    for _ in range(repeat):
        if before is not None:
            before()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def bench_rays(n: int, repeat: int) -> float:
    world = World(Storage(), paper_pile("1"))
    rng = np.random.default_rng(0)
    o = np.column_stack([rng.uniform(3, 57, n), rng.uniform(2, 38, n), np.full(n, 12.0)])
    g, az = rng.uniform(-np.pi / 2, np.pi / 2, n), rng.uniform(-np.pi, np.pi, n)
    d = np.column_stack([np.sin(g) * np.cos(az), np.sin(g) * np.sin(az), -np.cos(g)])
    world.cast(o[:1000], d[:1000])  # warm-up
    med, _ = median_time(lambda: world.cast(o, d), repeat)
    return n / med


def forget_remembered() -> None:
    """What a process remembers of the flights it reported (`forget_fits`, `forget_sims`), forgotten."""
    forget_fits()
    forget_sims()


def _survey(run: Path):
    """The survey of a run directory as the report computes it (default options), and its log header."""
    log = read_samplelog(run / SAMPLES_FILE)
    storage, frame, lever = header_geometry(log, run)
    return survey_from_samples(log.samples, log.header, storage, frame, lever, ReportOptions()), log.header


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--readme", type=Path,
                    help="also write the table into this page's marked section bench-ground (README.md)")
    ap.add_argument("--write", type=Path, help="also write the table to this Markdown file")
    args = ap.parse_args(argv)
    rows = []
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        cfg = FlyConfig(mission=Mission(p_traj=0.05), stockpile="1")
        fly_med, _ = median_time(lambda: fly(cfg, run, force=True), args.repeat)
        n = fly(cfg, run, force=True).n_samples
        rows.append((f"SITL fly, ideal plant, P_traj 5 % ({n:,} samples, {n / 500:.0f} s flight)", fly_med, ""))
        make_report(run, Path(tmp) / "warm", ReportOptions(plots=False), force=True)  # imports and caches warm

        def report_time(source: Path, name: str, opts: ReportOptions) -> float:
            """A fresh report's median: the remembered covariance fits and servo re-simulations forgotten before
            each run, as a new flight has none."""
            return median_time(lambda: make_report(source, Path(tmp) / name, opts, force=True), args.repeat,
                               before=forget_remembered)[0]

        no_plots = report_time(run, "r1", ReportOptions(plots=False))
        rows.append((f"ground report, no plots ({n:,} samples; the default: the pose correction runs, and is not "
                     "applied)", no_plots, "target <= 1 s"))
        without = ReportOptions(plots=False, pose_correction=False)
        off = report_time(run, "r0", without)
        rows.append((f"ground report, no plots, --no-pose-correction ({n:,} samples)", off, "target <= 1 s"))
        gp = ReportOptions(plots=False, surface_slopes=NodeSlopes.GP)
        gp_med = report_time(run, "r6", gp)
        rows.append((f"ground report, no plots, --surface-slopes gp ({n:,} samples)", gp_med, ""))
        scipy_slopes = ReportOptions(plots=False, surface_slopes=NodeSlopes.CURVATURE)
        sc_med = report_time(run, "r8", scipy_slopes)
        rows.append((f"ground report, no plots, --surface-slopes curvature ({n:,} samples)", sc_med, ""))
        plots = report_time(run, "r2", ReportOptions())
        rows.append((f"ground report, with plots ({n:,} samples; the default)", plots, "target <= 3 s"))
        plots_off = ReportOptions(pose_correction=False)
        p_off = report_time(run, "r5", plots_off)
        rows.append((f"ground report, with plots, --no-pose-correction ({n:,} samples)", p_off, "target <= 3 s"))
        every = ReportOptions(exports=tuple(ExportFormat))
        exports = report_time(run, "r4", every)
        rows.append((f"ground report, with plots and every export, georeferenced ({n:,} samples)", exports, ""))
        survey, header = _survey(run)
        alone, _ = median_time(lambda: write_exports(survey, header, tuple(ExportFormat), Path(tmp) / "x"), args.repeat)
        rows.append((f"of which the exports alone (`write_exports`, every format, {len(survey.cloud.points_w):,} "
                     f"points, {survey.grid.shape[0] * survey.grid.shape[1]:,} cells)", alone, ""))
        with_pose = ReportOptions(plots=False)
        vio_run = Path(tmp) / "vio"
        vio = fly(FlyConfig(mission=Mission(p_traj=0.05), stockpile="1", pose_error="vio"), vio_run, force=True)
        corrected = report_time(vio_run, "r7", with_pose)
        rows.append((f"ground report, no plots, `--pose-error vio` flight, pose corrected ({vio.n_samples:,} samples)",
                     corrected, ""))
        slow_run = Path(tmp) / "slow"
        slow = fly(FlyConfig(mission=Mission(p_traj=0.05), stockpile="1", payload="firmware",
                             faults=FaultSpec(servo_slow_factor=0.6)), slow_run, force=True)
        retimed = report_time(slow_run, "r9", ReportOptions(plots=False))
        rows.append((f"ground report, no plots, a servo at 60 % of its speed (firmware flight, {slow.n_samples:,} "
                     "samples; the servo's timing searched and re-simulated)", retimed, ""))
        cli = [sys.executable, "-m", "ground.cli", "report", str(run), "--out", str(Path(tmp) / "r3"), "--quiet",
               "--force"]
        cold, _ = median_time(lambda: subprocess.run(cli, check=True), 3)
        rows.append(("`pilescan-ground report` as a fresh process, with plots (incl. imports)", cold, ""))
    rate = bench_rays(1_000_000, args.repeat)
    load_after, cores = os.getloadavg()[0], os.cpu_count() or 1
    busy = (" (above the core count: other work shared the machine and every row is slower by about that ratio)"
            if max(load_before, load_after) > cores else "")
    lines = [f"Machine: {platform.machine()}, {cores} cores, Python {platform.python_version()}; "
             f"medians of {args.repeat} runs (3 for the fresh process); load average (1 min) {load_before:.1f} "
             f"before, {load_after:.1f} after{busy}.", "",
             "| benchmark | median | note |", "|---|---|---|"]
    lines += [f"| {name} | {t:.3f} s | {note} |" for name, t, note in rows]
    lines.append(f"| batch ray casting, 1 M rays (Embree) | {rate / 1e6:.2f} M rays/s | target >= 1 M rays/s |")
    text = "\n".join(lines)
    print(text)
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text("# Benchmarks\n\nRegenerate with `python -m tools.bench_ground --write "
                              f"{args.write}`.\n\n{text}\n")
    if args.readme:
        write_dated_section(args.readme, "tools.bench_ground", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
