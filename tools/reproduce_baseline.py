"""Baseline reproduction (paper Sec. 4.1, Fig. 11, 19, Table 2 first row), ideal and JSBSim plants.

Both piles x P_traj 5-30 % x the 20 servo initial positions of Fig. 9; volume error and R_a as
mean +- standard deviation, beside the figures the paper states in its text. Each (pile, P_traj)
is flown once: the servo's initial position does not change the flight, so the 20 positions reuse
the trajectory and only re-cast the beams (the same functions the run directory path uses).
Usage: python -m tools.reproduce_baseline [--write docs/results.md] [--jobs 2]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from ground.report import ReportOptions, survey_from_samples
from ground.surface import EMPTY_CELL_POLICIES, fill_empty, grid_volume, reconstructed_ratio_pct, volume_error_pct
from sitl.batch_sampler import sample_flight
from sitl.mission import Mission
from sitl.raycast import World
from sitl.run import PLANTS, FlyConfig, fly_trajectory, log_header
from sitl.stockpile import paper_pile

P_TRAJ_PCT = (5, 10, 15, 20, 25, 30)
N_POSITIONS = 20
# What the paper's text states (Sec. 4.1, 4.4, Table 2); None where it gives no number.
PAPER_VE = {("1", 5): 0.0, ("2", 5): 0.0, ("1", 30): (6.1, 0.5), ("2", 30): (4.3, 0.4),
            ("1", 10): "< 0.3", ("1", 15): "< 0.3", ("1", 20): "< 0.3"}
PAPER_RA = {("1", 30): 88.6, ("2", 30): 94.7, ("1", 5): 100.0, ("2", 5): 100.0}
PAPER_TABLE2 = {"1": (1.6, 96.6), "2": (1.6, 97.6)}


def run_case(pile_name: str, p_pct: int, plant: str = "jsbsim") -> dict:
    """All servo positions of one (pile, P_traj, plant): Ve per policy and R_a, per position."""
    base = FlyConfig(mission=Mission(p_traj=p_pct / 100), stockpile=pile_name, plant=plant)
    storage = base.mission.storage
    pile = paper_pile(pile_name, storage)
    world = World(storage, pile, base.lidar.max_range_m)
    traj, duration_s, energy_j = fly_trajectory(base)
    out: dict = {"ve": {p: [] for p in EMPTY_CELL_POLICIES}, "ra": [], "plant": plant, "energy_j": energy_j,
                 "duration_s": duration_s}
    for k in range(N_POSITIONS):
        cfg = replace(base, initial_position=k)
        wf = cfg.servo_waveform()
        samples = sample_flight(traj, wf, world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame)
        sv = survey_from_samples(samples, log_header(cfg, wf), storage, cfg.frame, np.array(cfg.lever_arm_body_m),
                                 ReportOptions(plots=False))
        for pol in EMPTY_CELL_POLICIES:
            v = grid_volume(fill_empty(sv.heights_fit, pol), sv.grid)
            out["ve"][pol].append(volume_error_pct(v, pile.volume_m3))
        out["ra"].append(reconstructed_ratio_pct(sv.heights_fit))
    return {"pile": pile_name, "p": p_pct, **out}


def _ms(values) -> str:
    return f"{np.mean(values):.2f} ± {np.std(values):.2f}"


def _paper(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, str):
        return v
    return f"{v[0]:.1f} ± {v[1]:.1f}" if isinstance(v, tuple) else f"≈ {v:g}"


def render(results: list[dict], wall_s: float) -> str:
    lines = []
    for plant in PLANTS:
        rows = [r for r in results if r["plant"] == plant]
        if rows:
            lines += [f"### {plant} plant", "", render_plant(rows), ""]
    if {r["plant"] for r in results} >= {"ideal", "jsbsim"}:
        lines += ["### Ideal vs JSBSim plant (Ve nearest, mean over servo positions)", "",
                  "| pile | P_traj | ideal [%] | jsbsim [%] | difference [pp] |", "|---|---|---|---|---|"]
        for r in sorted((r for r in results if r["plant"] == "jsbsim"), key=lambda r: (r["pile"], r["p"])):
            i = next(x for x in results if x["plant"] == "ideal" and (x["pile"], x["p"]) == (r["pile"], r["p"]))
            a, b = np.mean(i["ve"]["nearest"]), np.mean(r["ve"]["nearest"])
            lines.append(f"| {r['pile']} | {r['p']} % | {a:.2f} | {b:.2f} | {b - a:+.2f} |")
        lines.append("")
    lines.append(f"{len(results) * N_POSITIONS} surveys in {wall_s:.0f} s wall time.")
    return "\n".join(lines)


def render_plant(results: list[dict]) -> str:
    energy = {(r["pile"], r["p"]): r["energy_j"] for r in results}
    lines = ["| pile | P_traj | Ve nearest [%] | Ve leave [%] | Ve paper [%] | R_a [%] | R_a paper [%] | flight [s] "
             "| ΔE eq. 19 [%] |", "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(results, key=lambda r: (r["pile"], r["p"])):
        key = (r["pile"], r["p"])
        ref = energy.get((r["pile"], 5))
        de = "—" if r["energy_j"] is None or not ref else f"{(r['energy_j'] - ref) / ref * 100:+.1f}"
        lines.append(f"| {r['pile']} | {r['p']} % | {_ms(r['ve']['nearest'])} | {_ms(r['ve']['leave'])} | "
                     f"{_paper(PAPER_VE.get(key))} | {_ms(r['ra'])} | {_paper(PAPER_RA.get(key))} | "
                     f"{r['duration_s']:.0f} | {de} |")
    lines += ["", "Averages over the six P_traj (Table 2, baseline row):", "",
              "| pile | Ve nearest [%] | Ve leave [%] | Ve paper [%] | R_a [%] | R_a paper [%] |",
              "|---|---|---|---|---|---|"]
    for pile in ("1", "2"):
        rows = [r for r in results if r["pile"] == pile]
        if not rows:
            continue
        def mean(key, pol=None, rows=rows):
            return np.mean([np.mean(r[key][pol] if pol else r[key]) for r in rows])
        lines.append(f"| {pile} | {mean('ve', 'nearest'):.2f} | {mean('ve', 'leave'):.2f} | {PAPER_TABLE2[pile][0]} | "
                     f"{mean('ra'):.1f} | {PAPER_TABLE2[pile][1]} |")
    return "\n".join(lines)


DISCUSSION = """
## Reading the table

- Setup: the paper's baseline (Table 1): 60 x 40 x 15 m building, 12 m altitude, 1 m/s, 30 deg/s max
  yaw rate, one-step corners, semi-triangular servo (C = 0.95, 5 rad/s peak -> f = 0.668 Hz),
  LIDAR-Lite at 500 Hz with 1 cm resolution, no noise. Two vehicles: **jsbsim** (JSBSim's F450,
  1.4 kg + 40 g payload, flown by pilescan's autopilot with the paper's outer loops) and **ideal**
  (kinematic, exact waypoints, level attitude, turns in place). Mean ± standard deviation over the
  20 servo initial positions of Fig. 9. "Ve leave" uses the paper's treatment of cells outside the fitted surface
  (no volume); "Ve nearest" is pilescan's default (extend the surface to the walls).
- The paper's text gives Ve only at the ends of the P_traj range and the six-P_traj averages
  (Table 2); its Figs. 11 and 20 are not digitised here, so other cells show "—".
- Our piles are not the paper's piles: they come from the same generator (Sec. 3.1) with seeds
  chosen for Table 1's volumes, but the random heights differ, and so does how much material sits
  in the corner blind spots, which is what drives Ve at large P_traj. Pile 2 (material along the
  walls) is the most sensitive to that.
- Ideal vs JSBSim: the flown vehicle pitches and rolls a few degrees, slows into its turns and
  starts them before it stops; the volume errors differ from the ideal plant's by at most
  0.2 percentage points (table above), so the ideal plant is a fair fast path for sweeps.
- Energy (eq. 19, JSBSim only) counts the survey itself, from the first turn on W0 to the return
  there, without take-off and landing. Hover power dominates at 1 m/s, so energy follows flight
  time and falls by about 21 % at P_traj = 15 % and 32 % at 20 %; the paper reports about 16 % for
  15-20 %, its Webots energies presumably including the parts of the flight ours leaves out.
- Trends that hold: Ve rises and R_a falls with P_traj; the servo position matters more at large
  P_traj (the spread grows); pile 1 stays below 0.3 % up to P_traj = 20 % as the paper states.
  Pile 1's mean R_a (96.5 %) matches Table 2 (96.6 %).
- Where we differ: pile 1 at P_traj = 30 % has Ve ≈ 1.3 % against the paper's 6.1 %: our pile 1
  has less material in the four corner blind spots than theirs, and our in-place 90 deg turns
  dwell 3 s on each corner while the beam sweeps it. Pile 2 with the paper's `leave` policy is
  worse than the paper's (5.1 % vs 1.6 % on average): every wall of our pile 2 carries material
  (the generator puts random 1-7 m heights on the walls), and `leave` drops the strip between the
  last samples and each wall plus the corner blind spots. Extending the surface to the walls
  (`nearest`, pilescan's default) brings the average to 0.6 %.
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--write", type=Path, help="write the results page (e.g. docs/results.md)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--plants", default=",".join(PLANTS), help="comma-separated: jsbsim,ideal")
    args = ap.parse_args(argv)
    plants = [p for p in args.plants.split(",") if p]
    unknown = set(plants) - set(PLANTS)
    if unknown:
        ap.error(f"unknown plant(s): {', '.join(sorted(unknown))}")
    cases = [(pile, p, plant) for plant in plants for pile in ("1", "2") for p in P_TRAJ_PCT]
    t0 = time.perf_counter()
    results = []
    # spawn, not fork: a forked child inherits the parent's thread pools (BLAS, Embree's TBB) and can hang;
    # and one BLAS thread per worker, as the workers already fill the cores.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=max(1, args.jobs), mp_context=ctx) as pool:
        futures = [pool.submit(run_case, *c) for c in cases]
        for i, f in enumerate(futures, 1):
            results.append(f.result())
            r = results[-1]
            print(f"  [{i}/{len(cases)}] {r['plant']} pile {r['pile']} P_traj {r['p']} % done", flush=True)
    text = render(results, time.perf_counter() - t0)
    print(text)
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text("# Paper reproduction: results\n\nRegenerate with `python -m tools.reproduce_baseline "
                              f"--write {args.write}`.\n\n## Baseline (Sec. 4.1, Fig. 11, Table 2)\n\n{text}\n"
                              f"{DISCUSSION}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
