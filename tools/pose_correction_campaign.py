"""What the ground station's pose correction (`--pose-correction`, ground/pose_correction.py) does: per profile,
pile and P_traj, one `pilescan-sitl fly` per seed, its report without and with the correction, and the trajectory
error against the truth (truth.json's true and estimated trajectories, the correction interpolated at their
times). Writes the table into docs/pose_error.md.

    python -m tools.pose_correction_campaign --write docs/pose_error.md [--seeds 0 1] [--keep DIR]
        [--piles 1 2] [--p-traj 5 20] [--rows FILE ...] [--reuse]

--rows: JSON-lines files of rows already computed (the first one gets the new rows appended): a campaign can be
resumed, or split over processes (each with its --piles) and tabulated by a last call that reads all files.

--reuse (with --keep): a flight already in the folder is not flown again, only reported again with the correction
(the uncorrected report is kept too when it is there and was made by the code as it is now, `tools.source_digest`):
the same flights before and after a change of the ground code.

Both programs run as a user runs them (their command lines, in subprocesses).

A flight whose true path reached a wall or the roof crashed (`sitl.world.clearance`): `fly` refuses to write it,
and a kept flight flown before that check is found from its truth.json. Its row says so (`hit`) and it is left out
of the means and the targets' counts; the table's "hit a wall" column counts such flights. A flight `fly` refuses
before take-off (an altitude its rangefinder's climb over the pile would take through the roof) is no survey either,
and is counted beside them as refused.
"""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ArgumentParser
from firmware_py.core.sensor_noise import SensorNoiseModel
from firmware_py.core.storage import Storage
from sitl.missions.rectangle import Mission
from sitl.world.clearance import closest_approach, collision, f450_reach_m
from sitl.world.shapes import make_shape
from tools.doc_sections import write_section
from tools.source_digest import made_by_this_code, stamp_made_by_this_code

SECTION = "pose-correction-table"
PROFILES = ("none", "vio", "flow")
PILES = ("1", "2")
P_TRAJ_PCT = (5, 20)
PILE_CLEARANCE_M = 2.0
"""An own pile's top under the flight altitude (as the evaluation set's, tools/evalset.py)."""
VE_TARGET_PP = 0.3
"""Issue 15's target: the corrected Ve within this of the error-free flight's (per seed, counted in the table)."""
TRAJ_TARGET_M = 0.10
"""Issue 15's target: the trajectory's RMS against the truth after the correction."""


def trajectory_rms_m(truth: dict, correction: dict | None, rangefinder: dict | None = None) -> tuple[float, float]:
    """3-D position RMS of the estimate against the truth, before and after the report's corrections: the
    rangefinder's share of the height taken out first (report.json's `rangefinder_height`, its lift over time) and
    the pose correction on top (its knots, linear between, and its sweeps' heights). With a correction applied, both
    over the span it was fitted on (its first knot to its last: the first usable sample to the last). A payload that
    logs from before take-off to after the landing (a networked flight) has the climb and the descent in its log with
    no usable sample, where the correction is only held at its end's value: the `flow` flight's descent from the
    pile's height to the floor, 5 s of 175, took its RMS from 0.08 to 0.18 m (docs/pose_error.md)."""
    tr = (truth.get("pose_error") or {}).get("trajectory")
    if not tr:
        return 0.0, 0.0
    if tr.get("clock", "log") != "log":
        raise ValueError(f"the trajectory is on the {tr['clock']} clock, not the log's: align it first "
                         "(clock_offset_s, on_log_clock)")
    t, true_w, est_w = np.array(tr["t_s"]), np.array(tr["true_w_m"]), np.array(tr["estimated_w_m"])
    if correction and correction.get("applied") and len(correction.get("knot_t_s") or ()) >= 2:
        knots = correction["knot_t_s"]
        span = (t >= knots[0]) & (t <= knots[-1])
        if span.any():
            t, true_w, est_w = t[span], true_w[span], est_w[span]
    before = float(np.sqrt(np.mean(np.sum((est_w - true_w) ** 2, axis=1))))
    placed = est_w.copy()
    if rangefinder and rangefinder.get("applied") and rangefinder.get("lift_t_s"):
        placed[:, 2] += np.interp(t, rangefinder["lift_t_s"], rangefinder["lift_at_t_m"])
    if correction and correction.get("applied"):
        knots = np.array(correction["knot_t_s"])
        vals = np.array(correction["knot_values"])
        placed += np.column_stack([np.interp(t, knots, vals[:, c]) for c in range(3)])
        sweeps = correction.get("sweep_heights")
        if sweeps:  # the height refined sweep by sweep from the floor, on top of the knots (ground.sweep_heights)
            placed[:, 2] += np.interp(t, sweeps["t_s"], sweeps["dz_m"], left=0.0, right=0.0)
    return before, float(np.sqrt(np.mean(np.sum((placed - true_w) ** 2, axis=1))))


def clock_offset_s(traj: dict, log_t_s: np.ndarray, logged_w_m: np.ndarray, step_s: float = 0.1) -> tuple[float, float]:
    """The offset that puts truth.json's trajectory (on the simulator's clock, `serve`'s) on a payload log's clock:
    the shift that best lays its estimated trajectory over the poses the payload logged (both are the estimate the
    autopilot sent), a coarse search in step_s then a fine one; and the median distance left there (m), which
    says whether the two are the same flight. Returns (offset, distance): log time = trajectory time - offset."""
    t = np.asarray(traj["t_s"], dtype=float)
    est = np.asarray(traj["estimated_w_m"], dtype=float)
    lt, lw = np.asarray(log_t_s, dtype=float), np.asarray(logged_w_m, dtype=float)
    if len(t) < 2 or len(lt) < 2:
        raise ValueError("the trajectory and the log need two poses each to be aligned")
    pick = np.linspace(0, len(lt) - 1, min(len(lt), 2000)).astype(int)
    lt, lw = lt[pick], lw[pick]

    def misfit(off: float) -> float:
        at = lt + off
        inside = (at >= t[0]) & (at <= t[-1])
        if inside.sum() < 0.5 * len(lt):  # most of the log must lie within the trajectory
            return math.inf
        e = np.column_stack([np.interp(at[inside], t, est[:, c]) for c in range(3)])
        return float(np.median(np.linalg.norm(e - lw[inside], axis=1)))
    coarse = np.arange(t[0] - lt[-1], t[-1] - lt[0] + step_s, step_s)
    best = min(coarse, key=misfit)
    if not math.isfinite(misfit(best)):
        raise ValueError("the trajectory and the log do not overlap in time at any offset: not the same flight")
    fine = np.arange(best - step_s, best + step_s, step_s / 50.0)
    best = float(min(fine, key=misfit))
    return best, misfit(best)


def on_log_clock(truth: dict, offset_s: float) -> dict:
    """truth.json with its trajectory's times moved to the log's clock (`clock_offset_s`)."""
    pe = dict(truth["pose_error"])
    tr = dict(pe["trajectory"])
    tr["t_s"] = (np.asarray(tr["t_s"], dtype=float) - offset_s).tolist()
    tr["clock"] = "log"
    pe["trajectory"] = tr
    return {**truth, "pose_error": pe}


@dataclass(frozen=True)
class Building:
    """Where the campaign flies: the paper's building by default, or one of the user's (`--storage`)."""

    storage: str | None = None  # LxWxH (m); None: the paper's 60x40x15
    altitude_m: float | None = None  # None: fly's default (12 m)

    def fly_args(self) -> list[str]:
        return ((["--storage", self.storage] if self.storage else [])
                + (["--altitude", f"{self.altitude_m:g}"] if self.altitude_m is not None else []))

    def describe(self) -> str:
        if self.storage is None:
            return "the paper's building (60 x 40 x 15 m, 12 m, 1 m/s)"
        alt = "fly's default altitude" if self.altitude_m is None else f"{self.altitude_m:g} m"
        return f"a {self.storage.replace('x', ' x ')} m building ({alt}, 1 m/s)"


def own_pile(spec: str, building: Building, work: Path) -> tuple[str, str]:
    """An own pile FAMILY:SEED (`sitl.world.shapes`), its top PILE_CLEARANCE_M under the flight: (label, STL path)."""
    family, _, seed = spec.partition(":")
    storage = Storage.parse(building.storage) if building.storage else Storage()  # the paper's
    altitude = building.altitude_m if building.altitude_m is not None else Mission().altitude_m  # fly's default
    shape = make_shape(family, storage, altitude - PILE_CLEARANCE_M, int(seed or 0))
    path = work / f"pile-{family}-{seed or 0}.stl"
    shape.pile.mesh.export(path)
    return f"{family}:{seed or 0}", str(path)


def one(profile: str, pile: str, p_traj: int, seed: int, work: Path, reuse: bool = False,
        building: Building = Building(), stockpile: str | None = None,
        sensor_noise: SensorNoiseModel = SensorNoiseModel.NONE) -> dict:
    """One flight (`stockpile`: the --stockpile argument, default the pile's name) and its two reports."""
    noisy = sensor_noise is not SensorNoiseModel.NONE
    run = work / (f"{profile}-{pile.replace(':', '-')}-{p_traj}-{seed}" + (f"-{sensor_noise.value}" if noisy else ""))
    py = sys.executable
    flown = reuse and (run / "truth.json").is_file()
    row = {"profile": profile, "pile": pile, "p_traj": p_traj, "seed": seed}
    crashed = work / f"{run.name}.crash"  # what `fly` said of a flight that crashed: --reuse does not fly it again
    refused = work / f"{run.name}.refused"  # what `fly` said of a flight it would not fly (a rangefinder's climb)
    if reuse and not flown and crashed.is_file():
        return {**row, "hit": crashed.read_text().strip()}
    if reuse and not flown and refused.is_file():
        return {**row, "refused": refused.read_text().strip()}
    if not flown:
        cmd = [py, "-m", "sitl.cli", "fly", "--stockpile", stockpile or pile, "--p-traj", str(p_traj),
               *building.fly_args(), "--pose-error", profile, "--seed", str(seed), "--out", str(run), "--force",
               "--quiet", *(["--sensor-noise", sensor_noise.value] if noisy else [])]
        done = subprocess.run(cmd, stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:
            if "the vehicle hit" in done.stderr:
                crashed.write_text(done.stderr.strip().splitlines()[-1] + "\n")
                return {**row, "hit": done.stderr.strip().splitlines()[-1]}
            if done.returncode == 2 and "is too high for --pose-error" in done.stderr:
                # refused before take-off: no survey, as a crash is none, but not a crash
                refused.write_text(done.stderr.strip().splitlines()[-1] + "\n")
                return {**row, "refused": done.stderr.strip().splitlines()[-1]}
            sys.stderr.write(done.stderr)
            raise subprocess.CalledProcessError(done.returncode, cmd)
        crashed.unlink(missing_ok=True)  # flown again, and whole: an old crash no longer stands for it
    truth = json.loads((run / "truth.json").read_text())
    crash = kept_flight_crash(truth)
    if crash is not None:
        return {**row, "hit": crash}
    reps = {}
    for flag in ("--no-pose-correction", "--pose-correction"):
        rep = work / f"{run.name}{flag}"
        # the uncorrected report of a kept flight is reused when the code that made it is the code now
        if flown and flag == "--no-pose-correction" and (rep / "report.json").is_file() and made_by_this_code(rep):
            reps[flag] = json.loads((rep / "report.json").read_text())
            continue
        subprocess.run([py, "-m", "ground.cli", "report", str(run), "--out", str(rep), "--no-plots", "--force",
                        "--quiet", flag], check=True, stdout=subprocess.DEVNULL)
        stamp_made_by_this_code(rep)
        reps[flag] = json.loads((rep / "report.json").read_text())
    pc = reps["--pose-correction"].get("pose_correction") or {}
    before, after = trajectory_rms_m(truth, pc, reps["--pose-correction"].get("rangefinder_height"))
    return {**row, "ve_off": reps["--no-pose-correction"]["volume_error_pct"],
            "ve_on": reps["--pose-correction"]["volume_error_pct"],
            "dv_off_pct": signed_error_pct(reps["--no-pose-correction"]),
            "dv_on_pct": signed_error_pct(reps["--pose-correction"]), "applied": bool(pc.get("applied")),
            "traj_before_m": before, "traj_after_m": after,
            "in_interval": reps["--pose-correction"].get("truth_in_interval")}


def signed_error_pct(report: dict) -> float:
    """The report's volume less the true volume, in percent of the true volume: eq. (8) with its sign, so that two
    reports are compared by their volumes (an unsigned Ve counts -0.9 % and +1.0 % as 0.1 pp apart)."""
    truth = report["true_volume_m3"]
    return 100.0 * (report["volume_m3"] - truth) / truth if truth > 0 else math.nan


def kept_flight_crash(truth: dict) -> str | None:
    """Why a kept flight crashed (None: it kept clear of the walls and roof), from the true trajectory its
    truth.json keeps (a flight flown before `fly` checked its approach has no `closest_approach`; one flown
    after it cannot have crashed, `fly` refuses to write it). A flight on the truth has no trajectory: None."""
    storage = Storage.from_dict(truth["storage"])
    traj = (truth.get("pose_error") or {}).get("trajectory")
    if traj is None:
        return None
    approach = closest_approach(np.asarray(traj["t_s"]), np.asarray(traj["true_w_m"]), storage)
    return collision(approach, f450_reach_m())


def table(rows: list[dict]) -> str:
    lines = ["| pile | P_traj | profile | seeds | Ve, no pose error (%) | Ve uncorrected (%) | Ve corrected (%) | "
             f"applied | trajectory RMS before (m) | after (m) | Ve within {VE_TARGET_PP} pp | RMS after <= "
             f"{TRAJ_TARGET_M * 100:.0f} cm | truth in the 90 % interval | hit a wall |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for pile in dict.fromkeys(r["pile"] for r in rows):
        for p in sorted({r["p_traj"] for r in rows}):
            ref = [r for r in rows if r["pile"] == pile and r["p_traj"] == p and r["profile"] == "none"
                   and not r.get("hit")]
            ve_ref = statistics.fmean(r["ve_off"] for r in ref) if ref else float("nan")
            # against the error-free flight's volume, signed (rows from before the signed fields: unsigned Ve)
            signed = all("dv_off_pct" in r for r in ref) and all(
                "dv_on_pct" in r for r in rows if r["pile"] == pile and r["p_traj"] == p and not r.get("hit"))
            off_key, on_key = ("dv_off_pct", "dv_on_pct") if signed else ("ve_off", "ve_on")
            ref_signed = statistics.fmean(r[off_key] for r in ref) if ref else float("nan")
            ref_seed = {r["seed"]: r[off_key] for r in ref}
            for prof in PROFILES:
                case = [r for r in rows if r["pile"] == pile and r["p_traj"] == p and r["profile"] == prof]
                flew = [r for r in case if not r.get("refused")]
                n_refused = len(case) - len(flew)
                rs = [r for r in flew if not r.get("hit")]  # a crash is no survey
                hit = f"{len(flew) - len(rs)}/{len(flew)}" + (f" ({n_refused} refused by `fly`)" if n_refused else "")
                if not rs:
                    if flew or n_refused:
                        lines.append(f"| {pile} | {p} % | {prof} | 0 | {ve_ref:.2f} | | | | | | | | | {hit} |")
                    continue
                m = {k: statistics.fmean(r[k] for r in rs) for k in ("ve_off", "ve_on", "traj_before_m",
                                                                       "traj_after_m")}
                # per seed, against the error-free flight of the same seed
                ve_ok = sum(abs(r[on_key] - ref_seed.get(r["seed"], ref_signed)) <= VE_TARGET_PP for r in rs)
                rms_ok = sum(r["traj_after_m"] <= TRAJ_TARGET_M for r in rs)
                known = [r["in_interval"] for r in rs if r.get("in_interval") is not None]  # older rows lack it
                inside = f"{sum(known)}/{len(known)}" if known else ""
                lines.append(f"| {pile} | {p} % | {prof} | {len(rs)} | {ve_ref:.2f} | {m['ve_off']:.2f} | "
                             f"{m['ve_on']:.2f} | {sum(r['applied'] for r in rs)}/{len(rs)} | "
                             f"{m['traj_before_m']:.2f} | {m['traj_after_m']:.2f} | {ve_ok}/{len(rs)} | "
                             f"{rms_ok}/{len(rs)} | {inside} | {hit} |")
    return "\n".join(lines)


def regeneration_args(argv: list[str]) -> str:
    """The command line the page names, less `--rows` and its files: they are one machine's partial results (a
    campaign split over processes and tabulated by a last call), which a reader does not have; the flights and
    the rest of the options give the same table."""
    out, skipping = [], False
    for a in argv:
        if a == "--rows":
            skipping = True
        elif skipping and not a.startswith("--"):
            continue
        else:
            skipping = False
            out.append(a)
    return " ".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.pose_correction_campaign", description=__doc__)
    ap.add_argument("--write", type=Path, default=None, help="page whose pose-correction-table section to rewrite")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs and reports in this folder")
    ap.add_argument("--piles", nargs="+", default=list(PILES), choices=PILES)
    ap.add_argument("--p-traj", type=int, nargs="+", default=list(P_TRAJ_PCT))
    ap.add_argument("--rows", type=Path, nargs="+", default=None, help="JSON-lines files of rows (see above)")
    ap.add_argument("--reuse", action="store_true", help="with --keep: report the flights already there again, "
                    "without flying them again (see above)")
    ap.add_argument("--storage", default=None, metavar="LxWxH", help="fly this building instead of the paper's")
    ap.add_argument("--altitude", type=float, default=None, help="flight altitude (m; fly's default without)")
    ap.add_argument("--own-piles", nargs="+", default=None, metavar="FAMILY:SEED",
                    help="fly these generated piles (sitl.world.shapes, their top 2 m under the flight) "
                    "instead of the paper's (e.g. cone:1 ridge:2)")
    ap.add_argument("--sensor-noise", type=SensorNoiseModel, default=SensorNoiseModel.NONE,
                    choices=list(SensorNoiseModel),
                    help="the flights' sensor noise (fly's --sensor-noise; default none)")
    ap.add_argument("--section", default=SECTION, help=f"the page's section to rewrite (default {SECTION})")
    args = ap.parse_args(argv)
    building = Building(args.storage, args.altitude)
    if args.reuse and args.keep is None:
        ap.error("--reuse needs --keep (the folder of the flights)")
    rows: list[dict] = []
    for f in args.rows or []:
        if f.is_file():
            rows += [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
    done = {(r["profile"], r["pile"], r["p_traj"], r["seed"]) for r in rows}
    if args.reuse and done:
        # --reuse says "report the kept flights again"; a row already in --rows is taken as it is, so the two
        # together report nothing again for it (a regeneration that silently changed nothing: 2026-11-28)
        print(f"pose_correction_campaign: {len(done)} row(s) read from {', '.join(map(str, args.rows))} are taken as "
              "they are, not reported again; to report every kept flight again, leave out --rows", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        piles = ([own_pile(spec, building, work) for spec in args.own_piles] if args.own_piles
                 else [(pile, pile) for pile in args.piles])
        for pile, stockpile in piles:
            for p in args.p_traj:
                for prof in PROFILES:
                    for seed in args.seeds:
                        if (prof, pile, p, seed) in done:
                            continue
                        rows.append(one(prof, pile, p, seed, work, args.reuse, building, stockpile,
                                        args.sensor_noise))
                        print(json.dumps(rows[-1]), flush=True)
                        if args.rows:
                            with args.rows[0].open("a") as out:
                                out.write(json.dumps(rows[-1]) + "\n")
    seeds = " ".join(map(str, sorted({r["seed"] for r in rows})))
    noise = ("no sensor noise" if args.sensor_noise is SensorNoiseModel.NONE
             else f"sensor noise `{args.sensor_noise.value}`")
    text = (f"Mean over seeds {seeds} per row; {building.describe()}, payload firmware in the loop, {noise}; "
            "Ve (eq. 8) from `pilescan-ground report` with "
            "`--no-pose-correction` (uncorrected) and `--pose-correction` (corrected); trajectory RMS: 3-D position "
            "of the estimate against the truth; the next two columns count the seeds meeting issue 15's targets "
            "(the volume within 0.3 pp of the error-free flight's, signed: an unsigned Ve would count -0.9 % and "
            "+1.0 % as 0.1 pp apart; trajectory RMS after <= 10 cm), the next the corrected "
            "reports whose 90 % volume interval holds the true volume, the last the flights whose "
            "true path reached a wall or the roof (a crash: left out of the other columns). Regenerated by "
            f"`python -m tools.pose_correction_campaign {regeneration_args(sys.argv[1:] if argv is None else argv)}`."
            "\n\n" + table(rows))
    if args.write is not None:
        write_section(args.write, args.section, text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
