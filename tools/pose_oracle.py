"""How close can any pose correction come? The drifting flights of the pose campaigns, their samples re-posed with
the truth truth.json keeps (the true trajectory at 10 Hz, the estimate's error linear between), reported without a
pose correction: the volume of the flight the vehicle actually flew, as if its pose had been known.

Issue 15 compares the corrected volume with the error-free flight's. But the autopilot flies on its estimate, so
a drifting flight flies another path, sees other parts of the pile and leaves other cells to the fill: part of the
difference is the path's, and no correction of the pose can remove it. This tool splits the two:

- `true pose - error-free`: the path's share (what a perfect correction would still leave);
- `corrected - true pose`: the correction's own residual.

    python -m tools.pose_oracle --runs runs/pose [runs/pose-own ...] [--jobs 2] [--write docs/pose_error.md]

With `--height`, the second question: how much of the correction's residual is the height's? Each flight's samples
get the true *height* only (x, y and the heading keep their drift) and are reported *with* the correction, as a
user reports them; the trajectory's error after it and the volume are set beside the same flight corrected from its
logged height (sibling `NAME--true-height`, kept and reused like the other).

With `--horizontal`, the opposite: the height drifting alone. Each flight's samples get the true horizontal position
and heading (the logged height, and its drift, kept: a good horizontal estimate over a barometer that walks), and are
reported with the correction and without it (sibling `NAME--true-horizontal`, its reports in `report` and
`report-uncorrected`), each set beside the flight on its true pose: the walls see no height, so this is what the
height's own route of the correction is judged on.

Each run folder of the campaign (`PROFILE-PILE-PTRAJ-SEED[-NOISE]`, with its `--pose-correction` report beside it)
gets a sibling `NAME--true-pose` (the re-posed run, its report in `NAME--true-pose/report`), kept and reused on
the next call (delete it when the flight is flown again); a kept report is made again when the ground station's code
has changed since (`tools.source_digest`). Flights without a pose error, or that crashed, are
skipped.
"""

from __future__ import annotations

import json
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ArgumentParser
from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleLogWriter, read_samplelog, rewritable_header
from ground.pose_correction import PoseCorrection, apply_pose_correction
from tools.doc_sections import write_section
from tools.pose_correction_campaign import (
    TRAJ_TARGET_M,
    VE_TARGET_PP,
    kept_flight_crash,
    signed_error_pct,
    trajectory_rms_m,
)
from tools.source_digest import made_by_this_code, stamp_made_by_this_code
from tools.workers import worker_pool

SECTION = "pose-oracle-table"
SUFFIX = "--true-pose"
HEIGHT_SECTION = "pose-height-oracle-table"
HEIGHT_SUFFIX = "--true-height"
ALL = (0, 1, 2, 3)
"""The components re-posed by default: x, y, z (W) and the heading (`truth_correction`'s columns)."""
HEIGHT = (2,)
HORIZONTAL_SUFFIX = "--true-horizontal"
HORIZONTAL_SECTION = "pose-horizontal-oracle-table"
HORIZONTAL = (0, 1, 3)
"""x, y and the heading: the height keeps its drift."""


def truth_correction(truth: dict) -> PoseCorrection | None:
    """The correction that puts the logged estimate on the true trajectory (None: the flight has no pose error)."""
    tr = (truth.get("pose_error") or {}).get("trajectory")
    if not tr or truth["pose_error"].get("profile") in (None, "none"):
        return None
    if tr.get("clock", "log") != "log":
        raise ValueError(f"the trajectory is on the {tr['clock']} clock, not the log's")
    t = np.asarray(tr["t_s"], dtype=float)
    d_w = np.asarray(tr["true_w_m"], dtype=float) - np.asarray(tr["estimated_w_m"], dtype=float)
    d_yaw = np.angle(np.exp(1j * (np.asarray(tr["estimated_yaw_rad"], dtype=float)
                                  - np.asarray(tr["true_yaw_rad"], dtype=float))))
    values = np.column_stack([d_w, d_yaw])
    return PoseCorrection(knot_t_s=t, values=values, constrained=np.ones_like(values, dtype=bool), applied=True)


def repose(run: Path, out: Path, components: tuple[int, ...] = ALL) -> bool:
    """Write `out`: `run` with its samples' pose replaced by the truth, in these components (ALL; HEIGHT: the
    height only, the rest as logged). False when there is nothing to replace."""
    truth = json.loads((run / "truth.json").read_text())
    if kept_flight_crash(truth) is not None:
        return False
    corr = truth_correction(truth)
    if corr is None:
        return False
    if tuple(components) != ALL:
        values = np.where(np.isin(np.arange(4), components)[None, :], corr.values, 0.0)
        corr = PoseCorrection(corr.knot_t_s, values, corr.constrained, True)
    log = read_samplelog(run / "samples.pslog")
    if not isinstance(log.header, dict) or not isinstance(log.header.get("storage_frame"), dict):
        raise ValueError(f"{run / 'samples.pslog'}: no storage frame in the log header: not a flight to re-pose")
    frame = StorageFrame.from_dict(log.header["storage_frame"])
    samples = apply_pose_correction(log.samples, corr, frame)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for f in run.iterdir():
        if f.is_file() and f.name != "samples.pslog":
            shutil.copy2(f, out / f.name)
    header = rewritable_header(log.header)
    with SampleLogWriter(out / "samples.pslog", header, fsync=False) as w:
        w.append(samples)
    return True


def reported(run_p: Path, suffix: str, components: tuple[int, ...], report_args: list[str],
             report_dir: str = "report") -> dict | None:
    """The report of `run_p` re-posed in `components`, in its sibling NAME + suffix, folder report_dir (each made,
    or reused when it is there and was made by the code as it is now: `tools.source_digest`); None when there is
    nothing to re-pose or the report failed (said on stderr)."""
    oracle = run_p.parent / f"{run_p.name}{suffix}"
    rep = oracle / report_dir / "report.json"
    if not (rep.is_file() and made_by_this_code(rep.parent)):
        if not (oracle / "samples.pslog").is_file() and not repose(run_p, oracle, components):
            return None
        done = subprocess.run([sys.executable, "-m", "ground.cli", "report", str(oracle), "--out", str(rep.parent),
                               "--no-plots", "--force", "--quiet", *report_args], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:  # left out of the table, and said why
            print(f"pose_oracle: {oracle}: the report failed: {done.stderr.strip()}", file=sys.stderr)
            return None
        stamp_made_by_this_code(rep.parent)
    return json.loads(rep.read_text())


def twins(run_p: Path) -> tuple[dict, dict] | None:
    """The reports of the error-free flight of the same pile, P_traj and seed (uncorrected) and of this flight
    corrected; None when the campaign did not make both."""
    profile = parse_run(run_p.name)["profile"]
    ref = run_p.parent / ("none" + run_p.name[len(profile):] + "--no-pose-correction") / "report.json"
    corrected = run_p.parent / f"{run_p.name}--pose-correction" / "report.json"
    if not ref.is_file() or not corrected.is_file():
        return None
    return json.loads(ref.read_text()), json.loads(corrected.read_text())


def one(run: str) -> dict | None:
    """Re-pose one flight and report it; the row with the three volumes (None: not a drifting flight)."""
    run_p = Path(run)
    oracle = reported(run_p, SUFFIX, ALL, ["--no-pose-correction"])
    pair = twins(run_p)
    if oracle is None or pair is None:
        return None
    ref, corrected = pair
    return {"run": run_p.name, "folder": run_p.parent.name, "profile": parse_run(run_p.name)["profile"],
            "ve_ref": signed_error_pct(ref), "ve_true_pose": signed_error_pct(oracle),
            "ve_corrected": signed_error_pct(corrected)}


def with_true_pose_in(truth: dict, components: tuple[int, ...]) -> dict:
    """truth.json of a flight whose samples carry the true pose in these components (HEIGHT: the height): its
    estimated trajectory is the true one there (so the trajectory's error is measured against what the samples
    carry; the heading, 3, is not part of that error)."""
    tr = dict(truth["pose_error"]["trajectory"])
    est = np.array(tr["estimated_w_m"], dtype=float)
    axes = [c for c in components if c < 3]
    est[:, axes] = np.asarray(tr["true_w_m"], dtype=float)[:, axes]
    tr["estimated_w_m"] = est.tolist()
    return {**truth, "pose_error": {**truth["pose_error"], "trajectory": tr}}


def one_height(run: str) -> dict | None:
    """Give one flight the true height only, report it with the correction; the row (None: not a drifting flight)."""
    run_p = Path(run)
    oracle = reported(run_p, HEIGHT_SUFFIX, HEIGHT, [])
    pair = twins(run_p)
    if oracle is None or pair is None:
        return None
    ref, corrected = pair
    truth = json.loads((run_p / "truth.json").read_text())

    def after(t: dict, r: dict) -> float:
        return trajectory_rms_m(t, r.get("pose_correction"), r.get("rangefinder_height"))[1]
    return {"run": run_p.name, "folder": run_p.parent.name, "profile": parse_run(run_p.name)["profile"],
            "ve_ref": signed_error_pct(ref), "ve_corrected": signed_error_pct(corrected),
            "ve_true_height": signed_error_pct(oracle), "traj_corrected_m": after(truth, corrected),
            "traj_true_height_m": after(with_true_pose_in(truth, HEIGHT), oracle)}


def one_horizontal(run: str) -> dict | None:
    """Give one flight the true horizontal position and heading, report it with and without the correction; the row
    with the flight on its true pose beside it (None: not a drifting flight)."""
    run_p = Path(run)
    true_pose = reported(run_p, SUFFIX, ALL, ["--no-pose-correction"])
    corrected = reported(run_p, HORIZONTAL_SUFFIX, HORIZONTAL, [])
    logged = reported(run_p, HORIZONTAL_SUFFIX, HORIZONTAL, ["--no-pose-correction"], "report-uncorrected")
    if true_pose is None or corrected is None or logged is None:
        return None
    truth = with_true_pose_in(json.loads((run_p / "truth.json").read_text()), HORIZONTAL)
    before, after = trajectory_rms_m(truth, corrected.get("pose_correction"), corrected.get("rangefinder_height"))
    return {"run": run_p.name, "folder": run_p.parent.name, "profile": parse_run(run_p.name)["profile"],
            "ve_true_pose": signed_error_pct(true_pose), "ve_logged": signed_error_pct(logged),
            "ve_corrected": signed_error_pct(corrected),
            "applied": bool((corrected.get("pose_correction") or {}).get("applied")),
            "traj_before_m": before, "traj_after_m": after}


def flights(folders: list[Path]) -> list[Path]:
    """The campaign's drifting flights in these folders (not their reports, not the error-free flights)."""
    out = []
    for folder in folders:
        for d in sorted(folder.iterdir()):
            if (d.is_dir() and "--" not in d.name and not d.name.startswith("none-") and (d / "truth.json").is_file()
                    and (d.parent / f"{d.name}--pose-correction").is_dir()):
                out.append(d)
    return out


NOISE_SUFFIXES = ("-appendix-a", "-datasheet")


def parse_run(name: str) -> dict:
    """The campaign's run name PROFILE-PILE-PTRAJ-SEED[-NOISE] (PILE may hold dashes: `cone-1`) as its parts."""
    noise = next((n for n in NOISE_SUFFIXES if name.endswith(n)), "")
    parts = name.removesuffix(noise).split("-")
    if len(parts) < 4 or not parts[-1].isdigit() or not parts[-2].isdigit():
        raise ValueError(f"{name!r} is not a pose campaign's run name (PROFILE-PILE-PTRAJ-SEED[-NOISE])")
    return {"profile": parts[0], "pile": "-".join(parts[1:-2]), "p_traj": int(parts[-2]), "seed": int(parts[-1]),
            "noise": noise.lstrip("-") or "none"}


def by_pile(rows: list[dict]) -> dict[tuple[str, str, int], list[dict]]:
    """The rows per (campaign folder, pile, P_traj), both profiles together, in the rows' order: each table's lines."""
    groups: dict[tuple[str, str, int], list[dict]] = {}
    for r in rows:
        name = parse_run(r["run"])
        groups.setdefault((r["folder"], name["pile"], name["p_traj"]), []).append(r)
    return groups


def table(rows: list[dict]) -> str:
    """Per campaign folder, pile and P_traj (both profiles together): the path's share, the correction's residual
    and the two together, in percentage points of the true volume, and how many flights each keeps within the
    issue's 0.3 pp."""
    lines = ["| folder | pile | P_traj | flights | path's share: \\|true pose - error-free\\| (pp), mean / max | "
             "within "
             f"{VE_TARGET_PP} pp | correction's residual: \\|corrected - true pose\\| (pp), mean / max | within "
             f"{VE_TARGET_PP} pp | \\|corrected - error-free\\| (pp), mean | within {VE_TARGET_PP} pp |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for (folder, pile, p_traj), rs in by_pile(rows).items():
        path = [abs(r["ve_true_pose"] - r["ve_ref"]) for r in rs]
        resid = [abs(r["ve_corrected"] - r["ve_true_pose"]) for r in rs]
        total = [abs(r["ve_corrected"] - r["ve_ref"]) for r in rs]
        lines.append(f"| {folder} | {pile} | {p_traj} % | {len(rs)} | {statistics.fmean(path):.2f} / "
                     f"{max(path):.2f} | {sum(v <= VE_TARGET_PP for v in path)}/{len(rs)} | "
                     f"{statistics.fmean(resid):.2f} / {max(resid):.2f} | "
                     f"{sum(v <= VE_TARGET_PP for v in resid)}/{len(rs)} | {statistics.fmean(total):.2f} | "
                     f"{sum(v <= VE_TARGET_PP for v in total)}/{len(rs)} |")
    return "\n".join(lines)


def height_table(rows: list[dict]) -> str:
    """Per campaign folder, pile and P_traj: the corrected flights from their logged height and from the true one
    (x, y and heading drifting either way): the trajectory's error after the correction and the volume against
    the error-free flight's, with the issue's two targets counted."""
    lines = [f"| folder | pile | P_traj | flights | trajectory after (m), logged / true height | <= "
             f"{TRAJ_TARGET_M * 100:.0f} cm, logged / true height | \\|Ve - error-free\\| (pp), logged / true "
             f"height | within {VE_TARGET_PP} pp, logged / true height |",
             "|---|---|---|---|---|---|---|---|"]
    for (folder, pile, p_traj), rs in by_pile(rows).items():
        tl, tt = ([r[k] for r in rs] for k in ("traj_corrected_m", "traj_true_height_m"))
        vl, vt = ([abs(r[k] - r["ve_ref"]) for r in rs] for k in ("ve_corrected", "ve_true_height"))
        lines.append(f"| {folder} | {pile} | {p_traj} % | {len(rs)} | {statistics.fmean(tl):.3f} / "
                     f"{statistics.fmean(tt):.3f} | {sum(v <= TRAJ_TARGET_M for v in tl)} / "
                     f"{sum(v <= TRAJ_TARGET_M for v in tt)} | {statistics.fmean(vl):.2f} / "
                     f"{statistics.fmean(vt):.2f} | "
                     f"{sum(v <= VE_TARGET_PP for v in vl)} / {sum(v <= VE_TARGET_PP for v in vt)} |")
    return "\n".join(lines)


def horizontal_table(rows: list[dict]) -> str:
    """Per campaign folder, pile and P_traj: the flights whose height alone drifts, as logged and corrected, against
    the same flight on its true pose (the same path flown): how many the correction applied itself to, the volume's
    distance from the true pose's with the issue's target counted, and the trajectory's error (its height's)."""
    lines = [rf"| folder | pile | P_traj | flights | corrected | \|Ve - true pose\| (pp), as logged / corrected, "
             f"mean | within {VE_TARGET_PP} pp, as logged / corrected | trajectory RMS (m), as logged / corrected | "
             f"<= {TRAJ_TARGET_M * 100:.0f} cm, as logged / corrected |",
             "|---|---|---|---|---|---|---|---|---|"]
    for (folder, pile, p_traj), rs in by_pile(rows).items():
        vl, vc = ([abs(r[k] - r["ve_true_pose"]) for r in rs] for k in ("ve_logged", "ve_corrected"))
        tb, ta = ([r[k] for r in rs] for k in ("traj_before_m", "traj_after_m"))
        lines.append(f"| {folder} | {pile} | {p_traj} % | {len(rs)} | {sum(r['applied'] for r in rs)}/{len(rs)} | "
                     f"{statistics.fmean(vl):.2f} / {statistics.fmean(vc):.2f} | "
                     f"{sum(v <= VE_TARGET_PP for v in vl)} / {sum(v <= VE_TARGET_PP for v in vc)} | "
                     f"{statistics.fmean(tb):.3f} / {statistics.fmean(ta):.3f} | "
                     f"{sum(v <= TRAJ_TARGET_M for v in tb)} / {sum(v <= TRAJ_TARGET_M for v in ta)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.pose_oracle", description=__doc__)
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="the pose campaigns' --keep folders")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--rows", type=Path, default=None, help="write the rows here (JSON lines)")
    ap.add_argument("--write", type=Path, default=None,
                    help=f"page whose {SECTION} section (with --height: {HEIGHT_SECTION}; --horizontal: "
                         f"{HORIZONTAL_SECTION}) to rewrite")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--height", action="store_true",
                      help="re-pose the height only and report with the correction (module docstring)")
    mode.add_argument("--horizontal", action="store_true",
                      help="re-pose x, y and the heading only (the height drifting alone) and report with and "
                           "without the correction (module docstring)")
    args = ap.parse_args(argv)
    missing = [str(f) for f in args.runs if not f.is_dir()]
    if missing:
        ap.error(f"no such folder: {', '.join(missing)}")
    todo = [str(f) for f in flights(args.runs)]
    rows = []
    with worker_pool(args.jobs) as pool:
        job = one_height if args.height else one_horizontal if args.horizontal else one
        for i, row in enumerate(pool.map(job, todo), 1):
            if row is not None:
                rows.append(row)
            if sys.stderr.isatty():
                print(f"\r{i}/{len(todo)} flights", end="", file=sys.stderr, flush=True)
            elif i % 10 == 0 or i == len(todo):
                print(f"{i}/{len(todo)} flights", file=sys.stderr, flush=True)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    if args.rows:
        args.rows.write_text("".join(json.dumps(r) + "\n" for r in rows))
    command = "`python -m tools.pose_oracle " + " ".join(sys.argv[1:] if argv is None else argv) + "`"
    if args.height:
        section, table_text = HEIGHT_SECTION, (
            "Each drifting flight corrected (`pilescan-ground report`, the correction on) from its logged height "
            "and from the true height (its samples' height re-posed from truth.json; x, y and the heading keep their "
            "drift): the trajectory's 3-D RMS error after the correction, and |Ve - Ve of the error-free flight|. "
            f"Regenerated by {command}.\n\n" + height_table(rows))
    elif args.horizontal:
        section, table_text = HORIZONTAL_SECTION, (
            "Each drifting flight with its true horizontal position and heading (re-posed from truth.json) and its "
            "logged height, so the height alone drifts (`vio`: the barometer's walk; `flow`: that and the downward "
            "rangefinder's share), reported with `--no-pose-correction` (as logged) and as a user reports it "
            "(corrected), against the same flight on its true pose (the same path flown); trajectory RMS: 3-D "
            f"position against the truth. Regenerated by {command}.\n\n" + horizontal_table(rows))
    else:
        section, table_text = SECTION, (
            "Signed Ve (%) of three reports of each drifting flight: the error-free flight of the same pile, P_traj "
            "and seed; the drifting flight re-posed with the true trajectory (no correction); the drifting flight "
            f"corrected. Regenerated by {command}.\n\n" + table(rows))
    if args.write is not None:
        write_section(args.write, section, table_text)
    print(table_text)
    return 0 if rows or not todo else 1

if __name__ == "__main__":
    raise SystemExit(main())
