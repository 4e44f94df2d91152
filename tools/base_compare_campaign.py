"""Base surfaces and `compare` on flown surveys: a sloped floor and a scooped pile 1 (docs/base_and_compare.md).

1. **Sloped floor.** The paper's pile 1 on a floor that falls 1.5 % (towards the building's origin corner,
   at FALL_AZIMUTH_DEG from its length): one STL, the floor slab and the pile as one height field over the
   whole building, so the ray tracer sees the sloped floor wherever the pile leaves it bare. The plane is
   added at the mesh's vertices and the mesh interpolates linearly, so the material above the sloped floor
   is exactly pile 1's volume. Flown with JSBSim and reported with `--base floor` and `--base fitted-floor`.
2. **Compare.** Pile 1, and pile 1 with a scoop taken out (every vertex inside SCOOP's footprint lowered to
   at most its cut height: a loader's bite out of the pile's flank). The removed volume is the difference of
   the two meshes' exact volumes (`sitl.world.stockpile.volume_under_mesh` on the trimesh meshes flown).
   Both flown, reported, and `pilescan-ground compare OLD NEW` run on the two reports.

    python -m tools.base_compare_campaign [--runs runs/base_compare] [--doc docs/base_and_compare.md]

Runs already in --runs are reused (delete them to fly again). The flights use the datasheet sensor noise
so the fitted floor's thresholds come from a noise model that is not zero.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from firmware_py.core.storage import Storage
from sitl.world.shapes import Family, make_shape
from sitl.world.stockpile import paper_pile, volume_under_mesh

ROOT = Path(__file__).resolve().parents[1]
FALL_PCT = 1.5
"""The floor's fall: 1-2 % is what warehouse floors are laid to for drainage."""
FALL_AZIMUTH_DEG = 30.0
"""Direction the floor rises in, from the building's x axis towards y (it falls towards the origin corner)."""


@dataclass(frozen=True)
class Scoop:
    """Material above cut_m inside the footprint is taken away."""

    x_m: tuple[float, float] = (34.0, 46.0)
    y_m: tuple[float, float] = (22.0, 34.0)
    cut_m: float = 3.0


SCOOP = Scoop()
CONES = (Family.SEPARATE, 0, 8.0)
"""Bare floor between piles: four cones (`sitl.world.shapes.separate`, seed 0, tops under 8 m: a 12 m flight)."""


def floor_rise(x: np.ndarray, y: np.ndarray, fall_pct: float = FALL_PCT,
               azimuth_deg: float = FALL_AZIMUTH_DEG) -> np.ndarray:
    """Height of the sloped floor above z = 0 (0 at the origin corner, rising along the azimuth)."""
    s = fall_pct / 100.0
    a = math.radians(azimuth_deg)
    return s * math.cos(a) * x + s * math.sin(a) * y


def sloped_mesh(pile: trimesh.Trimesh) -> trimesh.Trimesh:
    v = pile.vertices.copy()
    v[:, 2] += floor_rise(v[:, 0], v[:, 1])
    return trimesh.Trimesh(v, pile.faces.copy(), process=False)


def scooped_mesh(pile: trimesh.Trimesh, scoop: Scoop = SCOOP) -> trimesh.Trimesh:
    v = pile.vertices.copy()
    inside = ((v[:, 0] >= scoop.x_m[0]) & (v[:, 0] <= scoop.x_m[1])
              & (v[:, 1] >= scoop.y_m[0]) & (v[:, 1] <= scoop.y_m[1]))
    v[inside, 2] = np.minimum(v[inside, 2], scoop.cut_m)
    return trimesh.Trimesh(v, pile.faces.copy(), process=False)


def plane_integral_m3(storage: Storage) -> float:
    """The sloped slab's volume over z = 0: the mean rise (at the floor's centre) times its area."""
    return float(floor_rise(np.array(storage.length_m / 2), np.array(storage.width_m / 2))) * storage.floor_area_m2


def make_meshes(out: Path, storage: Storage) -> dict:
    """Write pile1.stl, pile1_scooped.stl and pile1_sloped.stl; their exact volumes."""
    out.mkdir(parents=True, exist_ok=True)
    pile = paper_pile("1", storage).mesh
    family, seed, top_m = CONES
    cones = make_shape(family, storage, top_m, seed).pile.mesh
    meshes = {"pile1": pile, "pile1_scooped": scooped_mesh(pile), "pile1_sloped": sloped_mesh(pile),
              "cones": cones, "cones_sloped": sloped_mesh(cones)}
    for name, m in meshes.items():
        m.export(out / f"{name}.stl")
    v = {name: volume_under_mesh(m) for name, m in meshes.items()}
    return {
        "pile1_m3": v["pile1"],
        "scooped_m3": v["pile1_scooped"],
        "removed_m3": v["pile1"] - v["pile1_scooped"],
        "sloped_over_z0_m3": v["pile1_sloped"],
        "sloped_above_floor_m3": v["pile1_sloped"] - plane_integral_m3(storage),
        "slab_m3": plane_integral_m3(storage),
        "cones_m3": v["cones"],
        "cones_sloped_above_floor_m3": v["cones_sloped"] - plane_integral_m3(storage),
    }


def python() -> list[str]:
    return [sys.executable]


def run(cmd: list[str]) -> str:
    """Run a command from the checkout, echo it, return its stdout (a failure stops the campaign)."""
    print("$ " + " ".join(cmd[2:] if cmd[:1] == python() else cmd), flush=True)
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)})
    if res.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({res.returncode}): {res.stderr.strip()[-2000:]}")
    print(res.stdout, flush=True)
    return res.stdout


def fly(stl: Path, out: Path, seed: int) -> None:
    if (out / "truth.json").exists():
        print(f"(reusing {out})")
        return
    run([*python(), "-m", "sitl.cli", "fly", "--stockpile", str(stl), "--p-traj", "20",
         "--sensor-noise", "datasheet", "--seed", str(seed), "--out", str(out), "--force", "-q"])


def report(run_dir: Path, out: Path, base: str, truth_m3: float) -> dict:
    run([*python(), "-m", "ground.cli", "report", str(run_dir), "--out", str(out), "--base", base,
         "--truth-volume", repr(truth_m3), "--force", "--no-plots"])
    return json.loads((out / "report.json").read_text())


FLIGHTS = (  # name, mesh, seed (noise seeds differ: two flights never share their noise)
    ("cones_sloped", "cones_sloped.stl", 4),
    ("pile1_sloped", "pile1_sloped.stl", 1),
    ("pile1", "pile1.stl", 2),
    ("pile1_scooped", "pile1_scooped.stl", 3),
)


def campaign(runs: Path) -> dict:
    from sitl.world.stockpile import load_mesh
    storage = Storage()
    exact = make_meshes(runs, storage)
    # The truths from the meshes as the simulator loads them (float32 STL vertices), not the float64 originals.
    flown = {name: load_mesh(runs / stl, storage).volume_m3 for name, stl, _ in FLIGHTS}
    slab = plane_integral_m3(storage)
    truth = {"cones_sloped": flown["cones_sloped"] - slab, "pile1_sloped": flown["pile1_sloped"] - slab,
             "pile1": flown["pile1"], "pile1_scooped": flown["pile1_scooped"]}
    for name, stl, seed in FLIGHTS:
        fly(runs / stl, runs / name, seed)
    sloped = {}
    for name in ("cones_sloped", "pile1_sloped", "pile1"):  # pile1: a level floor, the control
        for base in ("floor", "fitted-floor"):
            try:
                rep = report(runs / name, runs / f"report_{name}_{base}", base, truth[name])
            except SystemExit as exc:  # a refused base is a result too
                sloped[(name, base)] = {"error": str(exc)}
                continue
            sloped[(name, base)] = rep
    for name in ("pile1", "pile1_scooped"):
        report(runs / name, runs / f"report_{name}", "floor", truth[name])
    removed = truth["pile1"] - truth["pile1_scooped"]
    run([*python(), "-m", "ground.cli", "compare", str(runs / "report_pile1"), str(runs / "report_pile1_scooped"),
         "--out", str(runs / "compare"), "--true-change", repr(-removed), "--force"])
    cmp = json.loads((runs / "compare" / "compare.json").read_text())
    # The same change measured as a report over an earlier survey's surface (--base REPORT_DIR).
    over = report(runs / "pile1_scooped", runs / "report_pile1_scooped_over_pile1", str(runs / "report_pile1"),
                  -removed)
    return {"exact": exact, "truth": truth, "removed_m3": removed, "sloped": sloped, "compare": cmp,
            "over_base": over}


def _ve(rep: dict) -> str:
    v = rep.get("volume_error_pct")
    return "-" if v is None else f"{v:.2f} %"


def page(res: dict, runs: Path) -> str:
    t = res["truth"]
    lines = [
        "Generated by `python -m tools.base_compare_campaign` (flights: `pilescan-sitl fly --plant jsbsim` (the "
        "default) with the firmware payload, `--p-traj 20 --sensor-noise datasheet`, one noise seed per flight; "
        f"runs in `{runs}`).",
        "",
        f"### Sloped floor: {FALL_PCT:g} % fall rising towards {FALL_AZIMUTH_DEG:g} deg from x",
        "",
        f"The floor slab adds {res['exact']['slab_m3']:,.1f} m³ over z = 0. The truth is the material above the "
        "sloped floor (the pile's own volume, exactly: the plane is added at the mesh's vertices). "
        "`cones_sloped`: four cones with bare floor between them; `pile1_sloped`: the paper's pile 1, which "
        "covers the floor wall to wall; `pile1`: pile 1 on the level floor (the control: a fitted floor should "
        "find z = 0).",
        "",
        "| pile | base | volume m³ | 90 % interval m³ | truth m³ | Ve | truth inside | base found |",
        "|---|---|---:|---|---:|---:|---|---|",
    ]
    centre_m = float(floor_rise(np.array(30.0), np.array(20.0)))  # the default 60 x 40 m building's centre
    for (name, base), rep in res["sloped"].items():
        if "error" in rep:
            lines.append(f"| {name} | {base} | refused | | {t[name]:,.1f} | | | {rep['error'][-200:]} |")
            continue
        lo, hi = rep["volume_interval_m3"]
        b = rep["base"]
        found = "z = 0" if b["kind"] == "floor" else (
            f"tilt {b['tilt_deg']:.2f} deg ({b['fall_pct']:.2f} % towards {b['rise_azimuth_deg']:.0f} deg), "
            f"{b['offset_at_centre_m']:+.3f} m at the centre (true {0.0 if name == 'pile1' else centre_m:+.3f}), "
            f"{b['n_floor_points']} floor points in {b['n_floor_cells']} cells")
        lines.append(f"| {name} | {base} | {rep['volume_m3']:,.1f} | {lo:,.1f} – {hi:,.1f} | {t[name]:,.1f} | "
                     f"{_ve(rep)} | {'yes' if rep['truth_in_interval'] else 'no'} | {found} |")
    c = res["compare"]
    o = res["over_base"]
    lines += [
        "",
        "### Compare: pile 1, then pile 1 with a scoop taken out",
        "",
        f"Scoop: everything above {SCOOP.cut_m:g} m inside x {SCOOP.x_m[0]:g}-{SCOOP.x_m[1]:g} m, "
        f"y {SCOOP.y_m[0]:g}-{SCOOP.y_m[1]:g} m; removed {res['removed_m3']:,.1f} m³ (the two meshes' exact "
        "volumes). `pilescan-ground compare` on the two reports:",
        "",
        "| | measured m³ | 90 % interval m³ | truth m³ |",
        "|---|---:|---|---:|",
        f"| net change | {c['net_m3']:+,.1f} | {c['net_interval_m3'][0]:+,.1f} – {c['net_interval_m3'][1]:+,.1f} | "
        f"{-res['removed_m3']:+,.1f} ({'inside' if c['truth_in_interval'] else 'outside'}) |",
        f"| cut | {c['cut_m3']:,.1f} over {c['cut_area_m2']:,.0f} m² | {c['cut_interval_m3'][0]:,.1f} – "
        f"{c['cut_interval_m3'][1]:,.1f} | {res['removed_m3']:,.1f} |",
        f"| fill | {c['fill_m3']:,.1f} over {c['fill_area_m2']:,.0f} m² | {c['fill_interval_m3'][0]:,.1f} – "
        f"{c['fill_interval_m3'][1]:,.1f} | 0 |",
        "",
        f"Level of detection {c['level_of_detection_m']:.3f} m; median change over the unchanged cells "
        f"{c['unchanged_offset_m'] * 1000:+.1f} mm. The surveys themselves: pile 1 {c['old_volume_m3']:,.1f} m³ "
        f"(truth {t['pile1']:,.1f}), scooped {c['new_volume_m3']:,.1f} m³ (truth {t['pile1_scooped']:,.1f}).",
        "",
        f"The same change as a report over the earlier survey (`--base` its report directory): "
        f"{o['volume_m3']:+,.1f} m³, 90 % interval {o['volume_interval_m3'][0]:+,.1f} – "
        f"{o['volume_interval_m3'][1]:+,.1f} m³ (truth {-res['removed_m3']:+,.1f}: "
        f"{'inside' if o['truth_in_interval'] else 'outside'}).",
        "",
        "![cut/fill](figures/base_compare_cutfill.png)",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "base_compare")
    ap.add_argument("--doc", type=Path, default=ROOT / "docs" / "base_and_compare.md")
    args = ap.parse_args(argv)
    from tools.doc_sections import write_section
    res = campaign(args.runs)
    fig = args.doc.parent / "figures" / "base_compare_cutfill.png"
    fig.parent.mkdir(parents=True, exist_ok=True)
    fig.write_bytes((args.runs / "compare" / "cutfill.png").read_bytes())
    write_section(args.doc, "base_compare_campaign", page(res, args.runs.relative_to(ROOT)
                                                          if args.runs.is_relative_to(ROOT) else args.runs))
    print(f"wrote {args.doc}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
