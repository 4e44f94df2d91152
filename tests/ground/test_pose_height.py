"""The pose correction's height (ground/pose_height.py): the floor's level read within its own scatter, a pile's toe
kept out of the floor, where the height is tied to the floor, and the level's and the untied stretches' standard
errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ground.plane_stretches import beams, stretch_floor_m
from ground.pose_height import (
    MIN_TIE_CELLS,
    crossings_misfit_m,
    floor_anchored,
    floor_from_below,
    floor_half_width,
    half_sample_mode,
    level_sigma_m,
    level_window,
    lowest_window,
    raised_floor_note,
    unanchored_stretches,
    untied_sigma_m,
)
from ground.pose_knots import BAND
from tests.ground.test_pose_correction import FRAME, LEVER, RESOLUTION, STORAGE, _height_walk, flight


def test_that_the_level_sigma_is_that_of_a_random_walk_s_mean_over_the_flight():
    # The mean over T of a walk of q per sqrt(s) from 0 has variance q^2 T / 3: 4,000 walks of 600 steps (seeded).
    rng = np.random.default_rng(0)
    q, dt, n = 0.05, 0.1, 600
    means = np.cumsum(rng.normal(0.0, q * math.sqrt(dt), (4000, n)), axis=1).mean(axis=1)
    assert float(np.std(means)) == pytest.approx(level_sigma_m(q, n * dt), rel=0.05)
    assert level_sigma_m(q, 0.0) == 0.0 and level_sigma_m(q, -1.0) == 0.0


def test_that_the_floor_kept_under_a_flat_top_is_the_level_s_own_cluster_not_the_pile_s_toe():
    # Under a degree of pointing noise the crossings' spread on slopes is 0.23 m, and three of it (0.7 m) reached a
    # pile's toe, which the height's joint solve then held at the floor's level (0.6 m of height error). The floor
    # is flat: its heights scatter by their own noise, and that sets how far from the level the floor is kept.
    rng = np.random.default_rng(4)
    floor = rng.normal(0.0, 0.05, 12)
    toe = np.array([0.60, 0.61])
    lowest = np.sort(np.concatenate([floor, toe]))
    half = floor_half_width(lowest, float(np.median(lowest)), 0.70, 0.125, np.full(14, 12))
    assert np.abs(floor - np.median(lowest)).max() < half < 0.60 - np.median(lowest)
    # an ideal sensor's floor: the typical median's own noise sets the width, and tol caps it
    exact = floor_half_width(np.zeros(5), 0.0, 0.05, 0.003, np.full(5, 9))
    assert exact == pytest.approx(BAND * 0.003 / 3.0)
    assert floor_half_width(np.array([0.0, 1.0, -1.0]), 0.0, 0.05, 0.003, np.full(3, 9)) == 0.05


def test_that_the_floor_s_level_is_read_within_the_floor_s_own_scatter_not_up_the_toe_s_ramp():
    # A pile that hides most of the floor, under a degree of pointing noise: a few floor cells seen, and above them
    # the toe rises with no gap; the crossings' spread on the slopes (tol) is 0.7 m. The level read in a window that
    # tall took in the ramp (0.6-0.9 m of height error on the paper's pile 2). Each cell is seen twice; its two
    # heights differ by the floor's own noise, which sets the level's window.
    rng = np.random.default_rng(7)
    floor_cells, toe_cells = np.arange(8), np.arange(8, 48)
    truth = np.concatenate([np.zeros(8), np.linspace(0.1, 1.0, 40)])
    cell = np.concatenate([floor_cells, toe_cells, floor_cells, toe_cells])
    med = np.tile(truth, 2) + rng.normal(0.0, 0.04, 2 * len(truth))
    counts = np.full(len(med), 10)
    order = np.argsort(med)
    cell, med, counts = cell[order], med[order], counts[order]
    tol, stray = 0.70, 10.0
    i0, i1 = lowest_window(med, counts, tol, stray)
    wide = float(np.median(med[i0:i1]))
    width = level_window(cell, med, counts, 0.12, 0.0, tol)
    assert 0.04 * BAND * 0.7 < width < 0.04 * BAND * 1.5
    j0, j1 = lowest_window(med, counts, width, stray)
    narrow = float(np.median(med[j0:j1]))
    assert wide > 0.25  # up the ramp
    assert abs(narrow) < 0.06, narrow  # the floor's level, within its noise
    # the frame's spread caps the window; a window nobody fills gives None
    assert level_window(cell, med * 100.0, counts, 0.12, 0.0, tol) == tol
    # the frame's misalignment between times widens it (a flat floor's heights carry it)
    assert level_window(cell, med, counts, 0.12, 0.1, tol) == pytest.approx(BAND * 0.1)
    assert lowest_window(med, counts, width, 1e6) is None


def test_that_the_half_sample_mode_finds_a_peak_a_one_sided_tail_lifts_the_median_of():
    rng = np.random.default_rng(3)
    floor = rng.normal(0.0, 0.1, 600)
    toe = rng.uniform(0.2, 0.87, 260)  # a pile's toe within the floor candidates' band
    heights = np.concatenate([floor, toe])
    assert np.median(heights) > 0.05
    assert abs(half_sample_mode(heights)) < 0.03
    assert half_sample_mode(np.array([1.0, 2.0, 2.1])) == pytest.approx(2.05)
    assert half_sample_mode(np.array([4.0])) == 4.0
    with pytest.raises(ValueError):
        half_sample_mode(np.array([]))


def test_that_floor_candidates_lose_a_pile_s_toe_and_keep_a_symmetric_floor_whole():
    rng = np.random.default_rng(4)
    n_floor, n_toe = 600, 260
    knots = np.array([0.0, 100.0])
    t = np.linspace(0.0, 100.0, n_floor + n_toe)
    z_true = np.concatenate([rng.normal(0.0, 0.1, n_floor), rng.uniform(0.35, 0.87, n_toe)])
    p = np.column_stack([np.zeros((len(t), 2)), z_true - 0.05])  # the solved height puts the floor 5 cm low
    floor = np.ones(len(t), dtype=bool)
    kept = floor_from_below(p, t, knots, np.full(2, 0.05), floor, 3.0)
    assert not kept[n_floor:].any()  # the toe, beyond the floor's own scatter above its level
    assert kept[:n_floor].mean() > 0.98
    only_floor = np.arange(len(t)) < n_floor
    assert floor_from_below(p, t, knots, np.full(2, 0.05), only_floor, 3.0) is only_floor  # nothing to drop


def _sightings(spec: list[tuple[int, float, float, float]], knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and times: per (knot interval, x, y, z), five points in that cell at the interval's middle."""
    p, t = [], []
    for interval, x, y, z in spec:
        for i in range(5):
            p.append((x + 0.05 * i, y, z))
            t.append(0.5 * (knots[interval] + knots[interval + 1]))
    return np.array(p), np.array(t)


def _cells(n: int, first: int, second: int, x0: float, z: float = 3.0) -> list[tuple[int, float, float, float]]:
    """n pile cells (1.5 m apart along y at x0), each seen in interval first and again in interval second."""
    return [(iv, x0, 1.2 + 1.5 * c, z) for c in range(n) for iv in (first, second)]


def test_that_the_height_is_tied_to_the_floor_only_where_the_floor_or_a_pile_seen_on_another_pass_ties_it():
    # The floor in intervals 0 and 9; MIN_TIE_CELLS pile cells seen in interval 0 and again in 6 (another pass) tie
    # 6; a pile cell seen in 2, 3 and 4 (one pass moving on) ties nothing: that is the chain whose errors add up.
    knots = np.arange(0.0, 31.0, 3.0)
    p, t = _sightings([(0, 1.2, 1.2, 0.0), *_cells(MIN_TIE_CELLS, 0, 6, 5.2), (2, 10.2, 10.2, 2.0),
                       (3, 10.2, 10.2, 2.0), (4, 10.2, 10.2, 2.1), (9, 30.2, 20.2, 0.0)], knots)
    floor = p[:, 2] == 0.0
    tied = floor_anchored(p, t, knots, np.zeros(len(p), dtype=bool), floor, STORAGE, 1.5)
    np.testing.assert_array_equal(np.flatnonzero(tied), [0, 6, 9])
    # 1-5 counts (the longest, 3-18 s); 7-8 is two intervals, within a pass's reach of tied ones on both sides
    assert unanchored_stretches(knots, tied) == (15.0, 3.0, 18.0)
    assert unanchored_stretches(knots, np.arange(len(knots) - 1) != 4) == (0.0, 0.0, 0.0)
    # the chain on one pass does not tie even when it reaches the floor's interval's neighbour
    p2, t2 = _sightings([(0, 1.2, 1.2, 0.0), (1, 10.2, 10.2, 2.0), (2, 10.2, 10.2, 2.0)], knots)
    tied2 = floor_anchored(p2, t2, knots, np.zeros(len(p2), dtype=bool), p2[:, 2] == 0.0, STORAGE, 1.5)
    np.testing.assert_array_equal(np.flatnonzero(tied2), [0])
    assert unanchored_stretches(knots, np.ones(len(knots) - 1, dtype=bool)) == (0.0, 0.0, 0.0)


def test_that_a_stretch_hanging_on_a_handful_of_cells_is_not_tied_and_routes_that_share_none_add_up():
    """The far half of a loop over the paper's pile 2 at P_traj 5 % hangs on 5-7 cells seen from both long legs, and
    its height came out 4-11 cm off: a tie needs MIN_TIE_CELLS cells, counted over routes that share no cell."""
    knots = np.arange(0.0, 31.0, 3.0)
    floor = [(0, 1.2, 1.2, 0.0)]

    def tied(spec):
        p, t = _sightings(floor + spec, knots)
        return np.flatnonzero(floor_anchored(p, t, knots, np.zeros(len(p), dtype=bool), p[:, 2] == 0.0, STORAGE,
                                             1.5))

    np.testing.assert_array_equal(tied(_cells(MIN_TIE_CELLS - 1, 0, 6, 5.2)), [0])  # one cell short: not tied
    half = MIN_TIE_CELLS // 2
    # two routes to interval 6 that share no cell: half the cells directly, the rest by way of interval 3
    routes = _cells(half, 0, 6, 5.2) + _cells(MIN_TIE_CELLS - half, 0, 3, 9.2) + _cells(MIN_TIE_CELLS - half, 3, 6,
                                                                                          13.2)
    np.testing.assert_array_equal(tied(routes), [0, 3, 6])
    # a bottleneck: interval 6 reached only through interval 3, by fewer cells than a tie needs beyond it
    bottleneck = _cells(MIN_TIE_CELLS, 0, 3, 9.2) + _cells(MIN_TIE_CELLS - 1, 3, 6, 13.2)
    np.testing.assert_array_equal(tied(bottleneck), [0, 3])


def test_that_an_untied_stretch_s_sigma_is_the_walk_pinned_at_its_tied_ends_weighted_by_its_share():
    # Between two tied moments the altitude reference's walk is a Brownian bridge: the mean over a stretch of T s has
    # variance q^2 T / 12 (4,000 bridges of 300 steps, seeded); at the flight's start or end, open on one side, a
    # walk from the tied end, q^2 T / 3. Each is weighted by its share of the flight; stretches add in quadrature.
    rng = np.random.default_rng(0)
    q, dt, n = 0.05, 0.1, 300
    walk = np.cumsum(rng.normal(0.0, q * math.sqrt(dt), (4000, n)), axis=1)
    bridge = walk - walk[:, -1:] * np.arange(1, n + 1) / n
    knots = np.arange(0.0, 91.0, 3.0)  # 30 intervals, 90 s
    tied = np.ones(30, dtype=bool)
    tied[10:20] = False  # 30 s between tied moments
    share = 30.0 / 90.0
    assert untied_sigma_m(knots, tied, q) == pytest.approx(float(np.std(bridge.mean(axis=1))) * share, rel=0.05)
    assert untied_sigma_m(knots, tied, q) == pytest.approx(q * math.sqrt(30.0 / 12.0) * share)
    open_end = np.ones(30, dtype=bool)
    open_end[20:] = False  # the last 30 s: nothing after it ties it
    assert untied_sigma_m(knots, open_end, q) == pytest.approx(q * math.sqrt(30.0 / 3.0) * share)
    both = tied.copy()
    both[24:] = False  # and the last 18 s, apart from the first stretch
    assert untied_sigma_m(knots, both, q) == pytest.approx(math.hypot(q * math.sqrt(30.0 / 12.0) * share,
                                                                      q * math.sqrt(18.0 / 3.0) * 18.0 / 90.0))
    short = np.ones(30, dtype=bool)
    short[10:12] = False  # two intervals: within a pass's reach of tied ones, as `unanchored_stretches` counts
    assert untied_sigma_m(knots, short, q) == 0.0
    assert untied_sigma_m(knots, np.ones(30, dtype=bool), q) == 0.0


def test_that_the_note_on_a_floor_taken_down_says_within_what():
    assert "0.20 m above z = 0, level and within the 0.39 m" in raised_floor_note(-0.2, 0.004, np.full(5, -0.2), 0.39)
    rangefinder = raised_floor_note(-0.2, 0.004, np.full(5, -0.2), math.inf)
    assert "downward rangefinder" in rangefinder and "inf" not in rangefinder
    assert "0.20 m below z = 0" in raised_floor_note(0.2, 0.004, np.full(5, 0.2))


def test_that_the_pile_seen_at_different_times_agrees_on_a_true_height_and_not_on_a_walking_one():
    samples, err = flight(_height_walk(0.03, seed=3))
    clean, _ = flight()
    knots = np.arange(0.0, samples["t_s"][-1] + 3.0, 3.0)
    truth = -np.interp(knots, samples["t_s"], err[:, 2])

    def misfit(s: np.ndarray, z: np.ndarray) -> float:
        b, _ = beams(s, LEVER, FRAME)
        p = b.vehicle_w + b.to_point_w
        wall = (p[:, 0] < 0.2) | (p[:, 0] > 59.8) | (p[:, 1] < 0.2) | (p[:, 1] > 39.8)
        return crossings_misfit_m(p, b.t_s, knots, z, wall, STORAGE, 3.0, 5.0, stretch_floor_m(RESOLUTION))

    (walking, noise), (corrected, _) = misfit(samples, np.zeros(len(knots))), misfit(samples, truth)
    assert walking > 0.05  # decimetres of walk: the pile's top seen at different heights ...
    assert 0.0 < noise < walking / 5  # ... far beyond the sightings' own noise (medians of their points)
    # the true height at the knots, linear between (what the walk does within 3 s is left) and an error-free flight
    assert corrected < walking / 4 and misfit(clean, np.zeros(len(knots)))[0] < 0.005
