"""The surface fits' triangulation: its barycentric transforms, computed in one pass, are scipy's."""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from ground.triangulation import barycentric_transforms, delaunay


def test_that_the_transforms_are_scipys_to_rounding_on_scattered_and_gridded_points():
    rng = np.random.default_rng(4)
    scattered = rng.uniform(0.0, 60.0, (3000, 2))
    gx, gy = np.meshgrid(np.arange(0.125, 20.0, 0.25), np.arange(0.125, 10.0, 0.25))  # cell centres: co-circular
    gridded = np.column_stack([gx.ravel(), gy.ravel()]) + rng.normal(0.0, 1e-3, (gx.size, 2))
    for xy in (scattered, gridded):
        want = Delaunay(xy).transform  # scipy's own, one LAPACK solve per triangle
        got = delaunay(xy).transform
        assert got.shape == want.shape
        assert np.array_equal(np.isnan(got), np.isnan(want))
        ok = np.isfinite(want)
        assert np.allclose(got[ok], want[ok], rtol=1e-12, atol=1e-12 * np.abs(want[ok]).max())


def test_that_a_degenerate_triangle_is_marked_as_scipy_marks_it():
    from scipy.spatial._qhull import _get_barycentric_transforms  # scipy's own routine, for the comparison only
    pts = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0], [1e-17, 2.0], [3.0, 1e-13]])
    simplices = np.array([[0, 1, 2], [0, 1, 3], [0, 3, 4], [0, 2, 5], [1, 3, 5]])
    want = _get_barycentric_transforms(pts, simplices.astype(np.intc), np.finfo(float).eps)
    got = barycentric_transforms(pts, simplices)
    assert np.array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(got[[0, 2]]).all() and np.isfinite(got[[1, 4]]).all()
    assert np.allclose(got[[1, 4]], want[[1, 4]], rtol=1e-12, atol=1e-12)  # entries of size 1


def test_that_points_are_found_and_interpolated_as_without_the_transforms():
    from scipy.interpolate import CloughTocher2DInterpolator
    rng = np.random.default_rng(8)
    xy = rng.uniform(0.0, 10.0, (800, 2))
    z = np.sin(xy[:, 0]) + np.cos(xy[:, 1])
    q = rng.uniform(-1.0, 11.0, (2000, 2))  # some outside the hull
    ours, scipys = delaunay(xy), Delaunay(xy)
    assert np.array_equal(ours.find_simplex(q), scipys.find_simplex(q))
    a, b = CloughTocher2DInterpolator(ours, z)(q), CloughTocher2DInterpolator(scipys, z)(q)
    assert np.array_equal(np.isnan(a), np.isnan(b)) and np.allclose(a[np.isfinite(a)], b[np.isfinite(b)], atol=1e-12)
