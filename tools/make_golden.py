"""Regenerate the golden files: a small sample log of the current format and the report figures it gives.

    python -m tools.make_golden            # rewrite tests/golden/
    python -m tools.make_golden --check    # regenerate into a temporary directory, compare, exit 1 on a diff

The log is a cut-down real run: pile 1 at P_traj 20 % flown by `sitl.runners.fly.fly` with the payload
firmware in the loop on the JSBSim plant (seed 0), keeping every `KEEP_EVERY`-th sample so the file stays
a few hundred KB while still covering the whole building. Its header is the run's, with `created_utc`
and the configuration's log path (a temporary directory) fixed so that regenerating writes the same
bytes. `truth.json` holds the true volume (for Ve), and `report_figures.json` the `report.json` values
`tests/test_golden.py` compares against.

A change of the log format, the SITL or the report shows up as a diff of these files: review it, then
commit the regenerated files with the change that caused it.
"""

from __future__ import annotations

import argparse
import filecmp
import json
import math
import sys
import tempfile
from pathlib import Path

from firmware_py.core.rundir import SAMPLES_FILE, TRUTH_FILE
from firmware_py.core.samplelog import SampleLogWriter, read_samplelog, rewritable_header
from firmware_py.core.storage import Storage
from ground.report import ReportOptions, make_report
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly

GOLDEN_DIR = Path(__file__).resolve().parent.parent / "tests" / "golden"
FIGURES_FILE = "report_figures.json"
KEEP_EVERY = 20
CREATED_UTC = "2026-01-01T00:00:00+00:00"
FIGURE_KEYS = ("volume_m3", "true_volume_m3", "volume_error_pct", "coverage_ratio_pct", "n_samples",
               "n_points_used", "n_points_removed_walls", "n_samples_excluded", "n_samples_servo_suspect",
               "n_samples_spikes", "n_cells_clipped", "cell_size_m", "uncovered_area_m2", "sweep_disagreement_m",
               "servo_timing", "mission_id", "log", "warnings")
"""The report.json values the golden test compares (not the provenance: software version, paths, timings)."""


def golden_config() -> FlyConfig:
    return FlyConfig(mission=Mission(storage=Storage(), p_traj=0.20), stockpile="1", plant="jsbsim",
                     payload="firmware", seed=0)


def write_golden(out: Path) -> dict:
    """Fly, cut the log down, write it with truth.json and the report figures into out; returns the figures."""
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="pilescan-golden-") as tmp:
        run = fly(golden_config(), tmp)
        log = read_samplelog(Path(tmp) / SAMPLES_FILE)
        truth = json.loads((Path(tmp) / TRUTH_FILE).read_text())
    header = rewritable_header(log.header)
    header["created_utc"] = CREATED_UTC
    payload_cfg = (header.get("config") or {}).get("payload")
    if isinstance(payload_cfg, dict) and "log" in payload_cfg:  # the temporary run's path: not the golden's
        payload_cfg["log"] = SAMPLES_FILE
    samples = log.samples[::KEEP_EVERY]
    with SampleLogWriter(out / SAMPLES_FILE, header, records_per_block=500, fsync=False, overwrite=True) as w:
        w.append(samples)
    golden_truth = {"true_volume_m3": run.true_volume_m3, "stockpile": truth["stockpile"],
                    "mission_id": truth["mission_id"], "seed": truth["seed"], "plant": truth["plant"],
                    "payload": truth["payload"], "flight_time_s": truth["flight_time_s"],
                    "n_samples_flown": len(log.samples), "kept_every": KEEP_EVERY}
    (out / TRUTH_FILE).write_text(json.dumps(golden_truth, indent=2) + "\n")
    figures = report_figures(out)
    (out / FIGURES_FILE).write_text(json.dumps(figures, indent=2) + "\n")
    return figures


def report_figures(run_dir: Path) -> dict:
    """The golden figures: the report's values on run_dir (no plots), as report.json holds them."""
    with tempfile.TemporaryDirectory(prefix="pilescan-golden-report-") as tmp:
        report = make_report(run_dir, tmp, ReportOptions(plots=False))
        written = json.loads((Path(tmp) / "report.json").read_text())
    assert written["volume_m3"] == report["volume_m3"]
    return {k: written[k] for k in FIGURE_KEYS}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="regenerate elsewhere and compare with tests/golden/")
    args = parser.parse_args(argv)
    if not args.check:
        figures = write_golden(GOLDEN_DIR)
        print(f"wrote {GOLDEN_DIR}: volume {figures['volume_m3']:.1f} m^3, {figures['n_samples']} samples")
        return 0
    with tempfile.TemporaryDirectory(prefix="pilescan-golden-check-") as tmp:
        write_golden(Path(tmp))
        _, differ, missing = filecmp.cmpfiles(GOLDEN_DIR, tmp, [SAMPLES_FILE], shallow=False)
        for name in (TRUTH_FILE, FIGURES_FILE):
            try:
                kept, made = (json.loads((d / name).read_text()) for d in (GOLDEN_DIR, Path(tmp)))
            except (OSError, ValueError):
                missing.append(name)
                continue
            for diff in figure_differences(name, made, kept, REL_TOL):
                print(f"  {diff}")
                if name not in differ:
                    differ.append(name)
    for name in differ + missing:
        print(f"differs from the regenerated one: tests/golden/{name}")
    return 1 if differ or missing else 0


REL_TOL = 1e-9
"""How far a regenerated figure may differ from the golden one: the last digits of a float sum move between machines
(the pile mesh's volume read 7206.878773739369 on one and ...367 on another, the same flight byte for byte), which
is no change of the log format, the SITL or the report."""


def figure_differences(key: str, got: object, want: object, rel_tol: float) -> list[str]:
    """Where a figure differs from the golden one (empty: none): exact for counts, strings, lists and structure
    (dict keys in order, and the type: True is not 1), floats within rel_tol. `tests/test_golden.py` holds the
    report's figures to the golden ones with the same rules."""
    if isinstance(want, float) and isinstance(got, int | float):
        ok = math.isclose(got, want, rel_tol=rel_tol, abs_tol=1e-9)
        return [] if ok else [f"{key}: {got!r} != golden {want!r}"]
    if isinstance(want, dict) and isinstance(got, dict):
        if list(got) != list(want):
            return [f"{key}: keys {list(got)} != golden {list(want)}"]
        return [d for k in want for d in figure_differences(f"{key}.{k}", got[k], want[k], rel_tol)]
    return [] if got == want and type(got) is type(want) else [f"{key}: {got!r} != golden {want!r}"]


if __name__ == "__main__":
    sys.exit(main())
