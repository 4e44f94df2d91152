"""Does the pose correction leave alone the flights that do not need it? (issue 15: whether it can be on by
default)

The pose-error campaign's error-free flights are the paper's two piles without sensor noise. A correction that is
on by default meets every pile, building and sensor: this runs it on a slice of the evaluation set
(`tools.evalset`: every pile instance, three P_traj, one servo phase, the three sensor-noise models; the poses are
the truth) and counts where it applied itself and what that did to Ve, with the survey's time with and without.

    python -m tools.pose_default_check --jobs 2 --write docs/pose_error.md

`--paper-phases N` adds the noise table's flights (`tools.noise_table`: the paper's building and piles 1 and 2 at
P_traj 5 / 20 / 30 %, the three sensor-noise models, N servo phases each), which are other flights than the
evaluation set's: five of them had their floor moved by the floor's route when no evaluation-set run had.

The runs are kept under --root (runs/pose-default) and reused; each survey pair is cached by the run and a digest
of the ground station's source, so a change to the correction computes them again.
"""

from __future__ import annotations

import functools
import hashlib
import statistics
import sys
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

from firmware_py.core.cli import ArgumentParser
from firmware_py.core.sensor_noise import SensorNoiseModel
from tools.doc_sections import write_section
from tools.evalset import (
    DEFAULT_FLIGHT_CACHE,
    N_SERVO_POSITIONS,
    NOISES,
    cases_for,
    instance_of,
    instances,
    load_run,
    phases_of,
    run_case,
    run_id,
    survey_metrics,
    survey_of,
)
from tools.sweep import Case, run_sweep

SECTION = "pose-correction-default-check"
DEFAULT_ROOT = Path("runs/pose-default")
P_TRAJ_PCT = (5, 20, 35)
CHECK_VERSION = "3"
"""Part of every check's cache key, with the ground station's own source (`ground_source_key`): bump it when what
a check computes changes. 2: the pointing and position noise the header states are in the correction's noise
floor. 3: the position's also in its noise level (the significance and the "too small to matter" test)."""


def ground_source_key() -> str:
    """A digest of the ground station's source: a check cached before the correction (or anything it sits on)
    changed is computed again, not read back as if it were today's."""
    import ground

    digest = hashlib.sha256()
    for path in sorted(Path(ground.__file__).parent.rglob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def surveyed_without_and_with(survey: Callable, true_m3: float) -> dict:
    """What the correction did to one flight: survey(opts) called without and with it (its ReportOptions), timed; the
    row's fields that `table` and `applied_rows` read, but for the flight's own (run_id, family, ...)."""
    from ground.report import ReportOptions

    out = {}
    for on in (False, True):
        t0 = time.perf_counter()
        sv = survey(ReportOptions(plots=False, pose_correction=on))
        out[on] = (sv, time.perf_counter() - t0)
    (off, t_off), (on, t_on) = out[False], out[True]
    m_off, m_on = survey_metrics(off, true_m3), survey_metrics(on, true_m3)
    pose = on.pose
    return {"applied": bool(pose is not None and pose.applied),
            "reason": "" if pose is None else (pose.reason or "; ".join(pose.notes)),
            "volume_off_m3": m_off["volume_m3"], "volume_on_m3": m_on["volume_m3"],
            "ve_off_pct": m_off["ve_pct"], "ve_on_pct": m_on["ve_pct"],
            "true_volume_m3": true_m3, "survey_off_s": t_off, "survey_on_s": t_on}


def check_run(case: Case, root: Path) -> list[dict]:
    """One stored run surveyed without and with the correction: did it apply, and what did it do to Ve."""
    run = load_run(root / "runs" / case.get("run"))
    tr = run.truth
    return [{"run_id": run.run_id, "family": tr["family"], "building": tr["building"], "p_traj_pct": tr["p_traj_pct"],
             "noise": tr["noise"],
             **surveyed_without_and_with(functools.partial(survey_of, run), run.true_volume_m3)}]


PAPER_PILES = ("1", "2")
PAPER_P_TRAJ_PCT = (5, 20, 30)
PAPER_NOISES = tuple(SensorNoiseModel)
"""The noise table's error-free flights the check adds with --paper-phases (`tools.noise_table`)."""
NOISE_TABLE = "noise table"
"""The rows' set for those flights (the evaluation set's rows carry none)."""


def paper_checks(phases: int, source: str) -> list[Case]:
    """One check per noise-table flight: each pile, P_traj, sensor-noise model and the first `phases` servo phases."""
    return [Case.make("posecheck-paper", pile=pile, p_traj_pct=p, noise=m.value, phase=k, version=CHECK_VERSION,
                      ground=source)
            for pile in PAPER_PILES for p in PAPER_P_TRAJ_PCT for m in PAPER_NOISES for k in range(phases)]


def check_paper(case: Case, flight_cache: Path) -> list[dict]:
    """One noise-table flight (the batch sampler's, as the table draws its noise) surveyed without and with the
    correction, as `check_run` surveys a stored run."""
    import numpy as np

    from ground.report import survey_from_samples
    from sitl.runners.fly import log_header
    from tools.noise_table import Case as NoiseCase
    from tools.noise_table import case_samples

    pile, p, phase = case.get("pile"), case.get("p_traj_pct"), case.get("phase")
    model = SensorNoiseModel(case.get("noise"))
    [(_, cfg, samples, stockpile)] = list(case_samples(NoiseCase(pile, p, model), [phase], flight_cache))
    survey = functools.partial(survey_from_samples, samples, log_header(cfg, cfg.servo_waveform()),
                               cfg.mission.storage, cfg.frame, np.array(cfg.lever_arm_body_m))
    return [{"run_id": f"paper-pile{pile}-p{p}-ph{phase}-{model.value}", "family": f"paper pile {pile}",
             "building": "paper", "set": NOISE_TABLE, "p_traj_pct": p, "noise": model.value,
             **surveyed_without_and_with(survey, stockpile.volume_m3)}]


def delta_pp(row: dict) -> float:
    """The correction's change of Ve, in percentage points of the true volume (the empty building: of 1 m^3)."""
    return 100.0 * (row["volume_on_m3"] - row["volume_off_m3"]) / max(row["true_volume_m3"], 1.0)


def table(rows: list[dict]) -> str:
    """Per sensor-noise model and P_traj: runs, how many the correction applied itself to, the largest change."""
    groups: dict[tuple[str, int], list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["noise"], r["p_traj_pct"])].append(r)
    out = ["| sensor noise | P_traj | runs | applied | largest \\|change of Ve\\| [pp] | survey without / with [s] |",
           "|---|---|---|---|---|---|"]
    for noise in [n.value for n in NOISES]:
        for p in sorted({k[1] for k in groups if k[0] == noise}):
            g = groups[(noise, p)]
            worst = max(abs(delta_pp(r)) for r in g)
            out.append(f"| {noise} | {p} % | {len(g)} | {sum(r['applied'] for r in g)} | {worst:.3f} | "
                       f"{statistics.median(r['survey_off_s'] for r in g):.2f} / "
                       f"{statistics.median(r['survey_on_s'] for r in g):.2f} |")
    return "\n".join(out)


def applied_rows(rows: list[dict]) -> str:
    """The runs the correction applied itself to, each with what it did."""
    hit = [r for r in rows if r["applied"]]
    if not hit:
        return "It applied itself to none of them."
    out = ["It applied itself to these:", "", "| run | Ve without [%] | Ve with [%] | what it said |",
           "|---|---|---|---|"]
    for r in sorted(hit, key=lambda r: -abs(delta_pp(r))):
        out.append(f"| {r['run_id']} | {r['ve_off_pct']:.2f} | {r['ve_on_pct']:.2f} | {r['reason']} |")
    return "\n".join(out)


def document(rows: list[dict], cmd: str, wall_s: float, phases: int, paper_phases: int = 0) -> str:
    evaluation = [r for r in rows if r.get("set") != NOISE_TABLE]
    paper = [r for r in rows if r.get("set") == NOISE_TABLE]
    n_fam = len({r["family"] for r in evaluation})
    n_b = len({r["building"] for r in evaluation})
    lines = [
        f"{len(evaluation)} runs of the evaluation set (every pile instance: {n_fam} families in {n_b} buildings; "
        f"{phases} servo phase{'s' if phases > 1 else ''} a flight; the three sensor-noise models), flown on the "
        "true pose, each surveyed without and "
        f"with the correction. Regenerated by `{cmd}` ({wall_s / 60:.1f} min of wall time).", "",
        table(evaluation), "", applied_rows(evaluation)]
    if paper:
        flights = f"{len(paper)} flight{'s' if len(paper) != 1 else ''}"
        lines += ["", f"And {flights} of the noise table (the paper's building, piles 1 and 2 at P_traj "
                      f"{' / '.join(map(str, PAPER_P_TRAJ_PCT))} %, {paper_phases} servo phases, the three "
                      "sensor-noise models; `tools.noise_table`), flown on the true pose:", "", table(paper), "",
                  applied_rows(paper)]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help=f"where the runs go (default {DEFAULT_ROOT})")
    ap.add_argument("--flight-cache", type=Path, default=DEFAULT_FLIGHT_CACHE, help="JSBSim flight cache")
    ap.add_argument("--p-traj", type=int, nargs="+", default=list(P_TRAJ_PCT), help="P_traj [%%] (default 5 20 35)")
    ap.add_argument("--phases", type=int, default=1, help="servo phases a flight (default 1)")
    ap.add_argument("--paper-phases", type=int, default=0,
                    help="also the noise table's flights, this many servo phases each (default 0: none)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--write", type=Path, default=None, help=f"page whose {SECTION} section to rewrite")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error("--jobs must be >= 1")
    if not 1 <= args.phases <= N_SERVO_POSITIONS:
        ap.error(f"--phases must be 1-{N_SERVO_POSITIONS}")
    if not 0 <= args.paper_phases <= N_SERVO_POSITIONS:
        ap.error(f"--paper-phases must be 0-{N_SERVO_POSITIONS}")
    t0 = time.perf_counter()
    cases = cases_for(instances(), p_traj_pct=tuple(args.p_traj), phases=args.phases)
    run_sweep(cases, functools.partial(run_case, root=args.root, flight_cache=args.flight_cache), args.root / "cases",
              jobs=args.jobs, progress=not args.no_progress, desc="flights")
    source = ground_source_key()
    checks = [Case.make("posecheck", run=run_id(instance_of(c), c.get("p_traj_pct"), k, n), version=CHECK_VERSION,
                        ground=source)
              for c in cases for k in phases_of(c) for n in NOISES]
    rows = run_sweep(checks, functools.partial(check_run, root=args.root), args.root / "checks", jobs=args.jobs,
                     progress=not args.no_progress, desc="surveys")
    if args.paper_phases:
        rows += run_sweep(paper_checks(args.paper_phases, source),
                          functools.partial(check_paper, flight_cache=args.flight_cache), args.root / "checks",
                          jobs=args.jobs, progress=not args.no_progress, desc="noise-table surveys")
    cmd = "python -m tools.pose_default_check" + (f" --p-traj {' '.join(map(str, args.p_traj))}"
                                                   if tuple(args.p_traj) != P_TRAJ_PCT else "")
    cmd += (f" --phases {args.phases}" if args.phases != 1 else "")
    cmd += (f" --paper-phases {args.paper_phases}" if args.paper_phases else "") + f" --jobs {args.jobs}"
    cmd += f" --write {args.write}" if args.write else ""
    text = document(rows, cmd, time.perf_counter() - t0, args.phases, args.paper_phases)
    print(text)
    if args.write is not None:
        write_section(args.write, SECTION, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
