"""Re-estimating a servo's real motion: the re-timing itself and the search (the whole path, on
flights with a delayed or slow servo, is in tests/sitl/test_faults.py)."""

import numpy as np
import pytest

from firmware_py.samplelog import SAMPLE_DTYPE
from ground.servo_timing import (
    DELAY_RANGE_S,
    GAIN_RANGE,
    estimate_servo_timing,
    retimed,
    sweep_center_rad,
)


def triangle_samples(delay_s=0.0, gain=1.0, center=0.2, n=5000, rate_hz=500.0, period_s=1.5, amp=1.2):
    """Samples whose logged angle is a triangle sweep about center (the model) and whose sweep_dir
    follows it; `delay_s`/`gain` describe a real shaft we then ask the search to find."""
    t = 100.0 + np.arange(n) / rate_hz
    phase = ((t / period_s) % 1.0)
    tri = np.where(phase < 0.5, -1 + 4 * phase, 3 - 4 * phase)  # -1 .. 1 .. -1
    s = np.zeros(n, dtype=SAMPLE_DTYPE)
    s["t_s"] = t
    s["servo_rad"] = center + amp * tri
    s["sweep_dir"] = np.where(phase < 0.5, 1, -1)
    return s


def test_that_retiming_shifts_the_angle_in_time_and_scales_it_about_the_centre():
    s = triangle_samples()
    out = retimed(s, 0.1, 0.5, 0.2)
    k = np.arange(100, 4000)
    np.testing.assert_allclose(out["servo_rad"][k], 0.2 + 0.5 * (s["servo_rad"][k - 50] - 0.2), atol=1e-6)
    assert np.array_equal(out["sweep_dir"][k], s["sweep_dir"][k - 50])  # it turns back 0.1 s later too
    assert np.array_equal(retimed(s, 0.0, 1.0, 0.2)["servo_rad"], s["servo_rad"])
    assert s["servo_rad"][0] == triangle_samples()["servo_rad"][0]  # the input is left alone


def test_that_the_centre_is_the_middle_of_the_logged_sweep():
    assert sweep_center_rad(triangle_samples(center=0.2)["servo_rad"]) == pytest.approx(0.2, abs=1e-3)
    assert sweep_center_rad(np.array([np.nan])) == 0.0


@pytest.mark.parametrize("true_d, true_g", [(0.03, 1.0), (0.08, 1.0), (0.12, 0.6), (-0.02, 1.1)])
def test_that_the_search_finds_the_delay_and_swing_that_minimise_the_disagreement(true_d, true_g):
    s = triangle_samples()
    real = retimed(s, true_d, true_g, 0.2)["servo_rad"]

    def disagreement(candidate):  # a stand-in for the sweeps' disagreement: distance to the real shaft
        return float(np.median(np.abs(candidate["servo_rad"] - real)[200:-200]))

    st = estimate_servo_timing(s, disagreement, before_m=disagreement(s))
    assert st.delay_s == pytest.approx(true_d, abs=0.003) and st.gain == pytest.approx(true_g, abs=0.011)
    assert st.disagreement_after_m < st.disagreement_before_m and st.evaluations < 200


def test_that_an_unmeasurable_disagreement_gives_no_estimate():
    assert estimate_servo_timing(triangle_samples(), lambda _s: None, before_m=1.0) is None


def test_that_the_search_bounds_cover_real_servo_faults():
    assert DELAY_RANGE_S[0] < 0 < 0.1 < DELAY_RANGE_S[1] and GAIN_RANGE[0] <= 0.5 and GAIN_RANGE[1] > 1.0
