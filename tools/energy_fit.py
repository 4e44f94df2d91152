"""Fit the coverage planner's energy model (`sitl.missions.coverage.EnergyModel`) on JSBSim F450 flights and
check it on flights not in the fit; writes its section of docs/coverage.md.

    python -m tools.energy_fit [--cache runs/sweep-cache] [--check-runs RUN_DIR ...] [--write docs/coverage.md]

The fit set: loops of the planner's family (three offset sets, plain and cut corners, 0.5-2 m/s), lawnmower
tours (legs 4, 8 and 16 m apart), sawtooth tours (turns of 113 and 143 degrees) and out-and-back legs (10 and
40 m), at 1 and 2 m/s, all at 30 deg/s. The held-out set: closed tours through seeded
random waypoints (5-13 of them, 1-2 m/s), the P_traj 20 % rectangle at 17, 6 and 1 deg/s, and any JSBSim run
directories given with --check-runs (their truth.json: the mission flown, its flight time and energy; e.g.
the gap re-flights of `tools.gap_campaign`). Every flight is cached like `tools.experiments`' (40 g payload).

The flight time is fitted by least squares on the model's four terms, the power as the energy-weighted ratio
E / T over the fit set; the braking is the least v^2 / (2 x) over the fit's plain-cornered loops, x the
farthest the vehicle ran past the loop towards a wall.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.storage import Storage
from sitl.missions.coverage import EnergyModel, LoopMission, LoopPlan, loop_turns_rad
from sitl.missions.rectangle import Mission
from tools.coverage_campaign import flown_jsbsim
from tools.doc_sections import write_section

STORAGE = Storage()
DOC = Path(__file__).resolve().parents[1] / "docs" / "coverage.md"
SECTION = "energy-fit"
YAW_30 = math.radians(30.0)


@dataclass(frozen=True)
class Flight:
    name: str
    group: str  # "fit" or "held-out"
    path_m: float
    speed_m_s: float
    yaw_rate_rad_s: float
    turns_rad: tuple[float, ...]
    time_s: float
    energy_j: float
    excursion_m: float | None = None  # farthest past the loop towards a wall (plain-cornered loops)


def terms(f: Flight) -> list[float]:
    """The model's five flight-time terms (EnergyModel.flight_time_s with unit coefficients)."""
    t = np.abs(np.asarray(f.turns_rad))
    return [f.path_m / f.speed_m_s, float(np.minimum(t, np.pi / 2).sum()) / f.yaw_rate_rad_s,
            float(np.maximum(t - np.pi / 2, 0.0).sum()) / f.yaw_rate_rad_s,
            f.speed_m_s * float(np.minimum(t / (np.pi / 2), 1.0).sum()), float(len(t))]


def fit_missions() -> dict[str, object]:
    out: dict[str, object] = {}
    sizes = (STORAGE.width_m, STORAGE.length_m, STORAGE.width_m, STORAGE.length_m)
    for v in (0.5, 1.0, 1.5, 2.0):
        for offs in ((0.05,) * 4, (0.2,) * 4, (0.1, 0.3, 0.15, 0.25)):
            for cut in (0.0, 2.0):
                plan = LoopPlan(tuple(o * s for o, s in zip(offs, sizes, strict=True)), cut, v)
                out[f"loop {'/'.join(f'{o * 100:g}' for o in offs)} % cut {cut:g} m {v:g} m/s"] = \
                    plan.mission(STORAGE, 12.0, YAW_30)
    for v in (1.0, 2.0):
        for gap in (4.0, 8.0, 16.0):
            pts = []
            for i, x in enumerate(np.arange(5.0, STORAGE.length_m - 5.0, gap)):
                ys = (5.0, STORAGE.width_m - 5.0) if i % 2 == 0 else (STORAGE.width_m - 5.0, 5.0)
                pts += [(float(x), ys[0]), (float(x), ys[1])]
            out[f"lawnmower {gap:g} m {v:g} m/s"] = LoopMission(STORAGE, (*pts, pts[0]), v, 12.0, YAW_30)
        for step in (10.0, 20.0):  # sawtooth: turns sharper than 90 degrees
            pts = [(float(x), 5.0 if i % 2 == 0 else STORAGE.width_m - 5.0)
                   for i, x in enumerate(np.arange(5.0, STORAGE.length_m - 4.0, step))]
            out[f"sawtooth {step:g} m {v:g} m/s"] = LoopMission(STORAGE, (*pts, pts[0]), v, 12.0, YAW_30)
        for length in (10.0, 40.0):  # out and back: two 180-degree turns
            a, b = (10.0, STORAGE.width_m / 2), (10.0 + length, STORAGE.width_m / 2)
            out[f"out and back {length:g} m {v:g} m/s"] = LoopMission(STORAGE, (a, b, a), v, 12.0, YAW_30)
    return out


def held_out_missions(seed: int = 7) -> dict[str, object]:
    out: dict[str, object] = {}
    rng = np.random.default_rng(seed)
    for i in range(8):
        n, v = int(rng.integers(5, 14)), float(rng.choice([1.0, 1.5, 2.0]))
        pts = [(float(rng.uniform(3, STORAGE.length_m - 3)), float(rng.uniform(3, STORAGE.width_m - 3)))
               for _ in range(n)]
        out[f"random tour {i} ({n} waypoints) {v:g} m/s"] = LoopMission(STORAGE, (*pts, pts[0]), v, 12.0, YAW_30)
    for yaw in (17.0, 6.0, 1.0):
        out[f"rect P_traj 20 % {yaw:g} deg/s"] = Mission(STORAGE, p_traj=0.2, yaw_rate_max_rad_s=math.radians(yaw))
    return out


def excursion_m(flown, mission) -> float:
    """How far the vehicle went past the loop's bounding box towards a wall."""
    t = np.arange(0.0, flown.duration_s, 0.05)
    p = flown.trajectory_at(t).pos_ned_m
    x, y = p[:, 0], -p[:, 1]  # W = (north, -east) with the identity frame
    wp = mission.waypoints_w()
    return float(max(wp[:, 0].min() - x.min(), x.max() - wp[:, 0].max(), wp[:, 1].min() - y.min(),
                     y.max() - wp[:, 1].max()))


def flight_of(name: str, group: str, mission, cache: Path) -> Flight:
    flown = flown_jsbsim(mission, cache)
    plain = isinstance(mission, LoopMission) and len(mission.waypoints) == 5
    return Flight(name, group, mission.path_length_m(), mission.speed_m_s, mission.yaw_rate_max_rad_s,
                  tuple(loop_turns_rad(mission.waypoints_w())), flown.duration_s, flown.energy_j,
                  excursion_m(flown, mission) if plain else None)


def flight_of_run(run: Path) -> Flight:
    """A flown run directory's mission (truth.json: a coverage or gap mission) and measured time and energy."""
    truth = json.loads((run / "truth.json").read_text())
    m = truth.get("mission") or {}
    if m.get("kind") != "coverage" or truth.get("energy_j") is None:
        raise ValueError(f"{run}: not a JSBSim flight of a loop mission")
    mission = LoopMission(STORAGE, tuple(tuple(p) for p in m["waypoints"]), m["speed_m_s"], m["altitude_m"],
                          m["yaw_rate_max_rad_s"])
    return Flight(run.name, "held-out", mission.path_length_m(), mission.speed_m_s, mission.yaw_rate_max_rad_s,
                  tuple(loop_turns_rad(mission.waypoints_w())), truth["flight_time_s"], truth["energy_j"])


def fit(flights: list[Flight]) -> EnergyModel:
    fs = [f for f in flights if f.group == "fit"]
    x = np.array([terms(f) for f in fs])
    t = np.array([f.time_s for f in fs])
    e = np.array([f.energy_j for f in fs])
    (a, b, b2, c, d), *_ = np.linalg.lstsq(x, t, rcond=None)
    brake = min(f.speed_m_s ** 2 / (2 * f.excursion_m) for f in fs if f.excursion_m and f.excursion_m > 0.01)
    return EnergyModel(power_w=float(e @ t / (t @ t)), leg_factor=float(a), turn_factor=float(b),
                       reverse_factor=float(b2),
                       stop_s_per_m_s=float(c), waypoint_s=float(d), brake_m_s2=float(brake))


def page(flights: list[Flight], model: EnergyModel, old: EnergyModel, args) -> str:
    def err(f: Flight, m: EnergyModel) -> float:
        return 100 * (m.energy_j(f.path_m, f.speed_m_s, f.turns_rad, f.yaw_rate_rad_s) / f.energy_j - 1)

    runs = " --check-runs " + " ".join(map(str, args.check_runs)) if args.check_runs else ""
    out = [f"Generated by `python -m tools.energy_fit{runs}`: JSBSim F450, 40 g payload. The fitted model (the "
           "defaults of `EnergyModel` in `sitl/missions/coverage.py` are these, rounded):", "",
           f"T = {model.leg_factor:.3f} L / v + {model.turn_factor:.3f} sum min(|dpsi|, 90 deg) / omega + "
           f"{model.reverse_factor:.3f} sum max(|dpsi| - 90 deg, 0) / omega + "
           f"{model.stop_s_per_m_s:.3f} s/(m/s) x v x sum min(|dpsi| / 90 deg, 1) + {model.waypoint_s:.3f} s x "
           f"waypoints; E = {model.power_w:.2f} W x T; braking {model.brake_m_s2:.2f} m/s^2 "
           f"(overshoot {model.overshoot_m(1.0):.2f} m at 1 m/s, {model.overshoot_m(2.0):.2f} m at 2 m/s).", "",
           "| set | flight | path [m] | v [m/s] | yaw rate [deg/s] | waypoints | flight [s] | energy [kJ] | "
           "model [kJ] | error [%] | before [%] |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for f in flights:
        e = model.energy_j(f.path_m, f.speed_m_s, f.turns_rad, f.yaw_rate_rad_s)
        out.append(f"| {f.group} | {f.name} | {f.path_m:.0f} | {f.speed_m_s:g} | "
                   f"{math.degrees(f.yaw_rate_rad_s):.0f} | {len(f.turns_rad)} | {f.time_s:.1f} | "
                   f"{f.energy_j / 1000:.2f} | {e / 1000:.2f} | {err(f, model):+.1f} | {err(f, old):+.1f} |")
    out += ["", "| set | flights | mean abs error [%] | max abs error [%] | before: mean / max [%] |",
            "|---|---|---|---|---|"]
    for name, sel in (("fit", lambda f: f.group == "fit"),
                      ("held-out, 30 deg/s", lambda f: f.group == "held-out" and f.yaw_rate_rad_s > math.radians(29)),
                      ("held-out, 17 and 6 deg/s", lambda f: f.group == "held-out"
                       and math.radians(5) < f.yaw_rate_rad_s < math.radians(29)),
                      ("held-out, 1 deg/s", lambda f: f.group == "held-out" and f.yaw_rate_rad_s < math.radians(5))):
        fs = [f for f in flights if sel(f)]
        if not fs:
            continue
        new, before = [abs(err(f, model)) for f in fs], [abs(err(f, old)) for f in fs]
        out.append(f"| {name} | {len(fs)} | {statistics.fmean(new):.1f} | {max(new):.1f} | "
                   f"{statistics.fmean(before):.1f} / {max(before):.1f} |")
    return "\n".join(out)


OLD_MODEL_J = (143.26, 228.0)
"""The model before (docs/coverage.md): E = 143.26 W x L / v + 228 J/rad x sum|dpsi|, fitted on two rectangles."""


@dataclass(frozen=True)
class _OldModel:
    """The energy model before this fit, for the 'before' column."""

    def energy_j(self, path_m: float, speed_m_s: float, turns_rad, yaw_rate_rad_s: float) -> float:
        return OLD_MODEL_J[0] * path_m / speed_m_s + OLD_MODEL_J[1] * float(np.abs(turns_rad).sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.energy_fit", description=__doc__.split("\n")[0])
    ap.add_argument("--cache", type=Path, default=Path("runs/sweep-cache"))
    ap.add_argument("--check-runs", type=Path, nargs="*", default=[], metavar="RUN_DIR",
                    help="JSBSim run directories of loop missions to check the model on too")
    ap.add_argument("--write", type=Path, default=DOC)
    args = ap.parse_args(argv)
    flights = []
    for group, missions in (("fit", fit_missions()), ("held-out", held_out_missions())):
        for name, m in missions.items():
            flights.append(flight_of(name, group, m, args.cache))
            print(f"{group} {name}: {flights[-1].time_s:.1f} s {flights[-1].energy_j / 1000:.2f} kJ", file=sys.stderr)
    for run in args.check_runs:
        try:
            flights.append(flight_of_run(run))
        except (OSError, ValueError, KeyError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    model = fit(flights)
    print(model)
    write_section(args.write, SECTION, page(flights, model, _OldModel(), args))
    print(f"wrote {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
