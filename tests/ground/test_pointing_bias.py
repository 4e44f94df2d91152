"""Where a pointing error places the points (ground.pointing_bias): behind the surface, along the beam."""

import math

import numpy as np
import pytest

from ground.pointing_bias import MIN_GRAZING_RAD, along_beam_bias_m, grid_normals, max_t, sweep_directions

SIGMA = math.radians(1.0)


def placed_range_excess_m(theta_rad: float, height_m: float = 12.0, n: int = 1_000_000) -> float:
    """A beam theta from the vertical turned by a normal pointing error in its sweep plane meets a floor height_m
    below; placed along the untouched beam at the range it came back with, it lies this far beyond the floor's
    range along that beam, on average (sampled in antithetic pairs, so the first-order term cancels exactly)."""
    half = np.random.default_rng(5).normal(0.0, SIGMA, n // 2)
    delta = np.concatenate([half, -half])
    return float(np.mean(height_m / np.cos(theta_rad + delta)) - height_m / math.cos(theta_rad))


@pytest.mark.parametrize("theta_deg", [0.0, 30.0, 60.0])
def test_that_a_pointing_error_places_points_behind_a_floor_by_r_sigma_squared_t_squared_plus_a_half(theta_deg):
    th = math.radians(theta_deg)
    d = np.array([[math.sin(th), 0.0, -math.cos(th)]])
    u = np.array([[math.cos(th), 0.0, math.sin(th)]])
    bias = along_beam_bias_m(np.array([12.0 / math.cos(th)]), d, u, np.array([[0.0, 0.0, 1.0]]), SIGMA)[0]
    assert bias == pytest.approx(placed_range_excess_m(th), rel=0.03)


def test_that_a_grazing_beam_takes_the_capped_bias_and_an_unknown_normal_the_least():
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    u = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    normals = np.array([[0.0, 0.0, 1.0], [np.nan, np.nan, np.nan]])  # a beam along the floor; no normal
    bias = along_beam_bias_m(np.array([10.0, 10.0]), d, u, normals, SIGMA)
    assert max_t(SIGMA) == pytest.approx(1.0 / math.tan(MIN_GRAZING_RAD))
    assert bias[0] == pytest.approx(10.0 * SIGMA**2 * (max_t(SIGMA) ** 2 + 0.5))
    assert bias[1] == pytest.approx(10.0 * SIGMA**2 * 0.5)
    assert np.all(along_beam_bias_m(np.array([10.0, 10.0]), d, u, normals, 0.0) == 0.0)


def test_that_a_larger_pointing_error_caps_t_further_from_grazing():
    assert max_t(math.radians(2.0)) == pytest.approx(1.0 / math.tan(math.radians(20.0)))


def test_that_the_sweep_direction_is_across_the_beam_in_its_sweep_plane():
    th = np.radians(np.linspace(-40, 40, 81))
    d = np.column_stack([np.zeros_like(th), np.sin(th), -np.cos(th)])  # a sweep across y
    u = sweep_directions(d)
    assert np.allclose(np.sum(u * d, axis=1), 0.0, atol=1e-12)
    assert np.allclose(u, np.column_stack([np.zeros_like(th), np.cos(th), np.sin(th)]), atol=1e-3)
    assert np.all(sweep_directions(np.tile([0.0, 0.0, -1.0], (5, 1))) == 0.0)  # a beam that does not turn


def test_that_the_normals_of_a_tilted_grid_are_its_planes_and_nan_off_it():
    xs = (np.arange(40) + 0.5) * 0.25
    ys = (np.arange(20) + 0.5) * 0.25
    h = 1.0 + 0.5 * xs[:, None] - 0.25 * ys[None, :]
    h[:, :2] = np.nan
    pts = np.array([[5.0, 3.0, 0.0], [5.0, 0.1, 0.0]])
    n = grid_normals(pts, h, (0.25, 0.25))
    assert np.allclose(n[0], np.array([-0.5, 0.25, 1.0]) / np.linalg.norm([-0.5, 0.25, 1.0]))
    assert np.all(np.isnan(n[1]))
