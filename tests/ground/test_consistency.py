"""The two sweep directions must see the same surface; a wrong servo model makes them disagree."""

import numpy as np

from ground.consistency import sweep_disagreement_m
from ground.surface import Grid


def test_that_agreeing_sweeps_measure_near_zero_and_shifted_ones_their_shift():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 10, (20_000, 2))
    z = 1.0 + 0.1 * xy[:, 0]
    d = np.where(rng.random(len(xy)) < 0.5, 1, -1)
    grid = Grid(10, 10, 0.25)
    agree, n = sweep_disagreement_m(np.column_stack([xy, z]), d, grid)
    assert n > 1000 and agree < 0.02
    shifted, _ = sweep_disagreement_m(np.column_stack([xy, z + np.where(d > 0, 0.5, 0.0)]), d, grid)
    assert abs(shifted - 0.5) < 0.05


def test_that_too_little_overlap_gives_no_verdict():
    pts = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0]])
    assert sweep_disagreement_m(pts, np.array([1, -1]), Grid(10, 10, 0.25)) == (None, 0)
