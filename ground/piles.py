"""Several piles in one building: the final height grid segmented into piles, each with its volume, 90 %
interval, footprint, peak, centroid and mass, in the units the reader asks for.

How a pile is found (docs/piles.md):

- **Material** is a cell higher than a threshold above the base: k = THRESHOLD_SIGMAS times the survey's
  typical point sigma (`ground.uncertainty.point_sigma_m`, from the log header's sensor model), never
  less than MIN_THRESHOLD_M. Below it a height is the floor's noise, not material: at 3 sigma one floor
  cell in 740 passes by chance, and such cells stand alone.
- **A pile** is a connected region (8-neighbour) of material cells at least `min_area_m2` in footprint
  (default DEFAULT_MIN_PILE_AREA_M2, and never fewer than MIN_PILE_CELLS cells): smaller regions are
  specks (noise, spillage) and are left out of every pile; their volume stays in the survey's total.
- **Names** come from the configuration's [[piles]] entries, each a point inside its pile: the entry
  names the pile whose region holds its point. When two entries fall in one region (two heaps grown
  together above the threshold), the region is split between them along the valley of the surface
  (a marker watershed on the height). An entry on no pile is a warning; an unnamed pile is "P1", "P2"...
  in decreasing volume.
- **Toes**: the threshold cuts a pile's foot off (a band threshold / tan(slope) wide all round, about 1 %
  of a 4 m cone's volume at a 0.25 m threshold). So each pile also takes the cells within TOE_RING of its
  region (threshold / tan(GENTLEST_REPOSE_DEG) plus one cell diagonal for the fitted surface's rounding),
  the nearest pile where two are that close; those cells' heights, floor noise included, count whole
  (noise averages out; clipping it at 0 would bias the pile up).
- **A pile's volume** is the sum of its cells' heights times the cell area (eq. (7) on its cells). The
  report gives what lies outside all piles too, so the piles and the total reconcile.
- **A pile's interval** is the survey's interval model (`ground.uncertainty.DEFAULT_INTERVAL_MODEL`)
  applied to the error terms restricted to the pile's cells (`survey_errors(mask=...)`).
- **Mass** is volume times a bulk density (kg/m³): per pile from the configuration, else `--density`.

SI always: report.json carries m³ and kg, plus the display units' values and names.
"""

from __future__ import annotations

import csv
import enum
import heapq
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from firmware_py.core.config_file import MAX_DENSITY_KG_M3, PileEntry
from ground.surface import Grid
from ground.uncertainty import DEFAULT_INTERVAL_MODEL, IntervalModel, SurveyErrors, widened_interval_m3

THRESHOLD_SIGMAS = 3.0
"""Material is a cell this many point sigmas above the base (one floor cell in 740 passes by chance)."""
MIN_THRESHOLD_M = 0.05
"""The least threshold, whatever the sensor: a layer thinner than 5 cm is spillage, not a pile."""
DEFAULT_MIN_PILE_AREA_M2 = 1.0
"""The least footprint of a pile: a square metre, about what one loader bucket leaves on the floor."""
MIN_PILE_CELLS = 4
"""Never fewer cells than this, whatever the cell size: one or two noisy cells are not a pile."""
M3_PER_YD3 = 0.9144**3
"""The international yard is exactly 0.9144 m."""
KG_PER_SHORT_TON = 907.18474
"""The US short ton is exactly 2,000 lb of 0.45359237 kg."""
KG_PER_TONNE = 1000.0
PILES_CSV = "piles.csv"
GENTLEST_REPOSE_DEG = 25.0
"""The gentlest angle of repose of loose bulk material (wet fines, some grains: 25-30 deg; sand, gravel,
coal, ores 30-45): a pile's toe below the threshold is at most threshold / tan(25 deg) wide."""


def toe_ring_m(threshold: float, grid: Grid) -> float:
    """How far beyond its thresholded region a pile's toe may reach (module docstring)."""
    diagonal = math.hypot(grid.length_m / grid.shape[0], grid.width_m / grid.shape[1])
    return threshold / math.tan(math.radians(GENTLEST_REPOSE_DEG)) + diagonal


def with_toes(labels: np.ndarray, grid: Grid, ring_m: float) -> np.ndarray:
    """labels with every unlabelled cell within ring_m of a pile given to its nearest pile."""
    if not (labels > 0).any() or ring_m <= 0:
        return labels
    c = grid.length_m / grid.shape[0], grid.width_m / grid.shape[1]
    d, (ix, iy) = ndimage.distance_transform_edt(labels == 0, sampling=c, return_indices=True)
    return np.where((labels == 0) & (d <= ring_m), labels[ix, iy], labels)


class VolumeUnit(enum.Enum):
    """How the report shows volumes (report.json keeps m³ too)."""

    M3 = "m3"
    YD3 = "yd3"

    @property
    def m3_per_unit(self) -> float:
        return {VolumeUnit.M3: 1.0, VolumeUnit.YD3: M3_PER_YD3}[self]

    @property
    def symbol(self) -> str:
        return {VolumeUnit.M3: "m³", VolumeUnit.YD3: "yd³"}[self]

    def of_m3(self, v_m3: float) -> float:
        return v_m3 / self.m3_per_unit


class MassUnit(enum.Enum):
    """How the report shows masses (report.json keeps kg too)."""

    TONNE = "t"
    SHORT_TON = "short-ton"

    @property
    def kg_per_unit(self) -> float:
        return {MassUnit.TONNE: KG_PER_TONNE, MassUnit.SHORT_TON: KG_PER_SHORT_TON}[self]

    @property
    def symbol(self) -> str:
        return {MassUnit.TONNE: "t", MassUnit.SHORT_TON: "short tons"}[self]

    def of_kg(self, m_kg: float) -> float:
        return m_kg / self.kg_per_unit


@dataclass(frozen=True)
class PileOptions:
    """What the user says about the piles: names and densities ([[piles]]), a density for all, units."""

    entries: tuple[PileEntry, ...] = ()
    density_kg_m3: float | None = None  # --density: for every pile without its own
    min_area_m2: float = DEFAULT_MIN_PILE_AREA_M2
    volume_unit: VolumeUnit = VolumeUnit.M3
    mass_unit: MassUnit = MassUnit.TONNE

    def __post_init__(self) -> None:
        d = self.density_kg_m3
        if d is not None and not (math.isfinite(d) and 0 < d <= MAX_DENSITY_KG_M3):
            raise ValueError(f"the density must be in (0, {MAX_DENSITY_KG_M3:g}] kg/m³, got {d:g}")
        if not (math.isfinite(self.min_area_m2) and self.min_area_m2 >= 0):
            raise ValueError(f"the least pile area must be a finite number of m² >= 0, got {self.min_area_m2:g}")


def threshold_m(point_sigma_m: float) -> float:
    """The height above the base a cell needs to count as material (module docstring)."""
    s = point_sigma_m if math.isfinite(point_sigma_m) and point_sigma_m > 0 else 0.0
    return max(THRESHOLD_SIGMAS * s, MIN_THRESHOLD_M)


_EIGHT = np.ones((3, 3), dtype=bool)


def least_cells(grid: Grid, min_area_m2: float) -> int:
    """A pile's least size in cells: min_area_m2 of them, and never fewer than MIN_PILE_CELLS."""
    return max(MIN_PILE_CELLS, math.ceil(min_area_m2 / grid.cell_area_m2 - 1e-9))


def segment(heights: np.ndarray, grid: Grid, threshold: float, min_area_m2: float) -> np.ndarray:
    """(nx, ny) int labels: 0 no pile, 1..n the piles in decreasing volume. NaN heights are no material."""
    h = np.nan_to_num(np.asarray(heights, dtype=float), nan=0.0)
    labels, n = ndimage.label(h > threshold, structure=_EIGHT)
    if n == 0:
        return labels
    idx = np.arange(1, n + 1)
    cells = ndimage.sum(np.ones_like(h), labels, idx)
    least = least_cells(grid, min_area_m2)
    volume = ndimage.sum(h, labels, idx)
    keep = [int(i) for i in idx[np.argsort(-volume, kind="stable")] if cells[i - 1] >= least]
    out = np.zeros_like(labels)
    for new, old in enumerate(keep, start=1):
        out[labels == old] = new
    return out


def _cell_of(x_m: float, y_m: float, grid: Grid) -> tuple[int, int] | None:
    nx, ny = grid.shape
    if not (0 <= x_m <= grid.length_m and 0 <= y_m <= grid.width_m):
        return None
    return min(nx - 1, int(x_m / grid.length_m * nx)), min(ny - 1, int(y_m / grid.width_m * ny))


def split_at_valleys(region: np.ndarray, heights: np.ndarray, seeds: Sequence[tuple[int, int]]) -> np.ndarray:
    """One region's cells shared among seeds (cells inside it) along the surface's valleys: a marker
    watershed, flooding down from the seeds, highest cell first, each cell taking the label of the
    neighbour that reached it. Returns (nx, ny) int: 0 outside the region, i + 1 for seed i's part."""
    region = np.asarray(region, bool)
    h = np.nan_to_num(np.asarray(heights, float), nan=0.0)
    nx, ny = region.shape
    out = np.zeros(region.shape, dtype=np.int32)
    queue: list[tuple[float, int, int, int]] = []
    order = 0
    for i, (ix, iy) in enumerate(seeds, start=1):
        if region[ix, iy] and out[ix, iy] == 0:
            out[ix, iy] = i
            heapq.heappush(queue, (-h[ix, iy], order, ix, iy))
            order += 1
    while queue:
        level, _, ix, iy = heapq.heappop(queue)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                jx, jy = ix + dx, iy + dy
                if 0 <= jx < nx and 0 <= jy < ny and region[jx, jy] and out[jx, jy] == 0:
                    out[jx, jy] = out[ix, iy]
                    # never higher than the pass it came over: a cell past a valley floods at the valley's level
                    heapq.heappush(queue, (max(-h[jx, jy], level), order, jx, jy))
                    order += 1
    return out


@dataclass(frozen=True)
class Assignment:
    """The piles found, the configuration entry naming each (None: unnamed) and the warnings."""

    labels: np.ndarray  # (nx, ny) 0 no pile, i the i-th pile (1-based)
    entries: tuple[PileEntry | None, ...]
    warnings: tuple[str, ...] = ()


def assign(labels: np.ndarray, heights: np.ndarray, grid: Grid, entries: Sequence[PileEntry],
           relief_m: float = 0.0, least_n: int = 1) -> Assignment:
    """Match configuration entries to the piles by their points; split a pile two entries share. relief_m: how far
    a part's summit must rise above its pass to another part to be a pile of its own (below it the split is
    warned: it follows no valley). least_n: a pile's least size in cells (`least_cells`); an entry whose part of a split
    would be smaller is not a pile of its own (warned, not reported), and its cells go to the other parts."""
    n = int(labels.max()) if labels.size else 0
    by_pile: dict[int, list[tuple[PileEntry, tuple[int, int]]]] = {}
    warnings = []
    for e in entries:
        cell = _cell_of(float(e.x_m), float(e.y_m), grid)  # type: ignore[arg-type]
        k = 0 if cell is None else int(labels[cell])
        if k == 0:
            warnings.append(f"configured pile {e.name!r} at x {e.x_m:g} m, y {e.y_m:g} m is on no pile the survey "
                            f"found{_nearest(labels, grid, e)}: not reported (moved, used up, or the point is off)")
            continue
        by_pile.setdefault(k, []).append((e, cell))  # type: ignore[arg-type]
    out = np.zeros_like(labels)
    named: list[PileEntry | None] = []
    for k in range(1, n + 1):
        mine = by_pile.get(k, [])
        if len(mine) <= 1:
            out[labels == k] = len(named) + 1
            named.append(mine[0][0] if mine else None)
            continue
        parts = split_at_valleys(labels == k, heights, [c for _, c in mine])
        while len(mine) > 1:  # a part smaller than a pile (a point on the flank, off its own heap) is no pile
            sizes = [int((parts == i).sum()) for i in range(1, len(mine) + 1)]
            small = [i for i, n_cells in enumerate(sizes) if 0 < n_cells < least_n]
            if not small:
                break
            i = min(small, key=lambda j: sizes[j])
            e = mine[i][0]
            warnings.append(f"configured pile {e.name!r} would take only {sizes[i] * grid.cell_area_m2:.1f} m² of the "
                            "pile it shares, less than a pile's least size: not reported (its point is on another "
                            "pile's flank; move it onto its own heap)")
            mine = mine[:i] + mine[i + 1:]
            parts = split_at_valleys(labels == k, heights, [c for _, c in mine])
        if len(mine) == 1:
            out[labels == k] = len(named) + 1
            named.append(mine[0][0])
            continue
        for i, (e, _) in enumerate(mine, start=1):
            if not (parts == i).any():  # its point's cell was another entry's seed
                first = next(o for o, c in mine if c == mine[i - 1][1])
                warnings.append(f"configured piles {first.name!r} and {e.name!r} point at the same cell: "
                                f"{e.name!r} not reported (move its point onto its own pile)")
                continue
            out[parts == i] = len(named) + 1
            named.append(e)
        split = [(i, e) for i, (e, _) in enumerate(mine, start=1) if (parts == i).any()]
        if len(split) < 2:
            continue
        warnings.append(f"one connected pile holds the configured piles {', '.join(repr(e.name) for _, e in split)}: "
                        "split between them along the surface's valley")
        flat = [e.name for i, e in split if not _has_summit(parts, i, heights, relief_m)]
        if flat:
            warnings.append(f"the part of configured pile(s) {', '.join(map(repr, flat))} has no summit of its own "
                            f"(none rises {relief_m:.2f} m above its pass to the next part): the split follows no "
                            "valley, so check that those points are on separate piles")
    return Assignment(out, tuple(named), tuple(warnings))


def _has_summit(parts: np.ndarray, i: int, heights: np.ndarray, relief_m: float) -> bool:
    """Whether part i's highest cell rises more than relief_m above the highest of its cells beside another part
    (its pass): a pile of its own, not a flank cut from its neighbour's."""
    h = np.nan_to_num(np.asarray(heights, float), nan=0.0)
    mine = parts == i
    beside = mine & ndimage.binary_dilation((parts > 0) & ~mine, structure=_EIGHT)
    return not beside.any() or float(h[mine].max()) - float(h[beside].max()) > relief_m


def _nearest(labels: np.ndarray, grid: Grid, e: PileEntry) -> str:
    if not (labels > 0).any():
        return ""
    c = grid.length_m / grid.shape[0], grid.width_m / grid.shape[1]
    ix, iy = np.nonzero(labels > 0)
    d = np.hypot((ix + 0.5) * c[0] - e.x_m, (iy + 0.5) * c[1] - e.y_m)  # type: ignore[operator]
    return f" (the nearest pile's edge is {float(d.min()):.1f} m away)"


def find_piles(heights: np.ndarray, grid: Grid, point_sigma_m: float, opts: PileOptions) -> Assignment:
    """The piles on the height grid (module docstring): segmented, named from the configuration, each with its toe.
    The pile table's cells, and the outlines the site map draws (the same call, the same cells)."""
    thr = threshold_m(point_sigma_m)
    found = assign(segment(heights, grid, thr, opts.min_area_m2), heights, grid, opts.entries, thr,
                   least_cells(grid, opts.min_area_m2))
    return Assignment(with_toes(found.labels, grid, toe_ring_m(thr, grid)), found.entries, found.warnings)


def pile_table(heights: np.ndarray, grid: Grid, point_sigma_m: float, opts: PileOptions,
               errors_in: Callable[[np.ndarray], SurveyErrors] | None,
               model: IntervalModel = DEFAULT_INTERVAL_MODEL, *, over: str = "the floor z = 0",
               extra_over: Callable[[np.ndarray], float] | None = None,
               found: Assignment | None = None) -> dict[str, Any]:
    """The report's ``piles`` record: how they were found, each pile, and what lies outside them.

    heights: above the base the piles are measured over (`over` names it); errors_in: the survey's error terms
    over a cell mask (None: no intervals); extra_over: the base's own 90 % half-width over a mask (a fitted
    floor's), added to each pile's interval in quadrature as the survey's interval adds it. found: the piles
    `find_piles` found on these heights (None: found here)."""
    thr = threshold_m(point_sigma_m)
    ring = toe_ring_m(thr, grid)
    found = found if found is not None else find_piles(heights, grid, point_sigma_m, opts)
    h = np.nan_to_num(np.asarray(heights, float), nan=0.0)
    a = grid.cell_area_m2
    cx, cy = grid.length_m / grid.shape[0], grid.width_m / grid.shape[1]
    piles = []
    unnamed = 0
    warnings = list(found.warnings)
    for i, entry in enumerate(found.entries, start=1):
        mask = found.labels == i
        if entry is None:
            unnamed += 1
        v = float(h[mask].sum() * a)
        ix, iy = np.nonzero(mask)
        w = np.clip(h[mask], 0.0, None)
        wsum = float(w.sum()) or 1.0
        peak = int(np.argmax(h[mask]))
        interval = None
        terms = None
        if errors_in is not None:
            t = errors_in(mask).terms
            terms = t.as_dict()
            if extra_over is None:
                interval = list(model.interval_m3(v, t))
            else:  # as ground.base.Base.interval_m3 widens the survey's interval by the base's own error
                e = extra_over(mask)
                interval = list(widened_interval_m3(v, *model.half_widths_m3(t), e, e))
        density = entry.density_kg_m3 if entry is not None and entry.density_kg_m3 is not None else opts.density_kg_m3
        if density is None and entry is not None and opts.entries:
            warnings.append(f"pile {entry.name!r} has no density ([[piles]] density_kg_m3 or --density): no mass")
        rec = {
            "label": entry.name if entry is not None else f"P{unnamed}",
            "configured": entry is not None,
            "material": None if entry is None else entry.material,
            "volume_m3": v,
            "volume_interval_m3": interval,
            "interval_terms_m3": terms,
            "footprint_area_m2": float(mask.sum() * a),
            "peak_height_m": float(h[mask].max()),
            "peak_xy_m": [float((ix[peak] + 0.5) * cx), float((iy[peak] + 0.5) * cy)],
            "centroid_xy_m": [float(((ix + 0.5) * cx * w).sum() / wsum), float(((iy + 0.5) * cy * w).sum() / wsum)],
            "extent_m": {"x": [float(ix.min() * cx), float((ix.max() + 1) * cx)],
                         "y": [float(iy.min() * cy), float((iy.max() + 1) * cy)]},
            "density_kg_m3": density,
            "mass_kg": None if density is None else v * density,
            "mass_interval_kg": None if density is None or interval is None else [x * density for x in interval],
        }
        rec["display"] = display_values(rec, opts.volume_unit, opts.mass_unit)
        piles.append(rec)
    in_piles = float(sum(p["volume_m3"] for p in piles))
    total = float(h.sum() * a)
    return {
        "method": f"connected regions (8-neighbour) of cells more than {thr:.3f} m up "
                  f"({THRESHOLD_SIGMAS:g} x the point sigma {point_sigma_m:.3f} m, at least {MIN_THRESHOLD_M:g} m), "
                  f"at least {opts.min_area_m2:g} m² and {MIN_PILE_CELLS} cells, each with its toe: the cells within "
                  f"{ring:.2f} m of it; measured over {over}",
        "threshold_m": thr,
        "toe_ring_m": ring,
        "min_area_m2": opts.min_area_m2,
        "volume_unit": opts.volume_unit.value,
        "mass_unit": opts.mass_unit.value,
        "n_piles": len(piles),
        "piles": piles,
        "over": over,
        "volume_in_piles_m3": in_piles,
        "volume_outside_piles_m3": total - in_piles,
        "volume_all_m3": total,
        "warnings": warnings,
    }


def display_values(p: Mapping[str, Any], vu: VolumeUnit, mu: MassUnit) -> dict[str, Any]:
    """A pile's volume and mass in the display units (None stays None)."""
    def vol(x: float | None) -> float | None:
        return None if x is None else vu.of_m3(x)

    def mass(x: float | None) -> float | None:
        return None if x is None else mu.of_kg(x)
    iv, im = p.get("volume_interval_m3"), p.get("mass_interval_kg")
    return {"volume": vol(p["volume_m3"]), "volume_interval": None if iv is None else [vol(x) for x in iv],
            "volume_unit": vu.value, "mass": mass(p.get("mass_kg")),
            "mass_interval": None if im is None else [mass(x) for x in im], "mass_unit": mu.value}


# ----- the CSV and the tables ------------------------------------------------------------------------------


def csv_columns(vu: VolumeUnit, mu: MassUnit) -> list[str]:
    """The header row: units in the column names (SI columns always, display columns when they differ)."""
    cols = ["label", "material", "volume_m3", "volume_low_m3", "volume_high_m3", "footprint_area_m2",
            "peak_height_m", "centroid_x_m", "centroid_y_m", "density_kg_m3", "mass_kg", "mass_low_kg",
            "mass_high_kg"]
    if vu is not VolumeUnit.M3:
        cols += [f"volume_{vu.value}", f"volume_low_{vu.value}", f"volume_high_{vu.value}"]
    cols += [f"mass_{mu.value}", f"mass_low_{mu.value}", f"mass_high_{mu.value}"]
    return cols


def write_piles_csv(table: Mapping[str, Any], path: Path) -> Path:
    """piles.csv: one row per pile (csv module; empty cells for what is unknown)."""
    vu, mu = VolumeUnit(table["volume_unit"]), MassUnit(table["mass_unit"])
    cols = csv_columns(vu, mu)

    def pair(v: Sequence[float] | None) -> tuple[Any, Any]:
        return ("", "") if v is None else (v[0], v[1])
    with path.open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for p in table["piles"]:
            d = p["display"]
            row = [p["label"], p["material"] or "", p["volume_m3"], *pair(p["volume_interval_m3"]),
                   p["footprint_area_m2"], p["peak_height_m"], *p["centroid_xy_m"],
                   "" if p["density_kg_m3"] is None else p["density_kg_m3"],
                   "" if p["mass_kg"] is None else p["mass_kg"], *pair(p["mass_interval_kg"])]
            if vu is not VolumeUnit.M3:
                row += [d["volume"], *pair(d["volume_interval"])]
            row += ["" if d["mass"] is None else d["mass"], *pair(d["mass_interval"])]
            w.writerow(row)
    return path


def _num(v: float | None, spec: str = ",.1f") -> str:
    return "-" if v is None else f"{v:{spec}}"


def pile_rows(table: Mapping[str, Any] | None) -> tuple[list[str], list[list[str]]]:
    """The report's pile table (header, rows) in the display units, for the console, Markdown and HTML."""
    if not isinstance(table, Mapping) or not table.get("piles"):
        return [], []
    try:
        vu, mu = VolumeUnit(table["volume_unit"]), MassUnit(table["mass_unit"])
    except (KeyError, ValueError):
        vu, mu = VolumeUnit.M3, MassUnit.TONNE
    head = ["Pile", "Material", f"Volume ({vu.symbol})", f"90 % interval ({vu.symbol})", "Footprint (m²)",
            "Peak (m)", "Centroid x, y (m)", "Density (kg/m³)", f"Mass ({mu.symbol})", f"90 % interval ({mu.symbol})"]
    rows = []
    for p in table["piles"]:
        d = p.get("display") or display_values(p, vu, mu)
        iv, im = d.get("volume_interval"), d.get("mass_interval")
        rows.append([str(p["label"]), p.get("material") or "-", _num(d["volume"]),
                     "-" if iv is None else f"{iv[0]:,.1f} – {iv[1]:,.1f}", _num(p["footprint_area_m2"]),
                     _num(p["peak_height_m"], ".2f"), f"{p['centroid_xy_m'][0]:.1f}, {p['centroid_xy_m'][1]:.1f}",
                     _num(p.get("density_kg_m3"), ",.0f"), _num(d.get("mass")),
                     "-" if im is None else f"{im[0]:,.1f} – {im[1]:,.1f}"])
    return head, rows


def piles_note(table: Mapping[str, Any] | None) -> str | None:
    """The sentence under the pile table that reconciles it with the survey: what the piles hold, what lies
    outside them (specks below a pile's size, and the floor's noise, which sums with its sign), the sum, and the
    base they are measured over."""
    if not isinstance(table, Mapping) or not table.get("piles"):
        return None
    try:
        vu = VolumeUnit(table["volume_unit"])
        inside, outside = float(table["volume_in_piles_m3"]), float(table["volume_outside_piles_m3"])
    except (KeyError, TypeError, ValueError):
        return None
    over = table.get("over") or "the floor z = 0"
    n = len(table["piles"])
    return (f"The {'pile holds' if n == 1 else f'{n} piles hold'} {vu.of_m3(inside):,.1f} {vu.symbol} and "
            f"{vu.of_m3(outside):,.1f} {vu.symbol} lies outside {'it' if n == 1 else 'them'} (specks smaller than a "
            f"pile, and the floor's noise, summed with its sign): {vu.of_m3(inside + outside):,.1f} {vu.symbol} in "
            f"all over {over}.")
