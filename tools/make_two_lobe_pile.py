"""Make the two-lobe test pile (`tests/data/two_lobe_pile.stl`): a pile unlike the paper's generator, for a
30 x 20 x 10 m bay, sized for the TFMini's lower flight (top 6 m: 3 m under a 9 m flight).

Two heaps of different heights side by side with a saddle between them, as a bay fed by two conveyor
drops looks: each lobe a cone at a material's angle of repose (about 35 deg: tan 0.7) with a rounded
top, its footprint made irregular by a few low harmonics of the direction; the pile is the higher of
the two lobes at each point (they merge into a saddle). An open height field over the floor at 0.5 m,
floor-only triangles left out (the floor is the building's).

    python -m tools.make_two_lobe_pile [--out tests/data/two_lobe_pile.stl]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import trimesh

from firmware_py.core.storage import Storage
from sitl.world.stockpile import heightfield_mesh

STORAGE = Storage(30.0, 20.0, 10.0)
CELL_M = 0.5
REPOSE_SLOPE = 0.7  # tan(35 deg)
TOP_ROUND_M = 1.5  # the top is rounded over this many metres of height
LOBES = (  # centre x, y (m), height (m), footprint stretch along x, harmonic phases
    (10.0, 9.0, 6.0, 1.3, (0.4, 1.9)),
    (21.0, 11.5, 4.5, 0.9, (2.2, 0.7)),
)
DEFAULT_OUT = Path(__file__).resolve().parents[1] / "tests" / "data" / "two_lobe_pile.stl"


def lobe_height(x: np.ndarray, y: np.ndarray, cx: float, cy: float, top_m: float, stretch: float,
                phases: tuple[float, float]) -> np.ndarray:
    """One heap: a cone at the angle of repose about (cx, cy), its radius varying with direction."""
    dx, dy = (x - cx) / stretch, y - cy
    theta = np.arctan2(dy, dx)
    r = np.hypot(dx, dy) / (1.0 + 0.12 * np.sin(2 * theta + phases[0]) + 0.08 * np.sin(3 * theta + phases[1]))
    # A parabolic cap over the top TOP_ROUND_M, meeting the cone below it with the same slope.
    r_join = 2 * TOP_ROUND_M / REPOSE_SLOPE
    a = REPOSE_SLOPE ** 2 / (4 * TOP_ROUND_M)
    z = np.where(r < r_join, top_m - a * r ** 2, top_m - TOP_ROUND_M - REPOSE_SLOPE * (r - r_join))
    return np.clip(z, 0.0, None)


def two_lobe_mesh(cell_m: float = CELL_M) -> trimesh.Trimesh:
    xs = np.linspace(0.0, STORAGE.length_m, round(STORAGE.length_m / cell_m) + 1)
    ys = np.linspace(0.0, STORAGE.width_m, round(STORAGE.width_m / cell_m) + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    z = np.max([lobe_height(gx, gy, cx, cy, h, s, ph) for cx, cy, h, s, ph in LOBES], axis=0)
    mesh = heightfield_mesh(xs, ys, z)
    on_floor = (mesh.vertices[mesh.faces][:, :, 2] <= 0.0).all(axis=1)
    mesh.update_faces(~on_floor)
    mesh.remove_unreferenced_vertices()
    return mesh


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)
    mesh = two_lobe_mesh()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(args.out)
    print(f"{args.out}: {len(mesh.faces)} triangles, top {mesh.vertices[:, 2].max():.2f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
