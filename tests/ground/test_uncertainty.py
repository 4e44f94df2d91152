"""The volume's error terms and interval (ground.uncertainty) and the warnings built on them."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from firmware_py.core.frames import StorageFrame
from firmware_py.core.storage import Storage
from ground.report import ReportOptions, summarise, survey_from_samples
from ground.surface import Grid, fill_empty
from ground.uncertainty import (
    DEFAULT_INTERVAL_MODEL,
    LEVEL_Z,
    ErrorTerms,
    IntervalModel,
    SharedDraws,
    blur_term_m3,
    face_cells,
    floor_curvature_noise_m_inv,
    interpolation_term_m3,
    laplacian_peak_gain_m2_inv,
    noise_term_m3,
    scatter_sigma_m,
    shared_draws,
    sweeps_term_m3,
    unseen_terms_m3,
)
from ground.volume_warnings import (
    MIN_FACE_CELLS,
    along_walls,
    faces_warning,
    level_warning,
    open_floor_reading,
    open_floor_warning,
    unseen_warning,
    wide_interval_warning,
)

GRID = Grid(20.0, 10.0, 0.5)
UNIT = IntervalModel(k_unseen=1, k_interpolation=1, k_noise=1, k_sweeps=1, k_faces=1, k_blur=1)
"""Every factor 1: the warnings' tests do not depend on the calibration."""


def _plane_points(n: int, rng: np.random.Generator, sigma: float = 0.0) -> np.ndarray:
    xy = rng.uniform([0, 0], [GRID.length_m, GRID.width_m], size=(n, 2))
    return np.column_stack([xy, 1.0 + 0.1 * xy[:, 0] + rng.normal(0, sigma, n) if sigma else 1.0 + 0.1 * xy[:, 0]])


def _heights_of(f) -> np.ndarray:
    cx, cy = GRID.centres()
    return f(cx, cy)


def test_that_an_unseen_corner_beside_a_flat_edge_costs_nothing():
    fit = _heights_of(lambda x, y: np.ones_like(x))
    fit[:4, :4] = np.nan
    filled = np.where(np.isfinite(fit), fit, 1.0)
    assert unseen_terms_m3(fit, filled, GRID) == (0.0, 0.0)  # the ground was not changing where sight stopped


def test_that_the_unseen_term_grows_with_the_edge_slope_and_the_distance_from_the_edge():
    slope = 0.5
    fit = _heights_of(lambda x, y: 2.0 + slope * x)
    fit[:2, :] = np.nan  # two columns along x = 0 unseen: 0.5 m and 1.0 m from the first seen column
    filled = fill_empty(fit, "nearest")
    low, high = unseen_terms_m3(fit, filled, GRID)
    ny = GRID.shape[1]
    expected = ny * slope * (0.5 + 1.0) * GRID.cell_area_m2
    assert low == pytest.approx(expected) and high == pytest.approx(expected)
    assert unseen_terms_m3(2 * fit - 2.0, 2 * filled - 2.0, GRID)[0] == pytest.approx(2 * expected)


def test_that_the_unseen_term_reads_the_edges_steepest_slope_within_a_metre_not_a_flattened_last_cell():
    """A flank whose fit goes flat in its last seen columns (an estimator's window reaching past the last points)
    still climbs on into the unseen cells: the reach takes the flank's slope from within EDGE_SLOPE_RADIUS_M of the
    nearest seen cell, and no slope from farther off."""
    from ground.uncertainty import EDGE_SLOPE_RADIUS_M, unseen_reach_m

    assert EDGE_SLOPE_RADIUS_M == pytest.approx(1.0)
    slope = 0.5
    cx, _ = GRID.centres()  # cells of 0.5 m: columns at x = 0.25, 0.75, ...
    fit = np.where(cx < 1.5, 2.0, 2.0 + slope * (cx - 1.5))  # flat in x < 1.5 m, the flank beyond
    fit[:2, :] = np.nan  # unseen: x < 1 m; the nearest seen column (1.25 m) reads half the flank's slope
    reach = unseen_reach_m(fit, GRID)
    assert reach[1, 5] == pytest.approx(slope * 0.5)
    assert reach[0, 5] == pytest.approx(slope * 1.0)
    far = np.where(cx < 3.0, 2.0, 2.0 + slope * (cx - 3.0))  # the flank starts 1.75 m from the nearest seen column
    far[:2, :] = np.nan
    assert unseen_reach_m(far, GRID)[:2].max() == pytest.approx(0.0)


def test_that_the_unseen_term_takes_the_edge_slope_from_the_heights_it_is_given_in_the_seen_cells_only():
    """With the GP's slopes the surface is smoothed at its edge; the unseen term takes the slope where sight stopped
    from the same nodes' surface with scipy's slopes (edge_m), and its unseen cells from the surface itself."""
    slope = 0.5
    steep = _heights_of(lambda x, y: 2.0 + slope * x)
    flat = np.full(GRID.shape, 2.5)  # the smoothed surface: no slope at the edge
    for heights in (steep, flat):
        heights[:2, :] = np.nan
    filled = fill_empty(flat, "nearest")
    assert unseen_terms_m3(flat, filled, GRID) == (0.0, 0.0)
    low, high = unseen_terms_m3(flat, filled, GRID, edge_m=steep)
    expected = GRID.shape[1] * slope * (0.5 + 1.0) * GRID.cell_area_m2
    assert low == pytest.approx(expected) and high == pytest.approx(expected)
    wider = np.where(np.isfinite(steep), steep, 50.0)  # edge_m's own heights in the unseen cells count for nothing
    assert unseen_terms_m3(flat, filled, GRID, edge_m=wider) == (low, high)
    holed = steep.copy()
    holed[2:, :] = np.nan  # no edge heights at all: the surface's own
    assert unseen_terms_m3(flat, filled, GRID, edge_m=holed) == (0.0, 0.0)


def test_that_the_floor_and_an_upper_bound_cap_the_unseen_term():
    fit = _heights_of(lambda x, y: 2.0 * x - 2.0)  # a steep flank, 0.5 m up at the first seen column (x = 1.25 m)
    fit[:2, :] = np.nan
    filled = fill_empty(fit, "nearest")  # 0.5 m copied into the unseen columns, 0.5 m and 1.0 m from the edge
    ny = GRID.shape[1]
    low, high = unseen_terms_m3(fit, filled, GRID)
    assert low == pytest.approx(ny * 2 * 0.5 * GRID.cell_area_m2)  # the truth cannot be below the floor
    assert high == pytest.approx(ny * 2.0 * (0.5 + 1.0) * GRID.cell_area_m2)
    # a roof 1.5 m above the fill leaves the nearer column its slope's 1.0 m and the farther 1.5 m of its 2.0 m
    assert unseen_terms_m3(fit, filled, GRID, upper_m=2.0)[1] == pytest.approx(ny * 2.5 * GRID.cell_area_m2)


def test_that_cells_left_empty_count_the_nearest_surface_on_the_high_side_only():
    fit = _heights_of(lambda x, y: np.ones_like(x))
    fit[:4, :4] = np.nan
    assert unseen_terms_m3(fit, fit, GRID) == (0.0, pytest.approx(16 * 1.0 * GRID.cell_area_m2))


def test_that_an_upper_bound_from_free_space_caps_the_high_side_where_it_is_known():
    fit = _heights_of(lambda x, y: 1.0 + 2.0 * x)
    fit[:4, :] = np.nan
    filled = fill_empty(fit, "nearest")
    upper = np.full(GRID.shape, np.nan)
    upper[:4, :] = filled[:4, :] + 0.5
    unbounded = unseen_terms_m3(fit, filled, GRID)
    low, high = unseen_terms_m3(fit, filled, GRID, upper_m=upper)
    assert high == pytest.approx(4 * GRID.shape[1] * 0.5 * GRID.cell_area_m2) and high < unbounded[1]
    assert low == pytest.approx(unbounded[0])


def test_that_interpolating_a_plane_costs_nothing_and_a_curved_surface_grows_with_the_gap():
    counts = np.zeros(GRID.shape, int)
    counts[::4, :] = 5  # tracks every 2 m
    plane = _heights_of(lambda x, y: 1.0 + 0.1 * x)
    assert interpolation_term_m3(plane, counts, GRID) == pytest.approx(0.0, abs=1e-9)
    bowl = _heights_of(lambda x, y: 0.02 * (x - 10.0) ** 2)
    near = interpolation_term_m3(bowl, counts, GRID)
    sparse = np.zeros(GRID.shape, int)
    sparse[::8, :] = 5  # tracks every 4 m
    far = interpolation_term_m3(bowl, sparse, GRID)
    assert 0 < near < far


def test_that_the_interpolation_terms_of_the_parts_of_a_floor_add_up_to_the_whole():
    # a pile's term is its share of the survey's: tracks every 2 m on one half, every 6 m on the other (the
    # halves' own gaps differ in size, which set each part's curvature scale when the part was asked alone)
    counts = np.zeros(GRID.shape, int)
    half = GRID.shape[0] // 2
    counts[:half:4, :] = 5
    counts[half::12, :] = 5
    bowl = _heights_of(lambda x, y: 0.02 * (x - 10.0) ** 2 + 0.03 * (y - 7.0) ** 2)
    left = np.zeros(GRID.shape, bool)
    left[:half] = True
    whole = interpolation_term_m3(bowl, counts, GRID)
    parts = interpolation_term_m3(bowl, counts, GRID, left) + interpolation_term_m3(bowl, counts, GRID, ~left)
    assert whole > 0 and parts == pytest.approx(whole)


def test_that_noise_in_the_fitted_surface_is_not_counted_as_curvature_between_tracks():
    # white height noise of 5 cm on a plane and on a bowl, tracks every 2 m: |laplacian| rectifies the noise into
    # bend; the term takes the noise's share out, measured from the spread over the gaps and capped by the scatter
    counts = np.zeros(GRID.shape, int)
    counts[::4, :] = 5
    noise = np.random.default_rng(0).normal(0.0, 0.05, GRID.shape)
    plane = _heights_of(lambda x, y: 1.0 + 0.1 * x)
    assert interpolation_term_m3(plane + noise, counts, GRID, scatter_m=0.05) < 0.6 * interpolation_term_m3(
        plane + noise, counts, GRID)
    bowl = _heights_of(lambda x, y: 1.0 + 0.02 * (x - 10.0) ** 2)  # off the floor: the floor's rule is tested below
    clean = interpolation_term_m3(bowl, counts, GRID)
    assert interpolation_term_m3(bowl + noise, counts, GRID) > 1.5 * clean  # the noise read as bend
    assert interpolation_term_m3(bowl + noise, counts, GRID, scatter_m=0.05) == pytest.approx(clean, rel=0.15)


WIDE = Grid(40.0, 20.0, 0.25)


def _tracks_every(cells: int) -> np.ndarray:
    counts = np.zeros(WIDE.shape, int)
    counts[::cells, :] = 5
    return counts


def test_that_noise_bridged_over_the_floor_is_not_counted_as_curvature():
    # 3 cm of noise on tracks 2 m apart, bridged straight between them, on the floor and lifted 1 m off it: on the
    # floor, which is flat, the noise's |L| at each distance from the tracks is measured and taken out; off it only
    # the survey's one spread is
    counts = _tracks_every(8)
    tracks = np.flatnonzero(counts[:, 0])
    at_tracks = np.random.default_rng(1).normal(0.0, 0.03, (len(tracks), WIDE.shape[1]))
    noise = np.array([np.interp(np.arange(WIDE.shape[0]), tracks, col) for col in at_tracks.T]).T
    on_floor = interpolation_term_m3(noise, counts, WIDE, scatter_m=0.03)
    lifted = interpolation_term_m3(1.0 + noise, counts, WIDE, scatter_m=0.03)
    assert 0 < on_floor < 0.6 * lifted


def test_that_a_quiet_survey_of_a_pile_on_the_floor_keeps_its_bend():
    # a dome on a bare floor, exact heights: the floor's quantile is capped by the points' scatter
    counts = _tracks_every(12)
    cx, cy = WIDE.centres()
    dome = np.clip(3.0 - 0.08 * ((cx - 20.0) ** 2 + (cy - 10.0) ** 2), 0.0, None)
    assert interpolation_term_m3(dome, counts, WIDE, scatter_m=0.001) == pytest.approx(
        interpolation_term_m3(dome, counts, WIDE), rel=0.01)


def test_that_the_floor_noise_is_the_quantile_of_each_distance_and_carried_to_sparse_distances():
    d_cells = np.concatenate([np.full(100, 1.0), np.full(100, 3.0), np.full(10, 5.0), np.full(5, 20.0)])
    lap = np.concatenate([np.linspace(0.0, 1.0, 100), np.linspace(0.0, 2.0, 100), np.full(10, 9.0), np.full(5, 9.0)])
    floor = np.ones(len(d_cells), bool)
    floor[:100] = False  # the nearest bin has no floor: nothing measured there
    tau = floor_curvature_noise_m_inv(lap, d_cells, floor, cap=10.0)
    assert np.all(tau[:100] == 0.0)
    assert tau[100:200] == pytest.approx(np.quantile(lap[100:200], 0.95))
    assert np.all(tau[200:] == tau[150])  # too few floor cells beyond: the nearer bin's
    assert np.all(floor_curvature_noise_m_inv(lap, d_cells, floor, cap=0.5)[100:] == 0.5)
    assert np.all(floor_curvature_noise_m_inv(lap, d_cells, floor, cap=0.0) == 0.0)


def test_that_a_quiet_survey_of_a_surface_curved_everywhere_keeps_its_bend():
    # the spread over the gaps is the bowl's own curvature here: the points' scatter caps what is taken as noise
    counts = np.zeros(GRID.shape, int)
    counts[::4, :] = 5
    bowl = _heights_of(lambda x, y: 0.02 * (x - 10.0) ** 2)
    assert interpolation_term_m3(bowl, counts, GRID, scatter_m=0.001) == pytest.approx(
        interpolation_term_m3(bowl, counts, GRID), rel=0.01)


def test_that_the_laplacian_filter_gain_is_its_largest_response_to_a_height_pattern():
    # waves of 1 m amplitude over every direction and period on a periodic grid: the filter's response at a crest
    cell, n = (0.5, 0.25), 64
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    for scale in (1.0, 2.5):
        best = 0.0
        for kx in range(0, n // 2, 2):
            for ky in range(0, n // 2, 2):
                wave = np.cos(2 * np.pi * (kx * i + ky * j) / n)
                lap = ((np.roll(wave, 1, 0) - 2 * wave + np.roll(wave, -1, 0)) / cell[0] ** 2
                       + (np.roll(wave, 1, 1) - 2 * wave + np.roll(wave, -1, 1)) / cell[1] ** 2)
                best = max(best, float(np.abs(ndimage.gaussian_filter(lap, scale, mode="wrap")).max()))
        gain = laplacian_peak_gain_m2_inv(scale, cell)
        assert 0.9 * gain < best <= 1.001 * gain


def test_that_the_noise_term_grows_with_the_points_scatter():
    rng = np.random.default_rng(1)
    terms = []
    for sigma in (0.01, 0.1):
        p = _plane_points(4000, rng, sigma)
        fit = _heights_of(lambda x, y: 1.0 + 0.1 * x)
        terms.append(noise_term_m3(scatter_sigma_m(p, fit, GRID), fit, GRID.counts(p), GRID))
    assert terms[1] == pytest.approx(10 * terms[0], rel=0.3)


def test_that_a_pose_draw_shared_by_a_messages_samples_adds_up_per_message():
    # one point in each of 800 cells (every cell its own area), ten points a pose message: the shared part adds as
    # ten points' areas squared per message, sqrt(10) times the same sigma counted as independent
    fit = _heights_of(lambda x, y: np.ones_like(x))
    cx, cy = GRID.centres()
    xy = np.column_stack([cx.ravel(), cy.ravel()])
    counts = GRID.counts(xy)
    message = np.arange(len(xy)) // 10
    alone = noise_term_m3(0.1, fit, counts, GRID)
    assert alone == pytest.approx(0.1 * GRID.cell_area_m2 * math.sqrt(len(xy)))
    shared = SharedDraws(0.1, message)
    assert noise_term_m3(0.1, fit, counts, GRID, points_xy=xy, shared=shared) == pytest.approx(math.sqrt(10) * alone)
    # a shared sigma above the scatter leaves no negative independent part; half of it shared, half the variance each
    assert noise_term_m3(0.05, fit, counts, GRID, points_xy=xy, shared=shared) == pytest.approx(
        math.sqrt(10) * alone)
    half = SharedDraws(0.1 / math.sqrt(2), message)
    assert noise_term_m3(0.1, fit, counts, GRID, points_xy=xy, shared=half) == pytest.approx(
        alone * math.sqrt(0.5 + 0.5 * 10))


def test_that_the_shared_draws_are_the_pose_message_intervals_of_the_sample_times():
    draws = shared_draws(np.array([0.001, 0.019, 0.021, 1.0]), 0.113, 50.0)
    assert draws.sigma_m == 0.113 and draws.group.tolist() == [0, 0, 1, 50]
    assert shared_draws(None, 0.113, 50.0) is None and shared_draws(np.zeros(3), 0.0, 50.0) is None


def test_that_the_blur_term_is_the_scatter_over_the_piles_footprint_only():
    fit = _heights_of(lambda x, y: np.where(x < 5.0, 2.0, 0.0))  # a 5 x 10 m block on bare floor
    assert blur_term_m3(0.1, fit, GRID) == pytest.approx(0.1 * 50.0)
    assert blur_term_m3(0.0, fit, GRID) == 0.0


def test_that_rising_and_falling_sweeps_at_different_heights_are_a_sweeps_term():
    rng = np.random.default_rng(2)
    p = _plane_points(8000, rng)
    d = np.where(np.arange(len(p)) % 2 == 0, 1, -1)
    fit = _heights_of(lambda x, y: 1.0 + 0.1 * x)
    assert sweeps_term_m3(p, d, fit, GRID) < 0.01  # m³ over 200 m²: a twentieth of a millimetre
    p[d == 1, 2] += 0.2
    area = GRID.length_m * GRID.width_m
    assert sweeps_term_m3(p, d, fit, GRID) == pytest.approx(0.1 * area, rel=0.1)  # cells both sweeps saw


def test_that_a_vertical_face_is_flagged_and_a_steep_smooth_slope_is_not():
    rng = np.random.default_rng(3)
    xy = rng.uniform([0, 0], [GRID.length_m, GRID.width_m], size=(20_000, 2))
    slope = np.column_stack([xy, np.tan(math.radians(40)) * xy[:, 0] * 0.3])  # 40 deg x 0.3: ~14 deg ramp
    assert face_cells(slope, GRID, 0.02, 4.0).n == 0
    box = np.column_stack([xy, np.where(xy[:, 0] < 10.0, 3.0, 0.0)])
    wall = np.column_stack([np.full(200, 10.1), rng.uniform(0, 10, 200), rng.uniform(0, 3, 200)])  # the face
    pts = np.vstack([box, wall])
    faces = face_cells(pts, GRID, 0.02, 4.0)
    assert faces.n > 0 and faces.mask[20].any()  # the cell column at x 10-10.5 m
    assert not faces.mask[:19].any() and not faces.mask[22:].any()


def test_that_the_interval_is_never_below_zero_and_widens_with_each_term():
    m = IntervalModel(k_unseen=1, k_interpolation=1, k_noise=1, k_sweeps=1, k_faces=1)
    assert m.interval_m3(5.0, ErrorTerms(noise_m3=50.0)) == (0.0, 55.0)
    base = m.half_widths_m3(ErrorTerms(noise_m3=3.0))
    wider = m.half_widths_m3(ErrorTerms(noise_m3=3.0, interpolation_m3=4.0))
    assert wider == (5.0, 5.0) and base == (3.0, 3.0)
    lo, hi = m.half_widths_m3(ErrorTerms(unseen_low_m3=4.0, unseen_high_m3=0.0))
    assert lo == 4.0 and hi == 0.0


def test_that_an_interval_model_refuses_a_negative_or_infinite_factor():
    with pytest.raises(ValueError, match="k_noise"):
        replace(DEFAULT_INTERVAL_MODEL, k_noise=-1.0)
    with pytest.raises(ValueError, match="k_faces"):
        replace(DEFAULT_INTERVAL_MODEL, k_faces=math.inf)


def test_that_the_unseen_warning_names_where_material_was_invented_and_stays_quiet_when_all_was_seen():
    fit = _heights_of(lambda x, y: np.ones_like(x))
    assert unseen_warning(fit, fit, GRID, ErrorTerms(noise_m3=1.0), UNIT) is None
    fit = _heights_of(lambda x, y: 4.0 - 0.5 * np.hypot(x, y))  # a pile rising into the corner
    fit[:6, :6] = np.nan  # a 3 x 3 m corner never seen
    filled = np.where(np.isfinite(fit), fit, 3.0)
    low, high = unseen_terms_m3(fit, filled, GRID)
    w = unseen_warning(fit, filled, GRID, ErrorTerms(unseen_low_m3=low, unseen_high_m3=high, noise_m3=1.0),
                       UNIT)
    assert w is not None and "x 0-3 m, y 0-3 m" in w and "27 m³" in w


def test_that_unseen_strips_along_the_walls_are_named_by_the_walls_not_the_whole_building():
    fit = _heights_of(lambda x, y: 1.0 + 0.1 * x)  # a pile filling the building to its walls
    fit[:4, :] = np.nan  # 2 m along the wall x = 0 ...
    fit[:, -3:] = np.nan  # ... and 1.5 m along y = 10, joined at their corner: one region spanning the building
    filled = np.where(np.isfinite(fit), fit, 1.0)
    low, high = unseen_terms_m3(fit, filled, GRID)
    w = unseen_warning(fit, filled, GRID, ErrorTerms(unseen_low_m3=low, unseen_high_m3=high, noise_m3=1.0), UNIT)
    assert w is not None and "the walls x = 0 m and y = 10 m (within 2 m)" in w and "x 0-20 m" not in w
    assert along_walls(np.isnan(fit), GRID) == "the walls x = 0 m and y = 10 m (within 2 m)"
    corner = np.zeros(GRID.shape, dtype=bool)
    corner[:6, :6] = True
    assert along_walls(corner, GRID) is None  # a corner is told by its extent, as before
    middle = np.zeros(GRID.shape, dtype=bool)
    middle[5:35, 5:15] = True
    assert along_walls(middle, GRID) is None  # spans the building, at no wall


def test_that_the_unseen_warning_stays_quiet_when_the_unseen_floor_widens_the_interval_by_little():
    fit = _heights_of(lambda x, y: 4.0 - 0.5 * np.hypot(x, y))
    fit[:6, :6] = np.nan
    filled = np.where(np.isfinite(fit), fit, 3.0)
    low, high = unseen_terms_m3(fit, filled, GRID)
    t = ErrorTerms(unseen_low_m3=low, unseen_high_m3=high, noise_m3=1.0)
    assert unseen_warning(fit, filled, GRID, t, UNIT, volume_m3=100 * high, max_pct=5.0) is None  # ±1 %: no need
    assert unseen_warning(fit, filled, GRID, t, UNIT, volume_m3=10 * high, max_pct=5.0) is not None


def test_that_the_unseen_warning_says_material_is_missing_when_the_cells_were_left_empty():
    fit = _heights_of(lambda x, y: np.ones_like(x))
    fit[:6, :6] = np.nan
    low, high = unseen_terms_m3(fit, fit, GRID)
    w = unseen_warning(fit, fit, GRID, ErrorTerms(unseen_low_m3=low, unseen_high_m3=high, noise_m3=1.0), UNIT)
    assert w is not None and "left out" in w and "9 m³" in w


def test_that_the_faces_warning_fires_on_a_face_whatever_its_share_and_on_a_lone_cell_only_when_it_weighs():
    rng = np.random.default_rng(4)
    xy = rng.uniform([0, 0], [GRID.length_m, GRID.width_m], size=(20_000, 2))
    box = np.column_stack([xy, np.where(xy[:, 0] < 10.0, 3.0, 0.0)])
    wall = np.column_stack([np.full(200, 10.1), rng.uniform(0, 10, 200), rng.uniform(0, 3, 200)])
    faces = face_cells(np.vstack([box, wall]), GRID, 0.02, 4.0)
    assert faces.n >= MIN_FACE_CELLS
    terms = ErrorTerms(faces_m3=float(0.5 * faces.excess_m.sum() * GRID.cell_area_m2), noise_m3=0.5)
    w = faces_warning(faces, GRID, terms, UNIT)
    assert w is not None and "vertical face" in w and "x 10-" in w and "calibrated on surfaces" in w
    # the interval is not calibrated for faces: a face warns even where its term is a sliver of the interval
    assert faces_warning(faces, GRID, replace(terms, noise_m3=1e4), UNIT) is not None
    # a lone cell (a stray return) warns only when it weighs in the interval
    stray = np.vstack([box, [[15.2, 5.2, 2.5]] * 3])
    lone = face_cells(stray, GRID, 0.02, 4.0)
    assert 0 < lone.n < MIN_FACE_CELLS
    lone_terms = ErrorTerms(faces_m3=float(0.5 * lone.excess_m.sum() * GRID.cell_area_m2), noise_m3=1e4)
    assert faces_warning(lone, GRID, lone_terms, UNIT) is None
    assert faces_warning(lone, GRID, replace(lone_terms, noise_m3=0.0), UNIT) is not None


def test_that_a_wide_interval_is_a_warning_and_a_tight_one_is_not():
    assert wide_interval_warning(1000.0, (990.0, 1010.0), 5.0) is None
    w = wide_interval_warning(1000.0, (800.0, 1200.0), 5.0)
    assert w is not None and "+/-20.0 %" in w and "(800.0 to 1,200.0 m³)" in w and "other warnings say why" in w
    # A small pile's bounds keep their tenths: a 2-litre box read "(0-0 m³)" for an interval of 0.0-0.1 m³.
    assert "(0.0 to 0.1 m³)" in wide_interval_warning(0.02, (0.0, 0.1), 5.0)
    # with no other warning, it does not send the reader to them
    assert "limited by" in wide_interval_warning(1000.0, (800.0, 1200.0), 5.0, explained=False)


def test_that_a_change_s_interval_is_judged_against_the_stock_it_changed_not_against_itself():
    # +2.2 m³ +- 28 m³ since a survey of 7,205 m³: 0.4 % of the stock, not 1,300 % of the change
    assert wide_interval_warning(2.2, (-26.3, 30.7), 5.0, stock_m3=7204.8) is None
    w = wide_interval_warning(2.2, (-400.0, 404.0), 5.0, stock_m3=7204.8)
    assert w is not None and "earlier survey's 7,204.8 m³" in w and "+/-5.6 %" in w
    assert wide_interval_warning(-30.0, (-60.0, 0.0), 5.0) is None  # a loss alone is no stock to judge by


def test_that_an_empty_building_reports_about_zero_with_an_interval_holding_zero_within_the_range_quantum():
    from firmware_py.core.samplelog import SampleLog
    from sitl.missions.rectangle import Mission
    from sitl.runners.fly import FlyConfig, log_header
    from sitl.sensing.batch_sampler import sample_flight
    from sitl.vehicle.ideal_plant import IdealPlant
    from sitl.world.raycast import World

    storage = Storage(30.0, 20.0, 10.0)
    cfg = FlyConfig(mission=Mission(storage=storage, altitude_m=8.0, p_traj=0.2))
    plant = IdealPlant(cfg.mission, StorageFrame())
    t = np.arange(int(plant.duration_s * cfg.lidar.rate_hz) + 1) / cfg.lidar.rate_hz
    wf = cfg.servo_waveform()
    samples = sample_flight(plant.states(t), wf, World(storage, None, cfg.lidar.max_range_m), cfg.lidar,
                            cfg.lever_arm_body_m, cfg.frame, seed=[0])
    header = log_header(cfg, wf)
    sv = survey_from_samples(samples, header, storage, cfg.frame, np.array(cfg.lever_arm_body_m),
                             ReportOptions(plots=False))
    log = SampleLog(header=header, samples=samples, blocks_ok=1, blocks_corrupt=0, blocks_truncated=0, bytes_skipped=0)
    rep = summarise(sv, log, ReportOptions(plots=False), 0.0)
    lo, hi = rep["volume_interval_m3"]
    assert abs(rep["volume_m3"]) < 0.001 * storage.length_m * storage.width_m * storage.height_m
    # The interval holds zero to within the range quantum's share over the floor (resolution / sqrt 12 of height):
    # the surface is the points' weighted mean, and the quantised floor points' mean here is 0.07 mm off zero
    # (0.03 m3 over 600 m2), more than their independent scatter allows (docs/design-notes.md).
    quantum_m3 = header["sensor"]["resolution_m"] / np.sqrt(12.0) * storage.length_m * storage.width_m
    assert (lo - quantum_m3 <= 0.0 <= hi and rep["volume_m3"] >= 0.0) or rep["volume_m3"] < 0
    assert hi >= 0.0 and rep["truth_in_interval"] in (True, False)
    assert rep["volume_error_pct"] is None and rep["volume_error_m3"] == pytest.approx(rep["volume_m3"])


def test_that_the_pose_term_is_the_height_s_standard_error_over_the_surfaced_cells_and_adds_in_quadrature():
    from ground.uncertainty import pose_term_m3
    grid = Grid(4.0, 2.0, 1.0)
    heights = np.ones(grid.shape)
    heights[0, 0] = np.nan  # not surfaced: not moved by the height
    assert pose_term_m3(0.05, heights, grid) == pytest.approx(0.05 * 7)
    mask = np.zeros(grid.shape, dtype=bool)
    mask[:2] = True
    assert pose_term_m3(0.05, heights, grid, mask) == pytest.approx(0.05 * 3)
    assert pose_term_m3(None, heights, grid) == 0.0
    model = IntervalModel(k_unseen=1, k_interpolation=1, k_noise=1, k_sweeps=1, k_faces=1, k_blur=1, k_pose=2.0)
    below, above = model.half_widths_m3(ErrorTerms(noise_m3=3.0, pose_m3=2.0))
    assert below == above == pytest.approx(5.0)  # sqrt(3^2 + (2 x 2)^2)
    with pytest.raises(ValueError, match="k_pose"):
        replace(model, k_pose=-1.0)


def test_that_a_corrected_height_that_holds_a_wide_interval_is_warned_about_and_a_small_one_is_not():
    from ground.volume_warnings import pose_warning
    model = IntervalModel(k_unseen=1, k_interpolation=1, k_noise=1, k_sweeps=1, k_faces=1, k_blur=1, k_pose=8.0)
    big = ErrorTerms(interpolation_m3=20.0, pose_m3=40.0)  # 320 m³ of 8,800: 3.6 %, over half the 5 % tolerance
    w = pose_warning(big, model, 8800.0, 5.0)
    assert w is not None and "drifting pose's height" in w and "+/-320 m³ (3.6 % of the volume)" in w
    assert pose_warning(ErrorTerms(interpolation_m3=20.0, pose_m3=2.0), model, 8800.0, 5.0) is None  # 16 m³
    assert pose_warning(ErrorTerms(interpolation_m3=400.0, pose_m3=40.0), model, 8800.0, 5.0) is None  # not most
    assert pose_warning(ErrorTerms(interpolation_m3=20.0), model, 8800.0, 5.0) is None  # no height corrected


def test_that_a_height_anchored_on_a_floor_the_walls_do_not_confirm_is_warned_about_with_what_it_moved():
    from ground.surface import Grid

    grid = Grid(24.0, 16.0, 1.0)
    heights = np.full(grid.shape, 3.0)  # the pile covers the floor wall to wall: 384 m²
    w = open_floor_warning(-0.26, heights, grid, 1192.0, 5.0)  # a held-out `vio` flight over pile 2
    assert w is not None and "-0.26 m" in w and "-100 m³" in w and "8.4 % of the volume" in w, w
    assert "hollow in the pile" in w and "beyond the 90 % interval" in w
    assert open_floor_warning(-0.01, heights, grid, 1192.0, 5.0) is None  # 3.8 m³: within half the tolerance
    assert open_floor_warning(None, heights, grid, 1192.0, 5.0) is None  # confirmed, or no floor used
    assert open_floor_warning(math.nan, heights, grid, 1192.0, 5.0) is None  # a failed solve says nothing
    assert "-0 m³" not in open_floor_warning(-0.001, heights, grid, 0.0, 5.0)  # nothing to compare: said, unsigned
    heights[:12] = np.nan  # only the surfaced cells move
    assert "-50 m³" in open_floor_warning(-0.26, heights, grid, 1192.0, 5.0)


def test_that_a_level_no_floor_pinned_widens_the_interval_by_its_stated_sigma_not_a_fitted_factor():
    # The level's sigma is the drift model's (ground.pose_height.level_sigma_m): a Gaussian error of that sigma
    # has its 90 % two-sided half-width at the normal's 95th percentile, added in quadrature to the rest.
    model = IntervalModel(k_unseen=1, k_interpolation=2, k_noise=1, k_sweeps=1, k_faces=1)
    base = ErrorTerms(interpolation_m3=30.0, unseen_low_m3=10.0, unseen_high_m3=20.0)
    below, above = model.half_widths_m3(replace(base, level_m3=50.0))
    assert below == pytest.approx(math.sqrt(60.0**2 + 10.0**2 + (1.6448536 * 50.0) ** 2))
    assert above == pytest.approx(math.sqrt(60.0**2 + 20.0**2 + (1.6448536 * 50.0) ** 2))
    assert model.half_widths_m3(base) == pytest.approx((math.hypot(60.0, 10.0), math.hypot(60.0, 20.0)))
    from scipy.stats import norm
    assert LEVEL_Z == pytest.approx(norm.ppf(0.95))


def test_that_untied_stretches_widen_the_interval_by_their_stated_sigma_as_the_level_does():
    model = IntervalModel(k_unseen=1, k_interpolation=2, k_noise=1, k_sweeps=1, k_faces=1)
    base = ErrorTerms(interpolation_m3=30.0, unseen_low_m3=10.0)
    below, _ = model.half_widths_m3(replace(base, untied_m3=50.0))
    assert below == pytest.approx(math.sqrt(60.0**2 + 10.0**2 + (LEVEL_Z * 50.0) ** 2))
    assert model.k_untied == LEVEL_Z


def test_that_a_level_on_the_logged_reference_is_warned_about_when_it_holds_a_wide_interval():
    model = IntervalModel(k_unseen=1, k_interpolation=1, k_noise=1, k_sweeps=1, k_faces=1)
    w = level_warning(ErrorTerms(interpolation_m3=10.0, level_m3=80.0), model, 1200.0, 5.0)  # +/-132 m³: 11 %
    assert w is not None and "+/-132 m³ (11.0 % of the volume)" in w and "logged altitude reference" in w, w
    assert "wall's foot or a strip of clear floor" in w
    named = level_warning(ErrorTerms(interpolation_m3=10.0, level_m3=80.0), model, 1200.0, 5.0, 0.02)
    assert "(a walk of 0.02 m/sqrt(s) believed, --baro-walk)" in named, named  # the drift it assumed, and the option
    assert level_warning(ErrorTerms(interpolation_m3=10.0, level_m3=10.0), model, 1200.0, 5.0) is None  # 16 m³
    assert level_warning(ErrorTerms(interpolation_m3=200.0, level_m3=80.0), model, 1200.0, 5.0) is None  # not most
    assert level_warning(ErrorTerms(interpolation_m3=10.0), model, 1200.0, 5.0) is None  # a floor pinned it


def test_that_a_height_anchored_on_an_open_floor_is_warned_about_with_the_other_readings_interval():
    # Were the floor seen only away from the walls a hollow, the level would be the logged reference's: the volume
    # less what the anchor moved, with the reference's drift in its interval (a held-out `vio` flight over pile 2 in
    # the 24 x 16 m building: anchored 1,037 m³, true 1,192 m³, this reading 1,143 m³ (1,012-1,274 m³)).
    grid = Grid(24.0, 16.0, 1.0)
    heights = np.full(grid.shape, 3.0)  # 384 m² surfaced
    model = IntervalModel(k_unseen=1, k_interpolation=1, k_noise=1, k_sweeps=1, k_faces=1)
    terms = ErrorTerms(interpolation_m3=12.0)
    w = open_floor_warning(-0.28, heights, grid, 1037.0, 5.0, 0.2, terms, model)
    other, half = 1037.0 + 0.28 * 384.0, math.hypot(12.0, LEVEL_Z * 0.2 * 384.0)
    assert f"the volume is about {other:,.0f} m³ instead" in w, w
    assert f"(90 % interval {other - half:,.0f}-{other + half:,.0f} m³" in w, w
    assert "this report's 90 % interval does not include" in w
    assert "beyond the 90 % interval" in open_floor_warning(-0.28, heights, grid, 1037.0, 5.0)  # no sigma: as before
    # the same reading as data, for report.json and the verdict
    reading = open_floor_reading(-0.28, heights, grid, 1037.0, 5.0, 0.2, terms, model)
    assert reading.volume_m3 == pytest.approx(other) and reading.interval_m3 == pytest.approx(
        (other - half, other + half))
    assert reading.as_dict()["condition"] == "the floor seen only away from the walls is a hollow in the pile"
    assert open_floor_reading(-0.28, heights, grid, 1037.0, 5.0).interval_m3 is None  # no sigma: no interval
    assert open_floor_reading(-0.01, heights, grid, 1037.0, 5.0, 0.2, terms, model) is None  # moved too little
    assert open_floor_reading(None, heights, grid, 1037.0, 5.0, 0.2, terms, model) is None  # a confirmed floor
    # the other reading's level spans the whole flight, so the anchored reading's untied stretches are in it
    untied = replace(terms, untied_m3=40.0)
    assert open_floor_reading(-0.28, heights, grid, 1037.0, 5.0, 0.2, untied, model).interval_m3 == pytest.approx(
        (other - half, other + half))
