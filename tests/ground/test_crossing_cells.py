"""The pile seen at different times, in cells (ground/crossing_cells.py)."""

from __future__ import annotations

import math

import numpy as np

from ground.crossing_cells import not_the_pile, slope_continues, up_noise_m


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


def test_that_what_a_beam_pointing_level_or_up_hit_is_no_part_of_the_pile():
    # the vehicle flies over the pile: at or above its height a beam finds a wall or the roof
    to_point = np.array([[0.0, 3.0, -2.0], [0.0, 9.0, 0.0], [0.0, 9.0, 0.4], [1.0, 0.0, -7.0]])
    wall = np.array([False, False, False, True])
    assert not_the_pile(wall, to_point).tolist() == [False, True, True, True]


def test_that_a_beam_up_by_less_than_its_pointing_noise_may_be_a_level_one_and_is_kept():
    to_point = np.array([[0.0, 9.0, 0.0], [0.0, 9.0, 0.4], [0.0, 9.0, 0.6], [0.0, 9.0, -0.1]])
    up_m = up_noise_m(to_point, math.radians(1.0))  # three degrees at 9 m: 0.47 m
    assert np.allclose(up_m, 3 * math.radians(1.0) * np.linalg.norm(to_point, axis=1))
    assert not_the_pile(np.zeros(4, dtype=bool), to_point, math.radians(1.0)).tolist() == [False, False, True, False]
