"""The strip of cells along a wall that no point reached: where the wall contacts contradict the fit there, unseen.

The surface fit covers the convex hull of the pile points. Along a wall the sweeps stop a few decimetres short of
it, so the row of cells against the wall holds no points, yet the hull runs along the wall from whatever the
sweeps saw at either end, and over a pile leaning on the wall long thin triangles join the floor beyond its ends to
its top one row in. Measured on the small building's bay pile (a 3.87 m prism up to the back wall): that row read
2.2 down to 0.05 m, -6.6 of the run's -8.9 m³ (docs/design-notes.md, "The wall strip"). The wall contacts
(`ground.wall_contact`) there read 3.87 m: the survey's own evidence, unused because the row was not unseen.

A cell is in a wall's *strip* when it holds no points and lies nearer that wall than any cell holding points: only
the hull's bridging decides it. Such a cell whose fitted height lies outside what the contacts either side of it
along the wall allow is taken as unseen, so the fill decides it from the points and the contacts together. What
two contacts allow, at a distance d from each: the ground may rise or fall at most `ground.unseen.MAX_SLOPE` from
each contact's bounds, and between them it may dip to the lower or rise to the higher: [min(low - S d), max(high +
S d)] over the two. The contacts' own bounds hold their noise; the fit's noise is the slack the caller gives (its
points' sigmas). A cell beyond the last contact on its wall has no pair and is left as fitted: one contact says
nothing about where the material ends (the bay pile's vertical ends). Only contacts whose material leans on the
wall as measured judge the strip (`WallContacts.measured_leaning`): under Appendix A's pointing error the leaning
test's allowance lets false contacts through, 4-8 m up a wall behind a crest, and on them the rule took fitted cells
and filled them metres high (measured: docs/design-notes.md).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ground.surface import Grid
from ground.unseen import MAX_SLOPE
from ground.wall_contact import WallContacts


def nearest_wall(grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Per cell, its nearest wall (0 x = 0, 1 x = length, 2 y = 0, 3 y = width, as `WallContacts.wall`) and the
    distance of its centre from that wall, m; (nx, ny) each."""
    x, y = grid.centres()
    dist = np.stack([x, grid.length_m - x, y, grid.width_m - y])
    wall = np.argmin(dist, axis=0)
    return wall, np.take_along_axis(dist, wall[None], axis=0)[0]


def strip_cells(counts: np.ndarray, grid: Grid) -> np.ndarray:
    """(nx, ny) True for the cells without points nearer their wall than any cell holding points (all False
    without points: there is no fit to judge)."""
    empty = np.asarray(counts) == 0
    if empty.all():
        return np.zeros(empty.shape, dtype=bool)
    to_points = ndimage.distance_transform_edt(empty, sampling=grid.cell_xy_m)
    return empty & (nearest_wall(grid)[1] < to_points)


def contact_band_m(contacts: WallContacts, grid: Grid, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) per cell: the heights the ground there may take by the contacts either side of it along its
    nearest wall (module docstring); -inf / +inf where no pair brackets it and outside `where`."""
    low, high = np.full(grid.shape, -np.inf), np.full(grid.shape, np.inf)
    wall, _ = nearest_wall(grid)
    x, y = grid.centres()
    for w in range(4):
        on = contacts.wall == w
        cells = np.asarray(where, dtype=bool) & (wall == w)
        if on.sum() < 2 or not cells.any():
            continue
        along_axis = 1 if w < 2 else 0  # a wall x = const runs along y
        order = np.argsort(contacts.xy_m[on, along_axis], kind="stable")
        xy, lo, hi = contacts.xy_m[on][order], contacts.low_m[on][order], contacts.high_m[on][order]
        cx, cy = x[cells], y[cells]
        j = np.searchsorted(xy[:, along_axis], (cx, cy)[along_axis])
        pair = (j > 0) & (j < len(xy))
        left, right = np.clip(j - 1, 0, len(xy) - 1), np.clip(j, 0, len(xy) - 1)
        d_left = np.hypot(xy[left, 0] - cx, xy[left, 1] - cy)
        d_right = np.hypot(xy[right, 0] - cx, xy[right, 1] - cy)
        band_low = np.minimum(lo[left] - MAX_SLOPE * d_left, lo[right] - MAX_SLOPE * d_right)
        band_high = np.maximum(hi[left] + MAX_SLOPE * d_left, hi[right] + MAX_SLOPE * d_right)
        low[cells] = np.where(pair, band_low, -np.inf)
        high[cells] = np.where(pair, band_high, np.inf)
    return low, high


def contradicted_strip(fit: np.ndarray, counts: np.ndarray, contacts: WallContacts, grid: Grid,
                       slack_m: float) -> np.ndarray:
    """(nx, ny) True for the strip cells (`strip_cells`) whose fitted height lies more than slack_m outside the
    band their contacts allow (`contact_band_m`): the hull's bridge, for the fill to decide instead. Only the contacts
    whose material leans on the wall as measured judge it (`WallContacts.measured_leaning`): a false contact would
    take a fitted cell and fill it metres high."""
    fit = np.asarray(fit, dtype=float)
    strip = strip_cells(counts, grid) & np.isfinite(fit)
    if not len(contacts) or not strip.any():
        return np.zeros(fit.shape, dtype=bool)
    low, high = contact_band_m(contacts.measured_leaning(), grid, strip)
    with np.errstate(invalid="ignore"):
        return strip & ((fit < low - slack_m) | (fit > high + slack_m))
