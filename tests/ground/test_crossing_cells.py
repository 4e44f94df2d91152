"""The pile seen at different times, in cells (ground/crossing_cells.py)."""

from __future__ import annotations

import numpy as np

from ground.crossing_cells import slope_continues


def test_that_a_slope_is_used_only_where_it_continues_up_or_down_it():
    # A pile's flank spans several cells; a block's edge caught in one cell has flat cells on both sides, and the
    # slope fitted across it is wherever the grid cut it (one such cell carried a whole registration by a metre).
    nx, ny = 6, 5
    gx, gy = np.zeros(nx * ny), np.zeros(nx * ny)
    flank = [1 * ny + 2, 2 * ny + 2, 3 * ny + 2]  # three cells in a row along x, sloping up x
    gx[flank] = 0.6
    step = 4 * ny + 4  # one cell sloping up y, its neighbours along y flat
    gy[step] = 0.9
    against = 5 * ny + 0  # sloping up x beside a cell sloping down x: not the same slope
    gx[against], gx[4 * ny + 0] = 0.5, -0.5
    sloped = np.hypot(gx, gy) > 0
    keep = slope_continues(sloped, gx, gy, nx * ny, ny)
    assert keep[flank].all()
    assert not keep[step] and not keep[against]
