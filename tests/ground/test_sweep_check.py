"""The stuck-servo check: a swept beam's range moves fast, a fixed one's only as fast as the vehicle."""

import numpy as np

from firmware_py.core.waveform import named_waveform
from ground.sweep_check import stuck_sweep_mask


def scene(stuck_after_s=None, noise_m=0.0):
    t = np.arange(0, 12, 0.002)
    wf = named_waveform("semi-triangular")
    gamma = wf.angle(t)
    if stuck_after_s is not None:
        gamma = np.where(t >= stuck_after_s, np.interp(stuck_after_s, t, gamma), gamma)
    # 12 m over a floor, walls 10 m to either side: range of a beam in the y-z plane
    r = np.minimum(12.0 / np.maximum(np.cos(gamma), 1e-6), 10.0 / np.maximum(np.abs(np.sin(gamma)), 1e-6))
    r = r + np.random.default_rng(0).normal(0, noise_m, len(t)) if noise_m else r
    return t, np.round(r, 2), 1.0 / wf.frequency_hz


def test_that_a_sweeping_beam_is_never_flagged_even_with_noise():
    for noise in (0.0, 0.025):
        t, r, period = scene(noise_m=noise)
        assert not stuck_sweep_mask(t, r, np.ones(len(t), bool), period).any()


def test_that_the_periods_after_the_servo_sticks_are_flagged():
    t, r, period = scene(stuck_after_s=4.0, noise_m=0.025)
    m = stuck_sweep_mask(t, r, np.ones(len(t), bool), period)
    assert not m[t < 3.0].any()
    assert m[t > 4.0 + period].mean() > 0.9


def test_that_too_few_samples_are_not_judged():
    t, r, period = scene(stuck_after_s=0.0)
    usable = np.zeros(len(t), bool)
    usable[::200] = True  # ~4 samples a period
    assert not stuck_sweep_mask(t, r, usable, period).any()
