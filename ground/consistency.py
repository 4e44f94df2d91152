"""Do the two sweep directions see the same surface? The check that catches a wrong servo model.

A hobby servo has no feedback: the angle logged with each sample is the firmware's model of the
shaft. If the real servo is slower than its calibration (or lags more), the model is wrong in
opposite senses on the two sweep directions (the shaft trails the command one way, then the
other), so the points of the rising and the falling sweeps land at different heights. With a good
model they agree to a few centimetres (the cells' own sampling); the median disagreement per cell
is the measure, and above `MAX_SWEEP_DISAGREEMENT_M` the report says the angles cannot be trusted.
"""

from __future__ import annotations

import numpy as np

from ground.surface import Grid
from ground.uncertainty import cell_spread_m

MAX_SWEEP_DISAGREEMENT_M = 0.3
"""Ten times what a correct model shows with 1 cm ranges, three times Appendix A's pose noise."""
MIN_POINTS_PER_CELL = 3
MIN_CELLS = 20


def sweep_disagreement_m(points_w: np.ndarray, sweep_dir: np.ndarray, grid: Grid,
                         face_spread: float | None = None) -> tuple[float | None, int]:
    """(median |mean z of rising-sweep points - mean z of falling-sweep points| over cells with
    MIN_POINTS_PER_CELL of each, number of such cells); None when fewer than MIN_CELLS compare.

    With face_spread (m), a cell where one direction's own points span more height than that is left
    out: it holds a vertical face or an overhang, which the two directions see from opposite sides, so
    their heights there differ for the shape's sake, not the servo's (a late servo shifts each
    direction's points together and spreads neither)."""
    p = np.asarray(points_w, dtype=float)
    d = np.asarray(sweep_dir)
    faces = np.zeros(grid.shape, dtype=bool)
    sums = []
    for direction in (1, -1):
        q = p[d == direction]
        if face_spread is not None:
            faces |= cell_spread_m(q, grid) > face_spread
        cell = grid.flat_cells(q)  # one lookup for both sums
        sums.append((grid.cell_sums(cell), grid.cell_sums(cell, q[:, 2])))
    (c1, z1), (c2, z2) = sums
    both = (c1 >= MIN_POINTS_PER_CELL) & (c2 >= MIN_POINTS_PER_CELL) & ~faces
    n = int(both.sum())
    if n < MIN_CELLS:
        return None, n
    return float(np.median(np.abs(z1[both] / c1[both] - z2[both] / c2[both]))), n
