"""The building's planes and each point's nearest one (ground/plane_stretches.py), which the pose correction and the
mount's self-calibration both assign points with."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from ground.plane_stretches import INSIDE_SIGN, nearest_plane, neighbour_noise_m, planes

STORAGE = Storage(60.0, 40.0, 15.0)


def test_that_the_inside_sign_is_positive_for_a_point_inside_the_building_on_every_plane():
    n, d = planes(STORAGE)
    inside = np.array([[30.0, 20.0, 5.0], [0.1, 39.9, 0.1]])
    outside = np.array([[-0.1, 20.0, 5.0], [30.0, 40.2, 5.0], [30.0, 20.0, -0.1]])
    assert ((inside @ n.T - d) * INSIDE_SIGN > 0).all()
    assert (((outside @ n.T - d) * INSIDE_SIGN) < 0).any(axis=1).all()


def test_that_each_point_gets_its_nearest_plane_within_the_window_and_only_among_those_allowed():
    n, d = planes(STORAGE)
    p = np.array([[30.0, 20.0, 0.02],    # on the floor, 2 cm up
                  [59.97, 20.0, 6.0],    # 3 cm short of the wall x = L
                  [30.0, 20.0, 6.0],     # in the middle: no plane within the window
                  [0.01, 0.02, 5.0]])    # in a corner: 1 cm from x = 0, 2 cm from y = 0
    j, r = nearest_plane(p, n, d, 0.05)
    assert j.tolist() == [0, 2, -1, 1]
    np.testing.assert_allclose(r[[0, 1, 3]], [0.02, -0.03, 0.01], atol=1e-12)
    # a window per point: the floor's point outside its own 1 cm window
    j, _ = nearest_plane(p, n, d, np.array([0.01, 0.05, 0.05, 0.05]))
    assert j.tolist() == [-1, 2, -1, 1]
    # the corner point may lie on y = 0 only (its stretch of sweep runs along that wall), the floor's point on none
    allowed = np.ones((4, 5), dtype=bool)
    allowed[3] = [False, False, False, True, False]
    allowed[0] = False
    j, r = nearest_plane(p, n, d, 0.05, allowed)
    assert j.tolist() == [-1, 2, -1, 3] and r[3] == 0.02


def test_that_the_noise_is_read_off_neighbours_on_one_plane_whatever_moves_them_alike():
    # a common offset of 5 cm (a pose or mount error) on a plane's points is not noise; their scatter is
    rng = np.random.default_rng(0)
    r = 0.05 + rng.normal(0.0, 0.002, 4000)
    plane = np.repeat([1, 2], 2000)
    assert neighbour_noise_m(plane, r) == pytest.approx(0.002, rel=0.1)
    # neighbours on different planes, or one off every plane, are no pair: with no pair left, nothing is measured
    assert neighbour_noise_m(np.array([0, -1, 1, -1, 2]), np.array([0.0, 1.0, 2.0, 3.0, 4.0])) is None
