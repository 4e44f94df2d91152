"""Change per pile between two surveys of one building (`pilescan-ground compare`'s per-pile records).

Both surfaces are segmented into piles the way the report does it (`ground.piles.segment`: cells above a
threshold from the surfaces' noise, connected, with a minimum area), the threshold the larger of the two
surveys' so that a pile is the same kind of thing in both. Piles are matched by the cells they share:
the pairs with the most common cells first, each pile used once. A matched pair's change is NEW - OLD
summed over the union of its two footprints (material taken off a flank counts even where the new pile no
longer reaches); a pile in one survey only is reported as new or gone, with its whole volume as the change,
when that change is outside its own interval of zero (else it may be the fills' noise: a speck by a wall).

The interval of a pile's change is the survey-wide net interval's half-widths scaled by the square root of
the pile's share of the compared cells: the errors are sums over cells, and the share that lies under one
pile is what that pile's change carries. It is an approximation (the unseen and interpolation errors sit
where the piles are, not uniformly), stated as such in the design notes.
"""

from __future__ import annotations

import math

import numpy as np

from ground.compare import Change
from ground.piles import DEFAULT_MIN_PILE_AREA_M2, segment, threshold_m
from ground.render import signless_zero
from ground.surface_file import SavedSurface, resampled


def _centroid(mask: np.ndarray, weight: np.ndarray, change: Change) -> list[float]:
    cx, cy = change.grid.centres()
    w = np.where(mask, np.clip(np.nan_to_num(weight), 0.0, None), 0.0)
    if w.sum() <= 0:
        w = mask.astype(float)
    return [round(float((cx * w).sum() / w.sum()), 2), round(float((cy * w).sum() / w.sum()), 2)]


def pile_changes(old: SavedSurface, new: SavedSurface, change: Change,
                 min_area_m2: float = DEFAULT_MIN_PILE_AREA_M2) -> list[dict]:
    """One record per pile of either survey (module docstring), matched pairs first by volume."""
    grid = change.grid
    old_h, new_h = resampled(old, grid), new.heights_m
    threshold = max(threshold_m(old.scatter_sigma_m), threshold_m(new.scatter_sigma_m))
    lo, ln = segment(old_h, grid, threshold, min_area_m2), segment(new_h, grid, threshold, min_area_m2)
    a = grid.cell_area_m2
    pairs = []
    for i in range(1, int(lo.max()) + 1):
        for j in np.unique(ln[(lo == i) & (ln > 0)]):
            pairs.append((int(((lo == i) & (ln == j)).sum()), i, int(j)))
    used_old, used_new, matched = set(), set(), []
    for _, i, j in sorted(pairs, reverse=True):
        if i not in used_old and j not in used_new:
            used_old.add(i)
            used_new.add(j)
            matched.append((i, j))
    n = max(1.0, change.compared_area_m2 / a)
    net_lo, net_hi = change.net_m3 - change.net_interval_m3[0], change.net_interval_m3[1] - change.net_m3
    diff = np.nan_to_num(change.diff_m, nan=0.0)

    def record(i: int | None, j: int | None) -> dict:
        in_old = lo == i if i else np.zeros(grid.shape, bool)
        in_new = ln == j if j else np.zeros(grid.shape, bool)
        region = in_old | in_new
        v_old = float(np.nansum(np.where(in_old, old_h, 0.0)) * a) if i else None
        v_new = float(np.nansum(np.where(in_new, new_h, 0.0)) * a) if j else None
        if i and j:
            d, status = float(diff[region].sum() * a), "matched"
        else:
            d, status = (v_new if j else -v_old), ("new" if j else "gone")
        k = math.sqrt(region.sum() / n)
        return {"status": status, "old_pile": f"P{i}" if i else None, "new_pile": f"P{j}" if j else None,
                "centroid_m": _centroid(in_new if j else in_old, new_h if j else old_h, change),
                "old_volume_m3": v_old, "new_volume_m3": v_new, "change_m3": d,
                "change_interval_m3": [d - k * net_lo, d + k * net_hi],
                "footprint_m2": float(region.sum() * a)}

    out = [record(i, j) for i, j in matched]
    unmatched = [record(None, j) for j in range(1, int(ln.max()) + 1) if j not in used_new]
    unmatched += [record(i, None) for i in range(1, int(lo.max()) + 1) if i not in used_old]
    return out + [r for r in unmatched if _significant(r)]


def _significant(r: dict) -> bool:
    """A pile in one survey only whose whole volume lies within its own interval of zero could be the two
    fills' noise (a speck along a wall): not reported as a pile brought in or taken away."""
    lo, hi = r["change_interval_m3"]
    return not lo <= 0.0 <= hi


def format_pile_changes(records: list[dict] | None) -> list[str]:
    """Console lines, one per pile."""
    lines = []
    for r in records or []:
        name = f"{r['old_pile'] or '-'} -> {r['new_pile'] or '-'}"
        lo, hi = r["change_interval_m3"]
        x, y = r["centroid_m"]
        change, lo, hi = (signless_zero(u, ".1f") for u in (r["change_m3"], lo, hi))
        lines.append(f"pile {name:<10} at ({x:.1f}, {y:.1f}) m  {r['status']:<7} change {change:+10,.1f} m³ "
                     f"(90 % interval {lo:,.1f} to {hi:,.1f})")
    return lines
