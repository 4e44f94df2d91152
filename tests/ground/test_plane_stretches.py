"""The building's planes and each point's nearest one (ground/plane_stretches.py), which the pose correction and the
mount's self-calibration both assign points with."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from ground import plane_stretches
from ground.plane_stretches import INSIDE_SIGN, LINE_FIT_CHUNK, nearest_plane, neighbour_noise_m, planes

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


def _line_fit_by_svd(p: np.ndarray, h: int, at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The same lines one window at a time, by the singular values of the centred points."""
    centre, u, off = [], [], []
    for i in at:
        w = p[i - h:i + h + 1]
        c = w.mean(axis=0)
        _, sv, vt = np.linalg.svd(w - c)
        centre.append(c)
        u.append(vt[0])
        off.append(math.sqrt((sv[1] ** 2 + sv[2] ** 2) / len(w)))
    return np.array(centre), np.array(u), np.array(off)


@pytest.mark.parametrize("chunk", [LINE_FIT_CHUNK, 2])
def test_that_each_window_s_line_is_its_points_principal_axis_far_from_the_origin_and_across_chunks(monkeypatch, chunk):
    """The windows are gathered in chunks and taken relative to their middle point: the same line as the window's own
    principal components, 60 m from the building's corner as at its origin."""
    monkeypatch.setattr(plane_stretches, "LINE_FIT_CHUNK", chunk)
    rng = np.random.default_rng(3)
    s = np.arange(400) * 0.05
    p = np.column_stack([s, 0.5 * s, np.sin(s)]) + rng.normal(0.0, 0.02, (400, 3)) + np.array([60.0, 40.0, 3.0])
    at = np.array([16, 17, 100, 250, 383])
    centre, u, off = plane_stretches.sliding_line_fit(p, 16, at)
    ref_c, ref_u, ref_off = _line_fit_by_svd(p, 16, at)
    np.testing.assert_allclose(centre, ref_c, atol=1e-9)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", u, ref_u)), 1.0, atol=1e-9)  # a direction, either sense
    np.testing.assert_allclose(off, ref_off, atol=1e-9)
    straight = np.column_stack([s, s, 2 * s]) + np.array([60.0, 40.0, 0.0])
    _, u_line, off_line = plane_stretches.sliding_line_fit(straight, 16, at)
    np.testing.assert_allclose(np.abs(u_line @ np.array([1.0, 1.0, 2.0]) / math.sqrt(6.0)), 1.0, atol=1e-12)
    assert np.all(off_line < 1e-6)


def _floor_sweeps(delay_s: float, offset_rad: float = 0.0):
    """A vehicle at 12 m over the floor sweeping a beam +-1 rad across its track at 2 Hz, sampled at 500 Hz, the servo
    lagging the logged angle by delay_s and off it by offset_rad: the points placed on the logged angle, their beam
    vectors, their heights (the floor's residuals) and the floor's plane index."""
    t = np.arange(0.0, 4.0, 0.002)
    logged = np.arcsin(np.sin(2 * np.pi * 2.0 * t)) * (2.0 / np.pi)  # a triangle wave of +-1 rad
    true = np.interp(t - delay_s, t, logged) + offset_rad
    rng = 12.0 / np.cos(true)  # where the true beam met the floor
    beam = rng[:, None] * np.column_stack([np.zeros_like(t), np.sin(logged), -np.cos(logged)])
    z = 12.0 + beam[:, 2]
    return t, beam, z, np.zeros(len(t), dtype=np.int64)


def test_that_a_servo_lagging_its_logged_angle_is_found_beside_the_planes_and_taken_out_of_their_misfit():
    n, _ = planes(STORAGE)
    t, beam, z, plane = _floor_sweeps(0.5e-3)
    split = plane_stretches.beside_a_servo_delay(t, beam, z, plane, n)
    assert split.delay_s == pytest.approx(0.5e-3, rel=0.1)
    assert split.misfit_m < 0.2 * plane_stretches.robust_rms(z)


def test_that_a_servo_offset_the_same_both_ways_is_not_taken_for_a_timing_offset():
    n, _ = planes(STORAGE)
    t, beam, z, plane = _floor_sweeps(0.0, offset_rad=math.radians(0.2))
    split = plane_stretches.beside_a_servo_delay(t, beam, z, plane, n)
    assert abs(split.delay_s) < 2e-5 and split.misfit_m > 0.9 * plane_stretches.robust_rms(z)


def _knot_and_angle_groups(t: np.ndarray, beam: np.ndarray, spacing_s: float = 1.0) -> np.ndarray:
    """Each point's group as the pose correction forms them: its knot interval (spacing_s) and logged angle's bin."""
    return plane_stretches.by_angle((t // spacing_s).astype(np.int64), np.arctan2(beam[:, 1], -beam[:, 2]))


def test_that_a_lag_is_found_on_the_planes_as_logged_with_each_knot_interval_and_angle_about_its_own_mean():
    """The pose correction fits this offset on the floor and walls as logged, before any drift is fitted: their points
    lie a drift off their planes, a metre from one knot interval to the next. Each knot interval's points at one logged
    angle about their own mean, the drift goes, and a 10 ms lag is found whole."""
    n, _ = planes(STORAGE)
    t, beam, z, plane = _floor_sweeps(0.010)
    steps = np.random.default_rng(1).uniform(-1.0, 1.0, 8)[(t // 1.0).astype(int)]
    split = plane_stretches.beside_a_servo_delay(t, beam, z + steps, plane, n, groups=_knot_and_angle_groups(t, beam))
    assert split.delay_s == pytest.approx(0.010, rel=0.02)
    assert split.significant(3.0, 0.01)
    assert split.misfit_m < 0.05 * plane_stretches.robust_rms(z + steps)


def test_that_a_servo_offset_or_scale_is_not_taken_for_a_lag_when_each_angle_is_its_own_group():
    """A servo off or over-scaled puts a point at one logged angle the same distance off whichever way it swept; a
    lag does not. Grouped by knot interval alone (here 3 s of a 0.6 Hz sweep, the floor seen out to 1.3 rad), the
    two directions do not see each angle equally often and a 3 deg offset reads as 4 ms of lag; at one angle, as
    nothing."""
    n, _ = planes(STORAGE)
    t = np.arange(0.0, 12.0, 0.002)
    logged = np.arcsin(np.sin(2 * np.pi * 0.6 * t)) * (2.0 / np.pi) * 1.4
    interval = (t // 3.0).astype(np.int64)
    for offset_rad, scale in ((math.radians(3.0), 1.0), (0.0, 1.05)):
        true = logged * scale + offset_rad
        beam = (12.0 / np.cos(true))[:, None] * np.column_stack([np.zeros_like(t), np.sin(logged), -np.cos(logged)])
        z = 12.0 + beam[:, 2] + 0.3 * np.sin(t / 3.0)  # and a drift
        plane = np.where(np.abs(true) < 1.3, 0, -1)
        by_interval, by_angle = (plane_stretches.beside_a_servo_delay(t, beam, z, plane, n, groups=g)
                                 for g in (interval, plane_stretches.by_angle(interval, logged)))
        assert by_interval.significant(3.0, 0.01), (offset_rad, scale)  # what the angle's groups are for
        assert not by_angle.significant(3.0, 0.01), (offset_rad, scale)


def test_that_angle_bins_hold_both_sweep_directions():
    t = np.arange(0.0, 2.0, 0.002)
    angle = np.arcsin(np.sin(2 * np.pi * 2.0 * t)) * (2.0 / np.pi)
    bins = plane_stretches.angle_bins(angle)
    up = np.gradient(angle) > 0
    both = np.intersect1d(bins[up], bins[~up])
    assert len(both) >= 0.9 * len(np.unique(bins)) and bins.min() == 0
    assert len(plane_stretches.angle_bins(np.zeros(0))) == 0 and np.all(plane_stretches.angle_bins(np.ones(5)) == 0)
