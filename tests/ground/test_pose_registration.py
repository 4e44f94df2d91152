"""The registration on the pile seen at different times (ground/pose_registration.py)."""

from __future__ import annotations

import numpy as np

from ground.pose_registration import pinned_to_floor


def test_that_a_cell_a_pass_saw_mostly_as_floor_is_held_at_the_floor_only_when_it_is_flat():
    # three cells of a 4 x 4 grid: 3 flat (a pass saw floor), 7 sloped (a pile's toe: a pass saw the floor's band
    # in it, the other the flank), 9 flat but never floor
    cells = np.array([3, 7, 9])
    inv = np.array([0, 0, 1, 1, 2])
    is_floor = np.array([True, False, True, False, False])
    gx, gy = np.zeros(16), np.zeros(16)
    gx[7], gy[7] = 0.4, -0.3
    assert pinned_to_floor(cells, inv, is_floor, gx, gy).tolist() == [True, False, False]
    gx[7] = gy[7] = 0.0  # the same cell flat: held
    assert pinned_to_floor(cells, inv, is_floor, gx, gy).tolist() == [True, True, False]
