"""Where a survey's volume error sits: in the cells holding points, in the cells the surface bridges
between them, or in the cells the empty-cell fill invents. Paper piles 1 and 2 on the paper's baseline
mission (the noise table's cases, `tools.noise_table`), each against the pile's exact surface.

A volume error summed over the whole floor hides which step made it. Split by cell, it says whether the
estimator reads the points wrong (occupied cells), the interpolant bridges the gaps between fan lines
wrong (bridged cells), or the fill invents wrongly (filled cells). The three parts add up to Ve (signed,
percent of the true volume), apart from the exact surface's own averaging over each cell (the "grid"
column: the true cell means' volume against the mesh's). The filled cells' part is split once more: the cells within
`--wall-band-m` of a wall, where the fill meets the walls' contacts or copies the pile's edge to the wall, and the
rest (at P_traj 25-30 % most of the filled cells' error lies along the walls: docs/design-notes.md).

    python -m tools.ve_breakdown --pile 1 --p-traj 30 --models none,appendix-a --phases 0,1,2,3
    python -m tools.ve_breakdown --pile 2 --p-traj 30 --models datasheet --surface-slopes gp
"""

from __future__ import annotations

import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ArgumentParser
from firmware_py.core.sensor_noise import SensorNoiseModel
from ground.report import ReportOptions, survey_from_samples
from ground.smoothing import DEFAULT_NODE_SLOPES, NodeSlopes
from ground.surface import SURFACE_FITS, Grid
from ground.wall_strip import nearest_wall
from sitl.runners.fly import log_header
from sitl.world.stockpile import paper_pile_spec, surface_height
from tools.experiments import N_POSITIONS
from tools.noise_table import MODELS, P_TRAJ_PCT, PILES, Case, case_samples

SUBSAMPLES = 5
"""Exact heights per cell side averaged for a cell's true mean height (25 per 0.25 m cell)."""
WALL_BAND_M = 4.0
"""The filled cells within this of a wall are the "at the walls" part (the default of `--wall-band-m`): a pile's
flank meets a wall within a few metres, and a leg's sweep stops short of the walls by about that much at P_traj
25-30 % (a diagnostic's split, not an estimator's constant)."""


@dataclass(frozen=True)
class Breakdown:
    """Signed volume errors, percent of the true volume, by the kind of cell that holds them."""

    ve_pct: float
    occupied_pct: float
    bridged_pct: float
    filled_pct: float
    grid_pct: float  # the true cell means' volume against the true volume: the cells' own averaging
    filled_walls_pct: float = 0.0  # of filled_pct, the cells within the wall band (`breakdown`'s near_walls)


def true_cell_means(height, grid: Grid, sub: int = SUBSAMPLES) -> np.ndarray:
    """(nx, ny) mean exact height of each cell, from sub x sub evenly spread points in it."""
    nx, ny = grid.shape
    xe, ye = grid.x_edges, grid.y_edges
    fx = np.concatenate([np.linspace(xe[i], xe[i + 1], sub + 2)[1:-1] for i in range(nx)])
    fy = np.concatenate([np.linspace(ye[j], ye[j + 1], sub + 2)[1:-1] for j in range(ny)])
    px, py = np.meshgrid(fx, fy, indexing="ij")
    z = height(np.column_stack([px.ravel(), py.ravel()])).reshape(px.shape)
    return z.reshape(nx, sub, ny, sub).mean(axis=(1, 3))


def breakdown(heights: np.ndarray, heights_fit: np.ndarray, occupied: np.ndarray, true_means: np.ndarray,
              cell_area_m2: float, true_volume_m3: float, near_walls: np.ndarray | None = None) -> Breakdown:
    """Split a survey's error: heights (after the fill), heights_fit (NaN where the fill acted), occupied
    (cells holding a point of the pile's cloud), the true cell means; near_walls (cells within the wall band, None:
    none) splits the filled cells' part."""
    err = (np.asarray(heights, dtype=float) - true_means) * cell_area_m2
    seen = np.isfinite(heights_fit)
    pct = 100.0 / true_volume_m3
    grid_pct = (true_means.sum() * cell_area_m2 - true_volume_m3) * pct
    return Breakdown(ve_pct=float(np.nansum(err)) * pct + grid_pct,
                     occupied_pct=float(err[seen & occupied].sum()) * pct,
                     bridged_pct=float(err[seen & ~occupied].sum()) * pct,
                     filled_pct=float(np.nansum(err[~seen])) * pct, grid_pct=grid_pct,
                     filled_walls_pct=0.0 if near_walls is None else float(np.nansum(err[~seen & near_walls])) * pct)


def wall_band(grid: Grid, band_m: float = WALL_BAND_M) -> np.ndarray:
    """(nx, ny) the cells whose centres lie within band_m of a wall."""
    return nearest_wall(grid)[1] < band_m


def occupied_cells(points_w: np.ndarray, grid: Grid) -> np.ndarray:
    return grid.counts(points_w[:, :2]) > 0


def run(pile: str, p_traj_pct: int, model: SensorNoiseModel, phases: list[int], surface_fit: str,
        cache_dir: Path, surface_slopes: NodeSlopes = DEFAULT_NODE_SLOPES,
        wall_band_m: float = WALL_BAND_M) -> list[Breakdown]:
    """One breakdown per servo start position, the noise drawn as the noise table draws it (`case_samples`)."""
    out, means, band = [], None, None
    opts = ReportOptions(plots=False, surface_fit=surface_fit, surface_slopes=surface_slopes)
    for _, cfg, s, stockpile in case_samples(Case(pile, p_traj_pct, model), phases, cache_dir):
        storage = cfg.mission.storage
        sv = survey_from_samples(s, log_header(cfg, cfg.servo_waveform()), storage, cfg.frame,
                                 np.array(cfg.lever_arm_body_m), opts)
        if means is None:  # the exact surface's cell means, on the survey's grid
            means = true_cell_means(surface_height(paper_pile_spec(pile), storage), sv.grid)
            band = wall_band(sv.grid, wall_band_m)
        out.append(breakdown(sv.heights, sv.heights_fit, occupied_cells(sv.pile_points_w, sv.grid), means,
                             sv.grid.cell_area_m2, stockpile.volume_m3, band))
    return out


def table(rows: dict[str, list[Breakdown]], wall_band_m: float = WALL_BAND_M) -> str:
    def ms(v: list[float]) -> str:
        return f"{statistics.fmean(v):+.2f} ± {statistics.pstdev(v):.2f}" if len(v) > 1 else f"{v[0]:+.2f}"
    out = [f"| case | Ve [%] | occupied cells [%] | bridged cells [%] | filled cells [%] | of which within "
           f"{wall_band_m:g} m of a wall [%] | grid [%] |", "|---|---|---|---|---|---|---|"]
    for name, bs in rows.items():
        out.append(f"| {name} | {ms([b.ve_pct for b in bs])} | {ms([b.occupied_pct for b in bs])} | "
                   f"{ms([b.bridged_pct for b in bs])} | {ms([b.filled_pct for b in bs])} | "
                   f"{ms([b.filled_walls_pct for b in bs])} | {bs[0].grid_pct:+.3f} |")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.ve_breakdown", description=__doc__.split("\n\n")[0])
    ap.add_argument("--pile", choices=PILES, default="1")
    ap.add_argument("--p-traj", type=int, choices=P_TRAJ_PCT, default=30, help="percent")
    ap.add_argument("--models", default="none,appendix-a", help="comma-separated sensor-noise models")
    ap.add_argument("--phases", default="0,1,2,3", help=f"comma-separated servo start positions (0-{N_POSITIONS - 1})")
    ap.add_argument("--surface-fit", choices=SURFACE_FITS, default=ReportOptions().surface_fit)
    ap.add_argument("--surface-slopes", choices=[v.value for v in NodeSlopes], default=DEFAULT_NODE_SLOPES.value,
                    help="where the local-linear surface's cubic takes its slopes (as pilescan-ground report's)")
    ap.add_argument("--wall-band-m", type=float, default=WALL_BAND_M,
                    help="the filled cells within this of a wall are split out (m)")
    ap.add_argument("--cache", type=Path, default=Path("runs/sweep-cache"), help="flight cache")
    args = ap.parse_args(argv)
    try:
        models = [SensorNoiseModel(m) for m in args.models.split(",")]
        phases = [int(k) for k in args.phases.split(",")]
        if not all(0 <= k < N_POSITIONS for k in phases):
            raise ValueError
    except ValueError:
        ap.error(f"--models takes {', '.join(m.value for m in MODELS)}; --phases integers 0-{N_POSITIONS - 1}")
    if not (args.wall_band_m > 0 and args.wall_band_m < float("inf")):
        ap.error(f"--wall-band-m must be a distance > 0 m, got {args.wall_band_m:g}")
    rows = {}
    for model in models:
        rows[f"pile {args.pile}, P_traj {args.p_traj} %, {model.value}"] = run(
            args.pile, args.p_traj, model, phases, args.surface_fit, args.cache, NodeSlopes(args.surface_slopes),
            args.wall_band_m)
        print(f"{model.value}: done", file=sys.stderr)
    print(table(rows, args.wall_band_m))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
