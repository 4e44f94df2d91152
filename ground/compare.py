"""Change between two surveys of one building (`pilescan-ground compare OLD NEW`): a cut/fill raster, its
figure, and the net, cut and fill volumes with 90 % intervals.

**Raster.** NEW - OLD per cell of NEW's grid (OLD resampled bilinearly when its cells differ, with a
warning), NaN where either survey has no surface. Positive is fill (material added), negative is cut
(material taken away), the survey convention of ArcGIS's Cut Fill and Civil 3D's volume surfaces.

**Net.** The sum of the raster times the cell area over every cell both surveys have: signed, so the
noise of the two surfaces averages out (no level of detection applied). Its interval: the net is wrong
by NEW's volume error less OLD's. Each survey's 90 % half-widths come from its own interval terms
(`ground.surface_file`); the net's low side pairs NEW's below with OLD's above, the high side NEW's above
with OLD's below, in quadrature (independent errors). Over cells where nothing changed, the two surveys
of one pile with one mission share their errors (blur, the unseen fill, the interpolation over the same
gaps), which cancel in the difference, so the surveys' half-widths are taken over the changed cells only,
scaled by the square root of their share of the compared cells (the error of a sum over a part of
independent cells). Over the unchanged cells two things stay, both read from the raster: each cell's
independent noise (z sigma_d per cell, summed in quadrature) and any offset between the two flights (the
median change over those cells, times the compared area: a height bias of one flight).

**Cut and fill.** Summed only over cells whose change exceeds the level of detection LoD = z sigma_d,
sigma_d the two surfaces' height noise in quadrature (each the points' scatter about its surface, stored
with it) and z the interval's normal quantile (1.645 at 90 %): the usual threshold of DEM-of-difference
change detection; below it, a cell's change cannot be told from noise, and summing |change| there would
count noise as both cut and fill. Their intervals take the surveys' half-widths in proportion to the square
root of their share of the changed cells, the low side clipped at 0.

**Per pile.** Change per pile needs the piles segmented in both surveys: `ground.pile_change` does that
from the two surfaces and this module's Change; compare.json's ``per_pile`` holds its records.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from statistics import NormalDist

import numpy as np

from firmware_py.core.cli import UserError
from firmware_py.core.rundir import OutputFolder, check_free
from firmware_py.core.version import software_version
from ground.render import signless_zero
from ground.surface import Grid
from ground.surface_file import SavedSurface, building_mismatch, resampled
from ground.uncertainty import INTERVAL_LEVEL

COMPARE_FILE = "compare.json"
COMPARE_FILES = (COMPARE_FILE, "cutfill.png", "cutfill.npz")
"""Every file a compare directory holds (compare.json last: its marker)."""

Z_INTERVAL = NormalDist().inv_cdf(0.5 + INTERVAL_LEVEL / 2)
"""A normal error's half-width at the interval's level (1.645 at 90 %)."""

@dataclass(frozen=True)
class Change:
    """NEW - OLD on NEW's grid, and its volumes (module docstring)."""

    grid: Grid
    diff_m: np.ndarray  # (nx, ny), NaN where either survey has no surface
    lod_m: float
    net_m3: float
    cut_m3: float  # > 0: material taken away
    fill_m3: float
    net_interval_m3: tuple[float, float]
    cut_interval_m3: tuple[float, float]
    fill_interval_m3: tuple[float, float]
    cut_area_m2: float
    fill_area_m2: float
    compared_area_m2: float
    offset_m: float = 0.0  # the median change over the cells without detectable change
    warnings: tuple[str, ...] = ()


def compare_surfaces(old: SavedSurface, new: SavedSurface) -> Change:
    """The change from old to new (module docstring); UserError when they are not of the same building."""
    why = building_mismatch(old, new)
    if why is not None:
        raise UserError(f"cannot compare the two surveys: {why}")
    grid = new.grid
    old_h = resampled(old, grid)
    warnings = []
    if old_h is not old.heights_m:
        warnings.append(f"the old survey's {old.cell_m:g} m grid was resampled (bilinear) to the new one's "
                        f"{new.cell_m:g} m cells")
    diff = new.heights_m - old_h
    both = np.isfinite(diff)
    if not both.any():
        raise UserError("cannot compare the two surveys: no cell has a surface in both")
    missing = int((np.isfinite(new.heights_m) | np.isfinite(old_h)).sum() - both.sum())
    if missing:
        warnings.append(f"{missing} cells ({missing * grid.cell_area_m2:,.0f} m²) have a surface in only one survey: "
                        "not compared")
    a = grid.cell_area_m2
    lod = Z_INTERVAL * math.hypot(old.scatter_sigma_m, new.scatter_sigma_m)
    d = np.where(both, diff, 0.0)
    cut_cells, fill_cells = d < -lod, d > lod
    net = float(d.sum() * a)
    cut = float(-d[cut_cells].sum() * a)
    fill = float(d[fill_cells].sum() * a)
    n = int(both.sum())
    changed = cut_cells | fill_cells
    quiet = both & ~changed
    share = math.sqrt(int(changed.sum()) / n)
    offset_m = float(np.median(d[quiet])) if quiet.any() else 0.0
    # Where nothing changed, what the two surveys share cancels: left are each cell's noise (independent) and
    # any offset between the two flights (the median change there), both read off the raster itself.
    shared = math.hypot(Z_INTERVAL * math.hypot(old.scatter_sigma_m, new.scatter_sigma_m) * a * math.sqrt(quiet.sum()),
                        abs(offset_m) * n * a)
    low = math.hypot(share * math.hypot(new.below_m3, old.above_m3), shared)
    high = math.hypot(share * math.hypot(new.above_m3, old.below_m3), shared)

    def part(v: float, cells: np.ndarray, low_side: float, high_side: float) -> tuple[float, float]:
        k = math.sqrt(int(cells.sum()) / max(1, int(changed.sum())))
        return max(0.0, v - k * low_side), v + k * high_side

    # Cut is material gone: the true cut is larger when the true net is lower (the net's low side), so the
    # cut's high side takes the net's low half-width and its low side the net's high one.
    return Change(grid, np.where(both, diff, np.nan), lod, net, cut, fill, (net - low, net + high),
                  part(cut, cut_cells, high, low), part(fill, fill_cells, low, high),
                  float(cut_cells.sum() * a), float(fill_cells.sum() * a), float(n * a), offset_m, tuple(warnings))


def change_record(c: Change, old: SavedSurface, new: SavedSurface, old_src: str, new_src: str,
                  per_pile: list[dict] | None, truth_net_m3: float | None = None) -> dict:
    rec = {
        "old": old_src, "new": new_src,
        "old_volume_m3": old.volume_m3, "new_volume_m3": new.volume_m3,
        "net_m3": c.net_m3, "net_interval_m3": list(c.net_interval_m3),
        "cut_m3": c.cut_m3, "cut_interval_m3": list(c.cut_interval_m3),
        "fill_m3": c.fill_m3, "fill_interval_m3": list(c.fill_interval_m3),
        "interval_level": INTERVAL_LEVEL,
        "level_of_detection_m": c.lod_m,
        "unchanged_offset_m": c.offset_m,
        "cut_area_m2": c.cut_area_m2, "fill_area_m2": c.fill_area_m2, "compared_area_m2": c.compared_area_m2,
        "cell_size_m": c.grid.length_m / c.grid.shape[0], "cell_area_m2": c.grid.cell_area_m2,
        "per_pile": per_pile,
        "warnings": list(c.warnings),
        "software_version": software_version(),
    }
    if truth_net_m3 is not None:
        rec["true_net_m3"] = truth_net_m3
        rec["net_error_m3"] = c.net_m3 - truth_net_m3
        rec["truth_in_interval"] = c.net_interval_m3[0] <= truth_net_m3 <= c.net_interval_m3[1]
    return rec


def format_change(rec: dict) -> str:
    def v(x: float, spec: str = ",.1f") -> str:
        return f"{signless_zero(x, spec):{spec}}"

    def iv(k: str) -> str:
        lo, hi = rec[k]
        return f"(90 % interval {v(lo)} to {v(hi)} m³)"
    lines = [f"net change    {v(rec['net_m3'], '+12,.1f')} m³ {iv('net_interval_m3')}",
             f"cut           {v(rec['cut_m3'], '12,.1f')} m³ {iv('cut_interval_m3')} "
             f"over {rec['cut_area_m2']:,.0f} m²",
             f"fill          {v(rec['fill_m3'], '12,.1f')} m³ {iv('fill_interval_m3')} "
             f"over {rec['fill_area_m2']:,.0f} m²",
             f"detection     changes under {rec['level_of_detection_m']:.3f} m not counted as cut or fill"]
    if rec.get("true_net_m3") is not None:
        where = "inside" if rec["truth_in_interval"] else "OUTSIDE"
        lines.append(f"true net      {rec['true_net_m3']:+12,.1f} m³ ({where} the interval)")
    return "\n".join(lines + [f"WARNING: {w}" for w in rec["warnings"]])


def cutfill_figure(c: Change, rec: dict):
    """The cut/fill map: diverging colours (cut blue, fill red), changes under the LoD grey, no data white."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import ListedColormap, TwoSlopeNorm
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    fig = Figure(figsize=(8.0, 5.5), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    g = c.grid
    d = c.diff_m
    span = float(np.nanmax(np.abs(d))) if np.isfinite(d).any() else 1.0
    span = max(span, 2 * c.lod_m, 1e-3)
    ax.pcolormesh(g.x_edges, g.y_edges, np.where(np.isfinite(d), 1.0, np.nan).T,
                  cmap=ListedColormap(["#d9d9d9"]), shading="flat")  # compared, no detectable change
    shown = np.where(np.abs(d) > c.lod_m, d, np.nan)
    m = ax.pcolormesh(g.x_edges, g.y_edges, shown.T, cmap="RdBu_r", norm=TwoSlopeNorm(0.0, -span, span),
                      shading="flat")
    fig.colorbar(m, ax=ax, label="height change, new − old [m]")
    ax.set_xlim(0, g.length_m)
    ax.set_ylim(0, g.width_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x (building length) [m]")
    ax.set_ylabel("y (building width) [m]")
    ax.set_title(f"Cut/fill: net {rec['net_m3']:+,.1f} m³ (cut {rec['cut_m3']:,.1f}, fill {rec['fill_m3']:,.1f})")
    ax.legend(handles=[Patch(color="#2166ac", label=f"cut (removed) {rec['cut_m3']:,.1f} m³"),
                       Patch(color="#b2182b", label=f"fill (added) {rec['fill_m3']:,.1f} m³"),
                       Patch(color="#d9d9d9", label=f"no change beyond {c.lod_m * 100:.2g} cm"),
                       Patch(facecolor="white", edgecolor="0.5", label="not in both surveys")],
              loc="upper right", fontsize="small", framealpha=0.85)
    return fig


def write_compare(c: Change, rec: dict, out_dir: str | Path, *, force: bool = False) -> Path:
    """compare.json, cutfill.png and cutfill.npz (the raster and its edges), compare.json last."""
    out = check_free(out_dir, COMPARE_FILES, force=force, what="compare")
    with OutputFolder(out, COMPARE_FILES, COMPARE_FILE, force=force, what="compare") as folder:
        cutfill_figure(c, rec).savefig(folder.staged("cutfill.png"), dpi=110)
        with folder.staged("cutfill.npz").open("wb") as f:
            np.savez_compressed(f, diff_m=c.diff_m, x_edges_m=c.grid.x_edges, y_edges_m=c.grid.y_edges,
                                level_of_detection_m=np.float64(c.lod_m))
        folder.staged(COMPARE_FILE).write_text(json.dumps(rec, indent=2) + "\n")
        folder.commit()
    return out
