"""Regenerate every page a change of the ground station's volumes touches, in the order their figures depend on.

A change of the default fill, surface or interval moves the volume of every survey, and with it the figures of a
dozen pages (the interval's calibration, Table 2, the noise tables, the unseen campaign, the pose campaigns, the
benchmark, README's generated sections). Each page names the command that made it; this runs them one after the
other, a few hours of work on a 2-core machine, and can be stopped and resumed:

    python -m tools.regenerate --list            # the steps, the pages each writes, and whether it is done
    python -m tools.regenerate                   # run the steps not yet done (resumable)
    python -m tools.regenerate --fresh           # forget what was done and run them all
    python -m tools.regenerate --only results noise

The order is the dependencies': the evaluation set's runs first (a fresh checkout has none; its rows and page keep
their own cache key, so this step only flies and samples what is missing); the interval's factors are in every
report, so they come next; the pose campaigns report their kept flights again (their old reports are moved aside by
the `pose-reports-aside` step, since `--reuse` keeps an uncorrected report it finds); the pose interval is fitted on
the campaigns' corrected reports; docs/noise.md, the longest, comes last. A step that fails stops the run
(`--keep-going` goes on): a later step may read what it should have written. Each step's output goes to its own log
in the state folder; the state records what is done, so a session cut short resumes where it stopped. The prose
around the generated sections (README's summaries of the pose campaigns, the design notes) is not a tool's: read it
against the new pages by hand.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from firmware_py.core.cli import ArgumentParser

POSE_RUNS = ("runs/pose", "runs/pose-own", "runs/pose-hidden", "runs/pose-noise-ds", "runs/pose-noise-aa")
"""The folders the pose campaigns keep their flights in (each flight's reports are siblings: NAME--FLAG)."""
POSE_REPORT_GLOBS = ("*--no-pose-correction", "*--pose-correction", "*--true-*")
"""The kept reports the campaigns and the pose oracle reuse when they find them: stale after a change of the fill."""
DEFAULT_STATE = Path("runs/regenerate")


@dataclass(frozen=True)
class Step:
    """One page-writing command. argv: the tool's arguments after `python -m` (None: an action of this module);
    pages: what it rewrites (for --list and for the reader)."""

    name: str
    argv: tuple[str, ...] | None
    pages: tuple[str, ...]
    about: str = ""


def _step(name: str, command: str, pages: str, about: str = "") -> Step:
    return Step(name, tuple(command.split()), tuple(pages.split()), about)


STEPS: tuple[Step, ...] = (
    _step("evalset", "tools.evalset --jobs 2 --no-progress", "",
          "the evaluation set's stored runs, which the interval is fitted on (about 25 min on a fresh checkout, "
          "seconds when runs/evalset holds them)"),
    _step("interval", "tools.calibrate_interval --jobs 2 --write docs/uncertainty.md --write-model --readme README.md "
          "--rows docs/interval-rows.csv", "docs/uncertainty.md ground/uncertainty.py README.md docs/interval-rows.csv",
          "the interval's factors, fitted on the evaluation set (about 20 min)"),
    _step("golden", "tools.make_golden", "tests/golden", "the golden run the tests compare against"),
    _step("demo", "tools.demo --write-readme README.md", "README.md", "the demo's summary in README"),
    _step("results", "tools.reproduce --write docs/results.md --rows docs/results-rows.csv --jobs 2 --quiet",
          "docs/results.md docs/results-rows.csv", "Table 2 and the paper's experiments (about 25 min)"),
    _step("noise-table", "tools.noise_table --write docs/results.md --costs docs/sensor_noise.md --jobs 2 "
          "--spot 1,20,none,0 "
          "--spot 1,20,datasheet,0 --spot 2,20,appendix-a,0 --spot 2,20,datasheet,0 --spot 1,30,datasheet,0 "
          "--spot 2,5,appendix-a,0 --spot 1,5,appendix-a,0", "docs/results.md docs/sensor_noise.md",
          "the sensor-noise table and what it costs"),
    _step("unseen", "tools.unseen_campaign", "docs/unseen.md", "the unseen fills on corner and wall-end piles"),
    _step("echo-check", "tools.echo_check --jobs 2 --write docs/unseen.md", "docs/unseen.md",
          "how often the floor-out-of-reach warning spoke over the evaluation set (about 8 min)"),
    _step("contact-check", "tools.contact_check --jobs 2 --write docs/unseen.md", "docs/unseen.md",
          "the wall contacts against the true ground over the evaluation set, by noise model"),
    _step("cell-sensitivity", "tools.cell_sensitivity --write docs/cell_sensitivity.md", "docs/cell_sensitivity.md",
          "the volume against the grid's cell, per fill (MEASURED_MAX_CELL_M is read off it)"),
    _step("slopes", "tools.slopes_evalset --jobs 2 --rows runs/slopes-evalset.csv --write docs/surface_estimators.md",
          "docs/surface_estimators.md", "the default slopes against the GP's and the GP's at the bridges over the "
          "evaluation set, each noisy run against its noise-free twin"),
    Step("pose-reports-aside", None, (), "the pose campaigns' kept reports moved aside, to be made again"),
    _step("pose", "tools.pose_correction_campaign --seeds 0 1 2 3 4 5 --piles 1 2 --p-traj 5 20 --keep runs/pose "
          "--reuse --write docs/pose_error.md", "docs/pose_error.md"),
    _step("pose-own", "tools.pose_correction_campaign --seeds 0 1 2 3 4 5 --keep runs/pose-own --storage 40x25x10 "
          "--altitude 7 --own-piles cone:1 ridge:2 --p-traj 5 20 --reuse --write docs/pose_error.md "
          "--section pose-correction-own-table", "docs/pose_error.md"),
    _step("pose-hidden", "tools.pose_correction_campaign --seeds 0 1 2 3 4 5 --piles 2 --p-traj 10 25 --storage "
          "24x16x10 --altitude 9 --keep runs/pose-hidden --reuse --write docs/pose_error.md "
          "--section pose-correction-hidden-floor", "docs/pose_error.md"),
    _step("pose-datasheet", "tools.pose_correction_campaign --seeds 0 1 2 --p-traj 20 --keep runs/pose-noise-ds "
          "--sensor-noise datasheet --reuse --write docs/pose_error.md --section pose-correction-noise-datasheet",
          "docs/pose_error.md"),
    _step("pose-appendix-a", "tools.pose_correction_campaign --seeds 0 1 2 --p-traj 20 --keep runs/pose-noise-aa "
          "--sensor-noise appendix-a --reuse --write docs/pose_error.md --section pose-correction-noise-appendix-a",
          "docs/pose_error.md"),
    _step("pose-interval", "tools.calibrate_pose_interval --write docs/uncertainty.md --write-model",
          "docs/uncertainty.md ground/uncertainty.py", "the interval's pose factor, on the campaigns' reports"),
    _step("bench", "tools.bench_ground --write docs/benchmarks.md --readme README.md", "docs/benchmarks.md README.md"),
    _step("pose-oracle", "tools.pose_oracle --runs runs/pose runs/pose-own runs/pose-noise-ds runs/pose-noise-aa "
          "--jobs 2 --write docs/pose_error.md", "docs/pose_error.md"),
    _step("pose-oracle-height", "tools.pose_oracle --runs runs/pose runs/pose-own --jobs 2 --height "
          "--write docs/pose_error.md", "docs/pose_error.md"),
    _step("pose-oracle-horizontal", "tools.pose_oracle --runs runs/pose runs/pose-own runs/pose-noise-ds "
          "runs/pose-noise-aa --jobs 2 --horizontal --write docs/pose_error.md", "docs/pose_error.md"),
    _step("rangefinder-share", "tools.rangefinder_share_check --runs runs/pose runs/pose-own runs/pose-noise-ds "
          "runs/pose-noise-aa --jobs 2 --write docs/pose_error.md", "docs/pose_error.md"),
    _step("pose-default", "tools.pose_default_check --phases 3 --paper-phases 20 --jobs 2 --write docs/pose_error.md",
          "docs/pose_error.md"),
    _step("lever-arm", "tools.lever_arm_check --jobs 2 --write docs/pose_error.md", "docs/pose_error.md"),
    _step("pose-uncorrected", "tools.pose_error_campaign --keep runs/pose-error-table --write docs/pose_error.md",
          "docs/pose_error.md", "what a drift does to the volume with the correction off (nine flights flown again)"),
    _step("pose-mount", "tools.pose_mount_check --seeds 0 1 2 --piles 1 2 --p-traj 20 --keep runs/pose-mount "
          "--write docs/pose_error.md", "docs/pose_error.md"),
    _step("self-calibration", "tools.calibration_campaign --runs runs/cal --jobs 2 --write docs/self_calibration.md",
          "docs/self_calibration.md", "the mounting faults' campaign (about 40 min on a fresh checkout, 15 when "
          "runs/cal holds its flights)"),
    _step("gaps", "tools.gap_campaign --piles 1 2 corner --first rect-30 coverage-95 --phase 0 --gap-coverage 95 "
          "--plant jsbsim", "docs/coverage.md", "two-flight surveys: a first flight, then --fill-gaps from its report "
          "(about 4 min)"),
    _step("noise", "tools.reproduce --experiments baseline,noise --write docs/noise.md --rows runs/noise-rows.csv "
          "--jobs 2 --quiet --readme README.md", "docs/noise.md README.md",
          "Appendix A's noise against the clean flights (about 80 min)"),
)
STEP_NAMES = tuple(s.name for s in STEPS)


def move_pose_reports_aside(root: Path, dest: Path) -> int:
    """Move the pose campaigns' kept reports (POSE_REPORT_GLOBS in POSE_RUNS under root) into dest, so the campaigns
    and the oracle make them again; the flights stay. Returns how many were moved."""
    moved = 0
    for folder in POSE_RUNS:
        d = root / folder
        if not d.is_dir():
            continue
        for pattern in POSE_REPORT_GLOBS:
            for rep in sorted(d.glob(pattern)):
                target = dest / f"{d.name}__{rep.name}"
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(str(rep), str(target))
                moved += 1
    return moved


def _done(state: dict, name: str) -> bool:
    return state.get(name, {}).get("ok") is True


def load_state(path: Path) -> dict:
    if not path.is_file():
        return {}
    try:
        state = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SystemExit(f"regenerate: {path} is not a state this tool wrote ({exc}): remove it or run with --fresh") \
            from None
    if not isinstance(state, dict) or not all(isinstance(v, dict) for v in state.values()):
        raise SystemExit(f"regenerate: {path} is not a state this tool wrote: remove it or run with --fresh")
    return state


def run_steps(steps: Sequence[Step], state_dir: Path, *, keep_going: bool = False, python: str = sys.executable,
              root: Path = Path("."), say: Callable[[str], None] = print) -> int:
    """Run the steps not yet done (by the state in state_dir), each with its log there; 0 when every step is done."""
    state_dir.mkdir(parents=True, exist_ok=True)
    state_path = state_dir / "state.json"
    state = load_state(state_path)
    failed = []
    for step in steps:
        if _done(state, step.name):
            say(f"{step.name}: done before, skipped")
            continue
        log = state_dir / f"{step.name}.log"
        say(f"{step.name}: running ({step.about or ', '.join(step.pages)}); log {log}")
        t0 = time.monotonic()
        if step.argv is None:
            moved = move_pose_reports_aside(root, state_dir / "old-pose-reports" / time.strftime("%Y%m%dT%H%M%S"))
            log.write_text(f"moved {moved} kept pose reports aside\n")
            ok = True
        else:
            with log.open("w") as out:
                done = subprocess.run([python, "-m", *step.argv], cwd=root, stdout=out, stderr=subprocess.STDOUT)
            ok = done.returncode == 0
        took = time.monotonic() - t0
        state[step.name] = {"ok": ok, "seconds": round(took, 1), "finished": time.strftime("%Y-%m-%d %H:%M:%S")}
        state_path.write_text(json.dumps(state, indent=1) + "\n")
        say(f"{step.name}: {'done' if ok else 'FAILED'} in {took / 60:.1f} min")
        if not ok:
            failed.append(step.name)
            if not keep_going:
                break
    if failed:
        say(f"failed: {', '.join(failed)} (logs in {state_dir}); fix and run again to resume")
        return 1
    return 0 if all(_done(state, s.name) for s in steps) else 1


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.regenerate", description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="list the steps, their pages and whether each is done")
    ap.add_argument("--only", nargs="+", choices=STEP_NAMES, metavar="STEP", help="run these steps only")
    ap.add_argument("--from", dest="start", choices=STEP_NAMES, metavar="STEP", help="run from this step on")
    ap.add_argument("--fresh", action="store_true", help="forget that the chosen steps were done before")
    ap.add_argument("--keep-going", action="store_true", help="go on after a step fails")
    ap.add_argument("--state", type=Path, default=DEFAULT_STATE, help=f"the state and logs (default {DEFAULT_STATE})")
    args = ap.parse_args(argv)
    steps = list(STEPS)
    if args.start:
        steps = steps[STEP_NAMES.index(args.start):]
    if args.only:
        steps = [s for s in steps if s.name in args.only]
    state_path = args.state / "state.json"
    if args.fresh and not args.list:  # forget the chosen steps only
        state = {k: v for k, v in load_state(state_path).items() if k not in {s.name for s in steps}}
        args.state.mkdir(parents=True, exist_ok=True)
        state_path.write_text(json.dumps(state, indent=1) + "\n")
    if args.list:
        state = load_state(state_path)
        for s in steps:
            mark = "done" if _done(state, s.name) else "to do"
            what = "python -m " + " ".join(s.argv) if s.argv else s.about
            print(f"{s.name:20s} {mark:6s} {', '.join(s.pages) or '-'}\n    {what}")
        return 0
    return run_steps(steps, args.state)


if __name__ == "__main__":
    raise SystemExit(main())
