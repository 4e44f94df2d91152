"""Three piles in one building, measured pile by pile: the scene, the flights, the report with a density, and
the section of docs/piles.md that shows per-pile volume against its truth, the 90 % interval and the tonnage.

    python -m tools.piles_campaign [--phases 0 5 10 15] [--out runs/piles-campaign]
    python -m tools.piles_campaign --scene-only     # just write the scene (OUT/scene: STL, truths, config)

The scene (`SCENE`): a BUILDING-sized bay holding three piles of different heights built from
`sitl.world.shapes.Mesa` (a cone, a low ridge and a pile pushed against the far wall x = L), with bare floor
between them. Each pile's truth is the volume under its own height-field mesh (`volume_under_mesh`), on the
same vertex grid as the scene's STL, which is the highest of the three (they do not overlap, so the scene's
truth is their sum: checked). The flights are the real lockstep firmware payload on the JSBSim vehicle
(`sitl.runners.fly`, as `pilescan-sitl fly --stockpile scene.stl` flies it), over a few servo phases, with
ideal returns and with the LIDAR-Lite's datasheet noise. Each report is `pilescan-ground report --config
scene.toml --density ...` as a user runs it: the configuration names the piles by a point inside each and
gives each its density.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.sensor_noise import SensorNoiseModel
from firmware_py.core.storage import Storage
from ground import cli as ground_cli
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from sitl.world.shapes import MESH_RESOLUTION_M, Mesa
from sitl.world.stockpile import heightfield_mesh, volume_under_mesh
from tools.doc_sections import write_section

BUILDING = Storage(40.0, 26.0, 10.0)
ALTITUDE_M = 8.0
"""The flight height: 3 m over the tallest pile (4.5 m), the roof 2 m above."""
P_TRAJ_PCT = 20
NOISES = ("none", "datasheet")
DEFAULT_PHASES = (0, 5, 10, 15)
DEFAULT_DENSITY_KG_M3 = 1600.0
"""--density: for a pile the configuration does not name (none here: all three are named)."""
DOC = Path(__file__).resolve().parents[1] / "docs" / "piles.md"


@dataclass(frozen=True)
class ScenePile:
    """One pile of the scene: a mesa, what the configuration calls it and its material's bulk density."""

    name: str
    material: str
    density_kg_m3: float
    mesa: Mesa

    @property
    def inside_xy_m(self) -> tuple[float, float]:
        """A point inside the pile (its core's centre): how the configuration names it."""
        m = self.mesa
        return (0.5 * (m.x0 + m.x1), 0.5 * (m.y0 + m.y1))


SCENE = (
    ScenePile("sand cone", "sand", 1600.0, Mesa(9.0, 9.0, 13.0, 13.0, height_m=4.5, repose_deg=34.0)),
    ScenePile("gravel ridge", "gravel", 1750.0, Mesa(20.5, 23.5, 4.5, 7.5, height_m=2.5, repose_deg=32.0)),
    ScenePile("coal against the wall", "coal", 850.0, Mesa(33.0, 40.0, 14.0, 19.0, height_m=4.0, repose_deg=36.0)),
)
"""Bulk densities are typical handbook values for the materials (dry sand 1,600, gravel 1,750, bituminous coal
850 kg/m³): the campaign's inputs, not measured here."""


def _vertex_grid(storage: Storage) -> tuple[np.ndarray, np.ndarray]:
    nx = round(storage.length_m / MESH_RESOLUTION_M) + 1
    ny = round(storage.width_m / MESH_RESOLUTION_M) + 1
    return np.linspace(0.0, storage.length_m, nx), np.linspace(0.0, storage.width_m, ny)


def scene_heights(piles: tuple[ScenePile, ...] = SCENE, storage: Storage = BUILDING) -> list[np.ndarray]:
    """Each pile's heights on the scene's vertex grid."""
    xs, ys = _vertex_grid(storage)
    px, py = np.meshgrid(xs, ys, indexing="ij")
    return [p.mesa.heights(px, py) for p in piles]


def pile_truths_m3(piles: tuple[ScenePile, ...] = SCENE, storage: Storage = BUILDING) -> dict[str, float]:
    """Each pile's true volume: under its own mesh, on the grid the scene's STL uses."""
    xs, ys = _vertex_grid(storage)
    return {p.name: volume_under_mesh(heightfield_mesh(xs, ys, z))
            for p, z in zip(piles, scene_heights(piles, storage), strict=True)}


def write_scene(folder: Path, piles: tuple[ScenePile, ...] = SCENE, storage: Storage = BUILDING) -> dict:
    """scene.stl (the three piles), truths.json (per pile and in all) and scene.toml (the report's
    configuration: the piles by a point inside each, their densities); returns the truths."""
    folder.mkdir(parents=True, exist_ok=True)
    xs, ys = _vertex_grid(storage)
    heights = scene_heights(piles, storage)
    if (np.sum([z > 0 for z in heights], axis=0) > 1).any():
        raise ValueError("the scene's piles overlap: their truths would not add up")
    mesh = heightfield_mesh(xs, ys, np.max(heights, axis=0))
    mesh.export(folder / "scene.stl")
    truths = pile_truths_m3(piles, storage)
    total = volume_under_mesh(mesh)
    if abs(total - sum(truths.values())) > 1e-6 * total:
        raise ValueError(f"the scene's volume {total} m³ is not the sum of its piles' {sum(truths.values())} m³")
    doc = {"piles_m3": truths, "total_m3": total,
           "analytic_m3": {p.name: p.mesa.volume_m3(storage) for p in piles},
           "tops_m": {p.name: p.mesa.height_m for p in piles}}
    (folder / "truths.json").write_text(json.dumps(doc, indent=2) + "\n")
    lines = ['[site]', 'name = "Three-pile test bay (simulated)"', 'timezone = "Europe/London"',
             f"length_m = {storage.length_m}", f"width_m = {storage.width_m}", f"height_m = {storage.height_m}",
             "", "[survey]", 'operator = "pilescan piles campaign"', 'aircraft = "F450 (JSBSim)"']
    for p in piles:
        x, y = p.inside_xy_m
        lines += ["", "[[piles]]", f'name = "{p.name}"', f'material = "{p.material}"', f"x_m = {x}", f"y_m = {y}",
                  f"density_kg_m3 = {p.density_kg_m3}"]
    (folder / "scene.toml").write_text("\n".join(lines) + "\n")
    return doc


def fly_one(scene: Path, noise: str, phase: int, out: Path) -> None:
    """One lockstep flight of the scene: the firmware payload on the JSBSim vehicle."""
    mission = Mission(storage=BUILDING, p_traj=P_TRAJ_PCT / 100, altitude_m=ALTITUDE_M)
    fly(FlyConfig(mission=mission, stockpile=str(scene / "scene.stl"), payload="firmware", initial_position=phase,
                  seed=phase, sensor_noise=SensorNoiseModel(noise)), out, force=True, progress=lambda _m: None)


def report_one(run: Path, scene: Path, density_kg_m3: float) -> dict:
    """`pilescan-ground report RUN --config scene.toml --density D`, as a user runs it; its report.json."""
    code = ground_cli.main(["report", str(run), "--out", str(run / "report"), "--force", "--no-plots", "-q",
                            "--config", str(scene / "scene.toml"), "--density", f"{density_kg_m3:g}"])
    if code != 0:
        raise RuntimeError(f"pilescan-ground report {run} exited {code}")
    return json.loads((run / "report" / "report.json").read_text())


def per_pile(report: dict, truths: dict[str, float]) -> dict[str, dict]:
    """Each configured pile's measured volume, interval, mass, against its truth (None: not found)."""
    out: dict[str, dict] = {}
    for name, truth in truths.items():
        p = next((q for q in report["piles"]["piles"] if q["label"] == name), None)
        if p is None:
            out[name] = {"found": False}
            continue
        lo, hi = p["volume_interval_m3"]
        out[name] = {"found": True, "volume_m3": p["volume_m3"], "truth_m3": truth,
                     "error_pct": 100.0 * (p["volume_m3"] - truth) / truth, "interval_m3": [lo, hi],
                     "holds_truth": lo <= truth <= hi, "mass_t": p["mass_kg"] / 1000.0,
                     "true_mass_t": truth * p["density_kg_m3"] / 1000.0, "peak_m": p["peak_height_m"]}
    return out


def _stats(xs: list[float], spec: str = "+.2f") -> str:
    if not xs:
        return "-"
    return f"{statistics.median(xs):{spec}} ({min(xs):{spec}} to {max(xs):{spec}})"


def page(doc: dict, results: dict, phases: list[int], example: dict) -> str:
    """The campaign's section of docs/piles.md."""
    truths = doc["piles_m3"]
    piles = {p.name: p for p in SCENE}
    lines = [
        "### Three piles in one building (`python -m tools.piles_campaign`)",
        "",
        f"A {BUILDING.length_m:g} x {BUILDING.width_m:g} x {BUILDING.height_m:g} m bay, flown at {ALTITUDE_M:g} m "
        f"with P_traj = {P_TRAJ_PCT} % by the lockstep firmware payload on the JSBSim vehicle, servo phases "
        f"{', '.join(map(str, phases))}, with ideal returns (`none`) and the LIDAR-Lite's datasheet noise. Each "
        "report is `pilescan-ground report RUN --config scene.toml --density 1600` (the configuration names the "
        "piles by a point inside each and gives each its density; --density is for any pile it does not name). "
        "Truth per pile: the volume under that pile's own mesh (`tools/piles_campaign.py`), the scene's STL being "
        "the highest of the three.",
        "",
        "| pile | top (m) | density (kg/m³) | true volume (m³) | true mass (t) |",
        "|---|---|---|---|---|",
    ]
    for name, t in truths.items():
        p = piles[name]
        lines.append(f"| {name} | {p.mesa.height_m:g} | {p.density_kg_m3:,.0f} | {t:,.1f} | "
                     f"{t * p.density_kg_m3 / 1000:,.1f} |")
    lines += ["", "Per pile, over the flights (median, and the range):", "",
              "| pile | noise | found | volume error % | truth inside the 90 % interval | interval width (% of the "
              "volume) | mass (t) |", "|---|---|---|---|---|---|---|"]
    for name in truths:
        for noise in NOISES:
            runs = [r[name] for r in results[noise]]
            ok = [r for r in runs if r["found"]]
            widths = [100 * (r["interval_m3"][1] - r["interval_m3"][0]) / r["volume_m3"] for r in ok]
            lines.append(f"| {name} | {noise} | {len(ok)}/{len(runs)} | {_stats([r['error_pct'] for r in ok])} | "
                         f"{sum(r['holds_truth'] for r in ok)}/{len(ok)} | {_stats(widths, '.2f')} | "
                         f"{_stats([r['mass_t'] for r in ok], ',.1f')} |")
    lines += ["", f"One of them in full (noise datasheet, phase {phases[0]}): the report's pile table.", "",
              "| pile | volume (m³) | 90 % interval (m³) | truth (m³) | footprint (m²) | peak (m) | mass (t) |",
              "|---|---|---|---|---|---|---|"]
    for p in example["piles"]["piles"]:
        lo, hi = p["volume_interval_m3"]
        t = truths.get(p["label"])
        truth = "-" if t is None else f"{t:,.1f}"
        mass = "-" if p["mass_kg"] is None else f"{p['mass_kg'] / 1000:,.1f}"
        lines.append(f"| {p['label']} | {p['volume_m3']:,.1f} | {lo:,.1f} – {hi:,.1f} | {truth} | "
                     f"{p['footprint_area_m2']:,.1f} | {p['peak_height_m']:.2f} | {mass} |")
    lines += ["", f"Survey total {example['volume_m3']:,.1f} m³ (truth {doc['total_m3']:,.1f}); in the piles "
              f"{example['piles']['volume_in_piles_m3']:,.1f} m³, outside them "
              f"{example['piles']['volume_outside_piles_m3']:,.2f} m³. Verdict line: \"{example['verdict']}\"."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--phases", type=int, nargs="+", default=list(DEFAULT_PHASES))
    ap.add_argument("--out", type=Path, default=Path("runs/piles-campaign"))
    ap.add_argument("--doc", type=Path, default=DOC)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--scene-only", action="store_true")
    args = ap.parse_args(argv)
    if any(not 0 <= k < 20 for k in args.phases):
        ap.error("--phases: each servo phase must be 0..19")
    scene = args.out / "scene"
    doc = write_scene(scene)
    if args.scene_only:
        print(json.dumps(doc, indent=2))
        return 0
    results: dict[str, list[dict]] = {n: [] for n in NOISES}
    example = None
    for noise in NOISES:
        for phase in args.phases:
            run = args.out / f"{noise}-{phase}"
            fly_one(scene, noise, phase, run)
            rep = report_one(run, scene, DEFAULT_DENSITY_KG_M3)
            got = per_pile(rep, doc["piles_m3"])
            results[noise].append(got)
            if noise == "datasheet" and phase == args.phases[0]:
                example = rep
            print(f"{noise} phase {phase}: " + "; ".join(
                f"{k} {v['volume_m3']:.1f}/{v['truth_m3']:.1f} m³" if v["found"] else f"{k} not found"
                for k, v in got.items()), file=sys.stderr)
    text = page(doc, results, args.phases, example or rep)
    write_section(args.doc, "piles-campaign", text)
    if args.json:
        args.json.write_text(json.dumps({"truths": doc, "results": results}, indent=2) + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
