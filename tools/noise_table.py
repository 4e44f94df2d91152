"""Ve with realistic sensing: piles 1 and 2 at P_traj 5 / 20 / 30 % under each sensor-noise model
(`--sensor-noise none|datasheet|appendix-a`), over the 20 servo start positions of Fig. 9.

One JSBSim flight per P_traj (cached and shared with `tools.experiments`: the flight depends on the
mission, not on the pile or the noise), sampled for each pile, model and start position by the batch
path (`sitl.sensing.batch_sampler`), which draws its errors with the same functions the lockstep
firmware-in-the-loop's emulators and autopilot use (`sitl.sensing.noise`); the noise is seeded by
(P_traj, pile, start position, model). Each log goes through the ground report's full pipeline
(`survey_from_samples`: despiking, servo re-timing, self-calibration); when the self-calibration
applies a correction the survey is also computed without it, so a false correction shows.
`--spot PILE,P,MODEL,PHASE` also flies that case with the payload firmware in the loop (`fly`,
lockstep) and reports it beside its batch twin.

    python -m tools.noise_table --write docs/results.md [--costs docs/sensor_noise.md] [--jobs 2]
        [--spot 1,20,datasheet,0 ...]
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ArgumentParser
from firmware_py.core.samplelog import SampleFlags
from firmware_py.core.sensor_noise import SensorNoiseModel
from ground.report import ReportOptions, make_report, survey_from_samples
from ground.surface import DEFAULT_EMPTY_CELLS, grid_volume, reconstructed_ratio_pct, volume_error_pct
from sitl.runners.fly import FlyConfig, fly, log_header
from sitl.sensing.batch_sampler import sample_flight
from sitl.world.raycast import World
from sitl.world.stockpile import Stockpile, paper_pile
from tools.doc_sections import write_section
from tools.experiments import ALL_EXPERIMENTS, N_POSITIONS, _flight
from tools.sweep import cached, content_key, fresh_run_note
from tools.workers import progress_map, worker_pool

SECTION = "noise-table"
PILES = ("1", "2")
P_TRAJ_PCT = (5, 20, 30)
MODELS = tuple(SensorNoiseModel)
TABLE_VERSION = "13"
"""Part of every case's cache key: bump it when what a case computes changes (2: the self-calibration refuses
corrections the data do not bear out, docs/design-notes.md; 3: the floor beside the walls is kept; 4: a
pointing-error term in the walls' tolerance, since reverted; 5: faces are left out of the sweep-disagreement
check; 6: the wall-contact fill is the default, and a mount correction must bring its plane points closer;
7: the despiking allows the header's per-sample pointing error; 8: the default surface fit is `local-linear`;
9: its windows' standard errors scaled to the data's own scatter; 10: the unseen fill held under the free-space
ceiling carried at the steepest slope; 11: the `carry-down` fill is the default; 12: the `wall-strip` fill is the
default); 13: `--surface-slopes gp-bridges` is the default."""
MODEL_VERSIONS = {SensorNoiseModel.APPENDIX_A: "3"}
"""Per model, in the key too: 2: the pose errors extrapolated as the payload did; 3: interpolated between the
messages on either side of each sample, as the payload now does (it waits for the pose after a sample)."""


@dataclass(frozen=True)
class Case:
    pile: str
    p_traj_pct: int
    model: SensorNoiseModel
    phases: int = N_POSITIONS

    def key(self) -> str:
        key = {"v": TABLE_VERSION, "pile": self.pile, "p": self.p_traj_pct, "model": self.model.value,
               "phases": self.phases}
        if self.model in MODEL_VERSIONS:
            key["model_v"] = MODEL_VERSIONS[self.model]
        return "noise-table-" + content_key(key)


def _config(case: Case, phase: int) -> FlyConfig:
    e = ALL_EXPERIMENTS["baseline"]
    return FlyConfig(mission=e.mission(case.p_traj_pct), stockpile=case.pile, initial_position=phase,
                     sensor_noise=case.model)


def survey_row(samples: np.ndarray, cfg: FlyConfig, true_m3: float) -> dict:
    """Ve and what the ground station did with one log (default pipeline; without self-calibration too
    when it applied a correction)."""
    header = log_header(cfg, cfg.servo_waveform())
    storage, lever = cfg.mission.storage, np.array(cfg.lever_arm_body_m)
    sv = survey_from_samples(samples, header, storage, cfg.frame, lever, ReportOptions(plots=False))
    ve = volume_error_pct(grid_volume(sv.heights, sv.grid), true_m3)
    applied = sv.mount is not None and sv.mount.any_applied
    ve_nocal = ve
    if applied:
        plain = survey_from_samples(samples, header, storage, cfg.frame, lever,
                                    ReportOptions(plots=False, self_calibration=False))
        ve_nocal = volume_error_pct(grid_volume(plain.heights, plain.grid), true_m3)
    return {"ve_pct": ve, "ve_nocal_pct": ve_nocal, "self_cal_applied": applied,
            "ra_pct": reconstructed_ratio_pct(sv.heights_fit), "spikes": sv.cloud.n_spikes,
            "no_return_pct": 100.0 * float(np.mean((samples["flags"] & int(SampleFlags.NO_RETURN)) != 0))}


def case_samples(case: Case, phases: Iterable[int],
                 cache_dir: Path) -> Iterator[tuple[int, FlyConfig, np.ndarray, Stockpile]]:
    """The case's batch samples at each servo start position in phases: (position, its config, the samples, the
    pile), the noise seeded by the case and the position (so any tool that samples a case draws this table's
    noise)."""
    e = ALL_EXPERIMENTS["baseline"]
    flown = _flight(e, float(case.p_traj_pct), cache_dir)
    base = _config(case, 0)
    pile = paper_pile(case.pile, base.mission.storage)
    world = World(base.mission.storage, pile, base.lidar.max_range_m)
    t = np.arange(int(flown.duration_s * base.lidar.rate_hz) + 1) / base.lidar.rate_hz
    traj = flown.trajectory_at(t)
    for k in phases:
        cfg = replace(base, initial_position=k)
        seed = [case.p_traj_pct, int(case.pile), k, MODELS.index(case.model)]
        yield k, cfg, sample_flight(traj, cfg.servo_waveform(), world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame,
                                    noise=cfg.noise(), seed=seed), pile


def run_case(case: Case, cache_dir: Path) -> list[dict]:
    """The rows of one case, one per servo start position (cached)."""
    def compute() -> list[dict]:
        return [{"phase": k, **survey_row(s, cfg, pile.volume_m3)}
                for k, cfg, s, pile in case_samples(case, range(case.phases), cache_dir)]
    return cached(cache_dir, case.key(), compute, kind="json")


def spot_check(pile: str, p_pct: int, model: SensorNoiseModel, phase: int) -> dict:
    """One case flown with the payload firmware in the loop (lockstep `fly`) and reported."""
    e = ALL_EXPERIMENTS["baseline"]
    cfg = FlyConfig(mission=e.mission(p_pct), stockpile=pile, initial_position=phase, sensor_noise=model,
                    payload="firmware", seed=phase)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        fly(cfg, run, force=True, progress=lambda _m: None)
        rep = make_report(run, Path(tmp) / "report", ReportOptions(plots=False))
        cal = rep.get("self_calibration") or {}
        applied = any(isinstance(v, dict) and v.get("applied") for v in cal.values())
        ve_nocal = rep["volume_error_pct"]
        if applied:
            ve_nocal = make_report(run, Path(tmp) / "plain", ReportOptions(plots=False, self_calibration=False)
                                   )["volume_error_pct"]
    return {"pile": pile, "p": p_pct, "model": model, "phase": phase, "ve_pct": rep["volume_error_pct"],
            "self_cal_applied": applied, "ve_nocal_pct": ve_nocal,
            "spikes": rep["n_samples_spikes"], "wall_s": time.perf_counter() - t0,
            "no_return_pct": 100.0 * rep["n_samples_excluded"] / max(1, rep["n_samples"])}


def _stats(values: list[float]) -> str:
    sd = statistics.pstdev(values) if len(values) > 1 else 0.0
    return f"{statistics.fmean(values):.2f} ± {sd:.2f}"


def table(results: dict[Case, list[dict]]) -> str:
    out = ["| pile | P_traj | sensor noise | Ve [%] mean ± sd | Ve max [%] | Ve without self-cal. [%] | "
           "self-cal. applied | R_a [%] | no returns [%] | spikes removed |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for case, rows in results.items():
        ve = [r["ve_pct"] for r in rows]
        out.append(f"| {case.pile} | {case.p_traj_pct} % | {case.model.value} | {_stats(ve)} | {max(ve):.2f} | "
                   f"{_stats([r['ve_nocal_pct'] for r in rows])} | "
                   f"{sum(r['self_cal_applied'] for r in rows)} of {len(rows)} | "
                   f"{statistics.fmean(r['ra_pct'] for r in rows):.1f} | "
                   f"{statistics.fmean(r['no_return_pct'] for r in rows):.1f} | "
                   f"{statistics.fmean(r['spikes'] for r in rows):.0f} |")
    return "\n".join(out)


def spot_table(spots: list[dict], results: dict[Case, list[dict]]) -> str:
    out = ["| pile | P_traj | sensor noise | start position | Ve firmware in the loop [%] | Ve batch, same position "
           "[%] | self-cal. applied (firmware) | Ve firmware without self-cal. [%] | Ve batch without self-cal. [%] "
           "| no returns + flagged (firmware) [%] | wall time [s] |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in spots:
        twin = next((r for c, rows in results.items() if (c.pile, c.p_traj_pct, c.model) == (s["pile"], s["p"],
                     s["model"]) for r in rows if r["phase"] == s["phase"]), None)
        batch = f"{twin['ve_pct']:.2f}" if twin else "-"
        batch_plain = f"{twin['ve_nocal_pct']:.2f}" if twin else "-"
        out.append(f"| {s['pile']} | {s['p']} % | {s['model'].value} | {s['phase']} | {s['ve_pct']:.2f} | {batch} | "
                   f"{'yes' if s['self_cal_applied'] else 'no'} | {s['ve_nocal_pct']:.2f} | {batch_plain} | "
                   f"{s['no_return_pct']:.1f} | {s['wall_s']:.0f} |")
    return "\n".join(out)


COSTS_SECTION = "noise-costs"
NOTED_COST_PP = 0.5
"""A row whose noise costs more than this over the noise-free row of the same pile and P_traj is named as an exception
in `costs` (half a point: the size of the paper's own Ve at its best P_traj)."""


def _mean(rows: list[dict], key: str) -> float:
    return statistics.fmean(r[key] for r in rows)


def costs(results: dict[Case, list[dict]], spots: list[dict]) -> str:
    """What the noise costs, read off the rows (docs/sensor_noise.md's section): the self-calibration's corrections,
    the cost at each P_traj over the noise-free row, the datasheet's no-returns, the despiking, the firmware spots."""
    by = {(c.pile, c.p_traj_pct, c.model): rows for c, rows in results.items()}
    noisy = [r for (_, _, m), rows in by.items() if m is not SensorNoiseModel.NONE for r in rows]
    out = [f"- **Corrections applied by the self-calibration from the building**: "
           f"{sum(r['self_cal_applied'] for r in noisy)} of the {len(noisy)} noisy surveys (every mount is square, "
           "so any correction would be false)."]
    for p in P_TRAJ_PCT:
        cost = [(statistics.fmean(r["ve_pct"] for r in rows) - _mean(by[(pile, p, SensorNoiseModel.NONE)], "ve_pct"),
                 pile, m) for (pile, pp, m), rows in by.items() if pp == p and m is not SensorNoiseModel.NONE]
        worst = max(cost)
        over = [f"pile {pile} {m.value} {c:+.2f} pp" for c, pile, m in sorted(cost, reverse=True) if c > NOTED_COST_PP]
        out.append(f"- **P_traj {p} %**: the noise moves the mean Ve by {min(cost)[0]:+.2f} to {worst[0]:+.2f} pp "
                   f"over the noise-free row of the same pile (the most: pile {worst[1]}, {worst[2].value})"
                   + (f"; more than {NOTED_COST_PP} pp: {', '.join(over)}." if over else "."))
    if all((pile, p, m) in by for pile in PILES for p in P_TRAJ_PCT
           for m in (SensorNoiseModel.NONE, SensorNoiseModel.DATASHEET)):  # the rows the bullet reads
        share = " / ".join(f"{_mean(by[(PILES[0], p, SensorNoiseModel.DATASHEET)], 'no_return_pct'):.1f}"
                           for p in P_TRAJ_PCT)
        plain = " / ".join(f"{_mean(by[(PILES[0], p, SensorNoiseModel.NONE)], 'no_return_pct'):.1f}"
                           for p in P_TRAJ_PCT)
        far = max(P_TRAJ_PCT)
        rows_far = [(pile, by[(pile, far, SensorNoiseModel.NONE)], by[(pile, far, SensorNoiseModel.DATASHEET)])
                    for pile in PILES]
        out.append(f"- **The datasheet's no-returns**: {share} % of pile {PILES[0]}'s samples at P_traj "
                   f"{' / '.join(str(p) for p in P_TRAJ_PCT)} % find no echo ({plain} % without noise: beams beyond "
                   f"the rated range). At P_traj {far} % the sweep's ends from the middle of the hall reach the walls "
                   "and corners less often: R_a "
                   + "; ".join(f"pile {pile} {_mean(a, 'ra_pct'):.1f} -> {_mean(b, 'ra_pct'):.1f} %, Ve "
                               f"{_stats([r['ve_pct'] for r in b])} % (max {max(r['ve_pct'] for r in b):.2f} %)"
                               for pile, a, b in rows_far) + ".")
    out.append(f"- **Despiking** removed {sum(r['spikes'] for r in noisy):,} samples in all {len(noisy)} noisy "
               "surveys (its threshold allows each sample's pointing error as the header states it).")
    if spots:
        pairs = []
        for s in spots:
            twin = next((r for r in by.get((s["pile"], s["p"], s["model"]), []) if r["phase"] == s["phase"]), None)
            batch = f"{twin['ve_nocal_pct']:.2f}" if twin else "-"
            pairs.append(f"pile {s['pile']} P_traj {s['p']} % {s['model'].value} {s['ve_nocal_pct']:.2f} / {batch}")
        spread = max(((statistics.pstdev(r["ve_pct"] for r in by[(s["pile"], s["p"], s["model"])]), s)
                      for s in spots if (s["pile"], s["p"], s["model"]) in by), key=lambda t: t[0], default=None)
        out.append(f"- **Firmware in the loop against the batch path** ({len(spots)} spot checks, Ve without "
                   f"self-calibration, firmware / batch at the same start position): {'; '.join(pairs)}. The noise "
                   "draws differ, so only the spread of the batch rows says whether two figures disagree"
                   + (f" (the widest: pile {spread[1]['pile']}, P_traj {spread[1]['p']} %, {spread[1]['model'].value},"
                      f" sd {spread[0]:.2f} pp)" if spread else "")
                   + f". The self-calibration applied a correction in {sum(s['self_cal_applied'] for s in spots)} of "
                   "the firmware flights.")
    return "\n".join(out)


def _spot(text: str) -> tuple[str, int, SensorNoiseModel, int]:
    try:
        pile, p, model, phase = text.split(",")
        if pile not in PILES or int(p) not in P_TRAJ_PCT or not 0 <= int(phase) < N_POSITIONS:
            raise ValueError
        return pile, int(p), SensorNoiseModel(model), int(phase)
    except ValueError:
        raise ValueError(f"--spot must be PILE,P_TRAJ,MODEL,PHASE with a pile of {PILES}, P_traj of {P_TRAJ_PCT}, "
                         f"a model of {', '.join(m.value for m in MODELS)} and a phase 0-19, got {text!r}") from None


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.noise_table", description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", type=Path, default=None, help="regenerate this tool's section of this page")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--phases", type=int, default=N_POSITIONS, help="servo start positions per case (default 20)")
    ap.add_argument("--cache", type=Path, default=Path("runs/sweep-cache"), help="flight and case cache")
    ap.add_argument("--costs", type=Path, default=None,
                    help="also write what the noise costs, read off the rows, into this page (docs/sensor_noise.md)")
    ap.add_argument("--spot", action="append", default=[], metavar="PILE,P,MODEL,PHASE",
                    help="also fly this case with the firmware in the loop (repeatable)")
    args = ap.parse_args(argv)
    if args.jobs < 1 or not 1 <= args.phases <= N_POSITIONS:
        ap.error(f"--jobs must be >= 1 and --phases 1-{N_POSITIONS}")
    try:
        spots = [_spot(s) for s in args.spot]
    except ValueError as exc:
        ap.error(str(exc))
    t0 = time.perf_counter()
    e = ALL_EXPERIMENTS["baseline"]
    for p in P_TRAJ_PCT:  # the flights first, once each (the workers then read them from the cache)
        _flight(e, float(p), args.cache)
    cases = [Case(pile, p, m, args.phases) for pile in PILES for p in P_TRAJ_PCT for m in MODELS]
    n_todo = sum(not (args.cache / f"{c.key()}.json").exists() for c in cases)
    with worker_pool(args.jobs) as pool:
        results = dict(zip(cases, progress_map(pool, run_case, cases, [args.cache] * len(cases), desc="noise_table"),
                           strict=True))
        print(table(results), flush=True)
        spot_rows = (progress_map(pool, spot_check, *zip(*spots, strict=True), desc="noise_table spots") if spots
                     else [])
    wall = time.perf_counter() - t0
    fresh_note = fresh_run_note(args.cache / "noise-table-fresh-run.json", n_todo == len(cases), wall, args.jobs)
    parts = [
        "## Ve with realistic sensing (`--sensor-noise`)",
        "",
        f"Regenerate with `python -m tools.noise_table --write docs/results.md --jobs {args.jobs}"
        + (f" --costs {args.costs}" if args.costs is not None else "")
        + "".join(f" --spot {s}" for s in args.spot) + f"` ({wall / 60:.1f} min on this run, which computed "
        f"{n_todo} of the {len(cases)} cases; flights and cases are cached in `{args.cache}`{fresh_note}). "
        "The paper's baseline (Table 1: semi-triangular sweep, 1 m/s, 30 deg/s yaw, "
        "one-step corners), the JSBSim vehicle, the paper's building; each row is "
        f"{args.phases} servo start positions (Fig. 9) sampled by the batch path with the same noise functions "
        "as `fly` (docs/noise.md says what each model is). Ve (eq. 8, the report's default "
        f"`{DEFAULT_EMPTY_CELLS}` empty cells) through the ground "
        "report's default pipeline: mean ± standard deviation and the worst (max) over the start positions. "
        "\"Ve without self-cal.\" is the same surveys with `--no-self-calibration` where the self-calibration "
        "applied a correction (elsewhere the same value): every correction on these flights is false, the mount "
        "is square. \"no returns\": samples flagged NO_RETURN (nothing within the sensor's range, or a "
        "datasheet no-return).",
        "",
        table(results),
    ]
    if spot_rows:
        parts += ["", "Spot checks with the payload firmware in the loop (`pilescan-sitl fly --sensor-noise MODEL "
                  "--phase K --seed K`, lockstep, then `pilescan-ground report`), beside the batch row of the same "
                  "start position (the noise draws differ: only the distributions are the same):", "",
                  spot_table(spot_rows, results)]
    text = "\n".join(parts)
    if args.write is not None:
        write_section(args.write, SECTION, text)
    if args.costs is not None:
        write_section(args.costs, COSTS_SECTION, f"Read off the noise table (docs/results.md) by the command that "
                      f"writes it, with `--costs {args.costs}` ({args.phases} servo start positions per row):\n\n"
                      + costs(results, spot_rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
