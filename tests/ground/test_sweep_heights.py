"""The corrected height refined sweep by sweep from the floor (`ground.sweep_heights`): a height that wanders faster
than the knots is followed where the sweeps see the floor, noise is not taken for it, and gaps fade to zero."""

from __future__ import annotations

import math

import numpy as np

from firmware_py.core.frames import SQUARE
from ground.pose_correction import PoseCorrection, apply_pose_correction
from ground.sweep_heights import MIN_FLOOR_POINTS, shrunk, sweep_heights, tapered
from tests.ground.test_pose_correction import FRAME, LEVER, NO_PILE, PERIOD_S, RESOLUTION, STORAGE, flight

WAVE_M, WAVE_S = 0.03, 6.0  # a height error knots two sweep periods (3 s) apart cannot follow: two a wave


def _wavy(t: np.ndarray) -> np.ndarray:
    out = np.zeros((len(t), 4))
    out[:, 2] = WAVE_M * np.sin(2.0 * math.pi * t / WAVE_S)
    return out


def _heights(samples: np.ndarray, reach_m: float = 0.15):
    return sweep_heights(samples, LEVER, FRAME, STORAGE, SQUARE, 0.025, 0.0, 0.0, RESOLUTION, 0.0, PERIOD_S / 2.0,
                         reach_m)


def test_that_a_height_wandering_between_the_knots_is_followed_from_the_floor_each_sweep_sees():
    samples, err = flight(_wavy, pile=NO_PILE, duration_s=40.0)
    heights = _heights(samples)
    assert heights is not None and heights.sweeps_used >= 0.9 * heights.sweeps
    t = samples["t_s"].astype(float)
    left = err[:, 2] + heights.at(t)  # the logged height's error once the sweeps' offsets are added
    inner = (t > 2.0) & (t < t[-1] - 2.0)
    assert np.sqrt(np.mean(left[inner] ** 2)) < 0.35 * np.sqrt(np.mean(err[inner, 2] ** 2))
    # placed as the report places them: the correction's `at` adds the sweeps' heights to its knots' (here none)
    knots = np.array([t[0], t[-1]])
    corr = PoseCorrection(knots, np.zeros((2, 4)), np.zeros((2, 4), dtype=bool), True, sweep_heights=heights)
    fixed = apply_pose_correction(samples, corr, FRAME)
    up_w = (FRAME.ned_to_w(np.column_stack([fixed["x_m"], fixed["y_m"], fixed["z_m"]]).astype(float))[:, 2]
            - FRAME.ned_to_w(np.column_stack([samples["x_m"], samples["y_m"], samples["z_m"]]).astype(float))[:, 2])
    assert np.allclose(up_w, heights.at(t))


def test_that_decimetres_of_range_noise_over_a_true_height_are_not_taken_for_a_wander():
    """No height error, 0.2 m of range noise: each sweep's offset is its own error, and shrinking keeps little of it."""
    samples, _ = flight(pile=NO_PILE, duration_s=40.0, noise_m=0.2, seed=3)
    heights = _heights(samples, reach_m=0.6)
    assert heights is None or heights.rms_m() < 0.01


def test_that_offsets_are_kept_whole_when_their_errors_are_nothing_and_dropped_when_they_are_all():
    off = np.array([0.02, -0.01, 0.03, -0.02])
    kept, k = shrunk(off, np.full(4, 1e-4))
    assert k > 0.99 and np.allclose(kept, off, atol=1e-4)
    dropped, k0 = shrunk(off, np.full(4, 0.05))
    assert k0 == 0.0 and not dropped.any()


def test_that_the_offset_fades_to_zero_beyond_the_ends_and_across_a_gap():
    t = np.array([0.0, 0.75, 1.5, 10.0, 10.75])
    ts, zs = tapered(t, np.full(5, 0.02), 0.75)
    assert ts[0] == -0.75 and zs[0] == 0.0 and ts[-1] == 11.5 and zs[-1] == 0.0
    gap = (ts > 1.5) & (ts < 10.0)
    assert np.allclose(ts[gap], [2.25, 9.25]) and not zs[gap].any()
    assert MIN_FLOOR_POINTS >= 3
