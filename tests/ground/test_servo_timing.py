"""Re-estimating a servo's real motion: the re-timing itself and the search (the whole path, on
flights with a delayed or slow servo, is in tests/sitl/faults/test_injector.py)."""

import numpy as np
import pytest

from firmware_py.core.samplelog import SAMPLE_DTYPE
from firmware_py.core.servo_model import ServoCalibration, modelled_sweep
from firmware_py.core.waveform import Waveform
from ground.servo_timing import (
    DELAY_RANGE_S,
    GAIN_RANGE,
    Resimulated,
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
    assert st.disagreement_after_m < st.disagreement_before_m and st.evaluations < 250


def test_that_an_unmeasurable_disagreement_gives_no_estimate():
    assert estimate_servo_timing(triangle_samples(), lambda _s: None, before_m=1.0) is None


def test_that_the_search_bounds_cover_real_servo_faults():
    assert DELAY_RANGE_S[0] < 0 < 0.1 < DELAY_RANGE_S[1] and GAIN_RANGE[0] <= 0.5 and GAIN_RANGE[1] > 1.0


def test_that_a_speed_factor_is_only_kept_when_it_beats_the_delay_alone_by_more_than_the_noise():
    s = triangle_samples()

    real = retimed(s, 0.03, 1.0, 0.2)["servo_rad"] - 0.2

    def biased(candidate):  # the right delay is 30 ms, and a smaller swing always looks a little better
        a = candidate["servo_rad"] - 0.2
        g = max(np.ptp(a) / np.ptp(real), 1e-6)
        return float(np.median(np.abs(a / g - real)[200:-200]) + 0.015 * g)

    st = estimate_servo_timing(s, biased, before_m=1.0, floor_m=0.02)
    assert st.gain == 1.0 and st.delay_s == pytest.approx(0.03, abs=0.002)
    assert estimate_servo_timing(s, biased, before_m=1.0, floor_m=0.0).gain != 1.0  # without the rule: fooled


HEADER = {"servo": {"shape_c": 0.95, "frequency_hz": 0.67, "amplitude_rad": 1.5, "phase_rad": 0.1, "direction": 1},
          "servo_calibration": {"center_us": 1500.0, "us_per_rad": 318.3, "min_us": 1000.0, "max_us": 2000.0,
                                "slew_rad_s": 5.0, "lag_s": 0.02},
          "servo_drive": {"t0_s": 50.0, "frame_s": 0.02}}


def test_that_the_servo_is_re_simulated_from_the_header_and_a_nominal_fit_changes_nothing():
    m = Resimulated.from_header(HEADER)
    assert m.t0_s == 50.0 and m.cal.slew_rad_s == 5.0 and m.waveform.amplitude_rad == 1.5
    s = triangle_samples(n=3000)
    s["t_s"] = 50.0 + np.arange(3000) / 500.0
    wf, cal = Waveform(0.95, 0.67, 1.5, 0.1, 1), ServoCalibration(us_per_rad=318.3)
    s["servo_rad"] = modelled_sweep(wf, cal, s["t_s"] - 50.0)
    assert np.allclose(m.apply(s, 0.0, 1.0)["servo_rad"], s["servo_rad"], atol=1e-6)
    slow = m.apply(s, 0.0, 0.6)["servo_rad"]
    truth = modelled_sweep(wf, ServoCalibration(us_per_rad=318.3, slew_rad_s=3.0), s["t_s"] - 50.0)
    assert np.abs(slow - truth).max() < 1e-6
    for broken in ({}, {**HEADER, "servo_drive": {"t0_s": "x", "frame_s": 0.02}},
                   {**HEADER, "servo_calibration": {"slew_rad_s": -1.0}}, {**HEADER, "servo_drive": None}):
        assert Resimulated.from_header(broken) is None


def test_that_a_drive_is_used_only_for_samples_it_can_have_driven():
    """A start a clock fault moved by days would make the re-simulation step every 20 ms frame since then."""
    m = Resimulated.from_header(HEADER)  # started at t = 50 s
    t = 50.0 + np.arange(3000) / 500.0
    assert m.drives(t) and m.drives(t + 800.0)  # a wait on the ground before the first sample
    assert not m.drives(t - 10.0) and not m.drives(t + 1e7) and not m.drives(np.array([np.nan]))


def test_that_the_search_on_several_threads_tries_the_same_candidates_and_finds_the_same_timing():
    """Each candidate is independent: on two threads the search is the same search, only sooner (the report runs it
    on every core, `ground.report`)."""
    m = Resimulated.from_header(HEADER)
    s = triangle_samples(n=3000)
    s["t_s"] = 50.0 + np.arange(3000) / 500.0
    real = m.apply(s, 0.06, 0.7)["servo_rad"]
    tried = {1: [], 2: []}

    def disagreement(threads):
        def of(candidate):
            tried[threads].append(float(candidate["servo_rad"][1234]))
            return float(np.median(np.abs(candidate["servo_rad"] - real)))
        return of

    one = estimate_servo_timing(s, disagreement(1), before_m=1.0, motion=Resimulated.from_header(HEADER))
    two = estimate_servo_timing(s, disagreement(2), before_m=1.0, motion=Resimulated.from_header(HEADER), threads=2)
    assert one == two and one.delay_s == pytest.approx(0.06, abs=0.003) and one.gain == pytest.approx(0.7, abs=0.011)
    assert sorted(tried[1]) == sorted(tried[2]) and len(tried[1]) == one.evaluations


def test_that_a_drive_steps_its_pulses_once_a_speed_for_every_delay_and_answers_as_the_model_does(monkeypatch):
    import ground.servo_timing as st

    m = Resimulated.from_header(HEADER)
    t = 50.0 + np.arange(3000) / 500.0
    stepped = []
    real = st.sweep_states
    monkeypatch.setattr(st, "sweep_states", lambda *a, **k: stepped.append(a[1].slew_rad_s) or real(*a, **k))
    for gain in (1.0, 0.6):
        for delay in (DELAY_RANGE_S[1], 0.0, 0.037, DELAY_RANGE_S[0]):  # the longest horizon asked last
            cal = ServoCalibration(**{**HEADER["servo_calibration"], "slew_rad_s": 5.0 * gain})
            assert np.array_equal(m.angles(t, delay, gain), modelled_sweep(m.waveform, cal, t - 50.0 - delay, 0.02))
    assert stepped == [5.0, 3.0]  # one stepping a speed, to the span of the delays searched
    m.angles(t + 1.0, 0.0, 1.0)  # later samples than any stepped for: stepped again
    assert stepped == [5.0, 3.0, 5.0]
