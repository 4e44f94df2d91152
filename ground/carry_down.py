"""The unseen cells filled from the nearest seen height, carried on down where the seen surface falls towards them.

The `nearest` copy puts the last seen height level across unseen ground. In a *shadow* (an unseen cell a beam
passed over on its way to a hit beyond: the ground there lies below the sightline over what cast the shadow) where
the seen surface *falls* towards the cell (a flank that goes on behind a crest, the floor behind a box) the copy is
a plateau at the edge's height that granular material cannot hold past a crest, and the fill runs high. Carried
down at the slope the surface had at the edge, the fill follows the flank instead, and the floor stops it: a hard
bound, the one the copy already respects. Where the surface rises or is level towards the unseen cells the copy is
kept: a rising slope carried up has only the free-space ceiling above it, a loose bound, and it overshoots flat
tops and runs with the noise of the edge. Unseen cells no beam passed over (a corner no sweep reached) keep the copy
too: nothing says the ground there falls (carried down everywhere, the corner piles read lower still). Measured on
the evaluation set: docs/design-notes.md, "The unseen fill carried down the seen slope in the shadows".

The slope is that of the plane fitted to the seen cells within `SLOPE_RADIUS_M` of the edge cell (a square window),
never steeper than `ground.unseen.MAX_SLOPE`.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ground.unseen import MAX_SLOPE

SLOPE_RADIUS_M = 1.0
"""Half the side of the window the edge's slope is fitted over: metres of the seen surface, wider than the local
estimator's smoothing of single points and far narrower than a pile (1 m and 2 m read the evaluation set alike)."""


def window_slopes(heights: np.ndarray, cell_x_m: float, cell_y_m: float,
                  radius_m: float = SLOPE_RADIUS_M) -> tuple[np.ndarray, np.ndarray]:
    """(gx, gy) at every cell: the slope of the least-squares plane through the finite cells of the square window
    within radius_m of it, (nx, ny) each; 0 where the window holds fewer finite cells than it is wide, or only a
    line of them (no plane)."""
    h = np.asarray(heights, dtype=float)
    known = np.isfinite(h)
    k = max(1, round(radius_m / min(cell_x_m, cell_y_m)))
    side = 2 * k + 1
    # Coordinates from the grid's corner, in metres: sums of squares over a few metres of a 100 m floor keep
    # their precision in float64.
    x = np.broadcast_to((np.arange(h.shape[0]) * cell_x_m)[:, None], h.shape)
    y = np.broadcast_to((np.arange(h.shape[1]) * cell_y_m)[None, :], h.shape)
    w = known.astype(float)
    z = np.where(known, h, 0.0)

    def mean(a: np.ndarray) -> np.ndarray:
        return ndimage.uniform_filter(a, side, mode="constant")

    s = mean(w)
    with np.errstate(divide="ignore", invalid="ignore"):
        mx, my, mz = mean(w * x) / s, mean(w * y) / s, mean(z) / s
        cxx = mean(w * x * x) / s - mx * mx
        cyy = mean(w * y * y) / s - my * my
        cxy = mean(w * x * y) / s - mx * my
        cxz = mean(z * x) / s - mx * mz
        cyz = mean(z * y) / s - my * mz
        det = cxx * cyy - cxy * cxy
        gx = (cxz * cyy - cyz * cxy) / det
        gy = (cyz * cxx - cxz * cxy) / det
    plane = (s * side * side >= side - 0.5) & (det > 1e-9 * (cell_x_m * cell_y_m) ** 2)
    return np.where(plane, gx, 0.0), np.where(plane, gy, 0.0)


def carry_down(heights: np.ndarray, cell_x_m: float, cell_y_m: float, where: np.ndarray | None = None,
               radius_m: float = SLOPE_RADIUS_M, max_slope: float = MAX_SLOPE) -> np.ndarray:
    """heights with its NaN cells filled: the nearest finite cell's height (as the `nearest` copy picks it), lowered
    in the cells of `where` (None: every one) by the seen slope there times the distance where the surface falls
    towards the cell (the slope no steeper than max_slope), never below the floor (z = 0) nor below that height when
    it is already under the floor. Unchanged when no cell or every cell is finite."""
    h = np.asarray(heights, dtype=float)
    empty = ~np.isfinite(h)
    if not empty.any() or empty.all():
        return h
    gx, gy = window_slopes(h, cell_x_m, cell_y_m, radius_m)
    _, (ix, iy) = ndimage.distance_transform_edt(empty, return_indices=True)
    near = h[ix, iy]
    dx = (np.arange(h.shape[0])[:, None] - ix) * cell_x_m
    dy = (np.arange(h.shape[1])[None, :] - iy) * cell_y_m
    drop = np.clip(gx[ix, iy] * dx + gy[ix, iy] * dy, -max_slope * np.hypot(dx, dy), 0.0)
    if where is not None:
        drop = np.where(where, drop, 0.0)
    return np.where(empty, np.maximum(near + drop, np.minimum(near, 0.0)), h)
