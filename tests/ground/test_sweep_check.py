"""The stuck-servo check: a swept beam's range moves fast, a fixed one's only as fast as the vehicle."""

import numpy as np

from firmware_py.core.waveform import named_waveform
from ground.sweep_check import stuck_sweep_mask


def scene(stuck_after_s=None, noise_m=0.0, height_m=12.0, walls_m=10.0):
    """Times, ranges, sweep period and the logged (commanded) servo angles of a beam swept in the y-z plane
    height_m over a floor between walls walls_m to either side; the shaft sticks at stuck_after_s."""
    t = np.arange(0, 12, 0.002)
    wf = named_waveform("semi-triangular")
    logged = wf.angle(t)
    gamma = logged
    if stuck_after_s is not None:
        gamma = np.where(t >= stuck_after_s, np.interp(stuck_after_s, t, gamma), gamma)
    r = np.minimum(height_m / np.maximum(np.cos(gamma), 1e-6), walls_m / np.maximum(np.abs(np.sin(gamma)), 1e-6))
    r = r + np.random.default_rng(0).normal(0, noise_m, len(t)) if noise_m else r
    return t, np.round(r, 2), 1.0 / wf.frequency_hz, logged


def test_that_a_sweeping_beam_is_never_flagged_even_with_noise():
    for noise in (0.0, 0.025):
        t, r, period, logged = scene(noise_m=noise)
        assert not stuck_sweep_mask(t, r, np.ones(len(t), bool), period).any()
        assert not stuck_sweep_mask(t, r, np.ones(len(t), bool), period, servo_rad=logged).any()


def test_that_the_periods_after_the_servo_sticks_are_flagged():
    t, r, period, logged = scene(stuck_after_s=4.0, noise_m=0.025)
    for m in (stuck_sweep_mask(t, r, np.ones(len(t), bool), period),
              stuck_sweep_mask(t, r, np.ones(len(t), bool), period, servo_rad=logged)):
        assert not m[t < 3.0].any()
        assert m[t > 4.0 + period].mean() > 0.9


def test_that_too_few_samples_are_not_judged():
    t, r, period, _ = scene(stuck_after_s=0.0)
    usable = np.zeros(len(t), bool)
    usable[::200] = True  # ~4 samples a period
    assert not stuck_sweep_mask(t, r, usable, period).any()


def test_that_a_working_sweep_on_the_ground_is_not_blamed_on_the_servo():
    # the vehicle on the floor before take-off, the LiDAR 0.3 m up: a working sweep changes range at under
    # a metre a second, as a stuck one does, so the check cannot tell and does not judge (it flagged them all)
    t, r, period, logged = scene(height_m=0.3, walls_m=0.8, noise_m=0.01)
    assert stuck_sweep_mask(t, r, np.ones(len(t), bool), period).mean() > 0.9  # ranges alone: "stuck"
    assert not stuck_sweep_mask(t, r, np.ones(len(t), bool), period, servo_rad=logged).any()
