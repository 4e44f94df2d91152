"""The sensor-noise math: its statistics (seeded, with bounds several standard errors wide) and its seams."""

import math

import numpy as np
import pytest

from firmware_py.core.sensor import LIDARLITE_V3, TFMINI_S, ReturnModel
from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel
from sitl.sensing.noise import (
    PoseNoiser,
    RangeNoiser,
    ServoNoiser,
    angle_errors,
    datasheet_sigma_m,
    dropout_probability,
    measured_ranges,
    noise_streams,
    pose_errors_at,
    quantise,
)

N = 200_000  # the std of a sample std is sigma / sqrt(2N) = 0.16 % of sigma: 3 % bounds are ~19 of them


def draws(model, spec, r, seed=0, cos_i=1.0):
    return measured_ranges(np.full(N, r), SensorNoise.of(model, spec), noise_streams(seed), cos_i)


@pytest.mark.parametrize("spec", [LIDARLITE_V3, TFMINI_S])
@pytest.mark.parametrize("r", [1.0, 2.4])
def test_that_datasheet_noise_near_the_sensor_has_the_absolute_sigma(spec, r):
    got = draws(SensorNoiseModel.DATASHEET, spec, r)
    assert np.isfinite(got).all()  # head-on, well inside the rated range: every echo returns
    assert got.std() == pytest.approx(spec.range_sigma_m, rel=0.03)
    assert abs(got.mean() - r) < 5 * spec.range_sigma_m / math.sqrt(N)  # no bias (the datasheets state none)


def test_that_datasheet_noise_grows_with_the_range_as_the_relative_figure():
    r = 20.0  # LIDAR-Lite: 1 % of 20 m = 20 cm > 2.5 cm; within its effective range at rho 0.3
    got = draws(SensorNoiseModel.DATASHEET, LIDARLITE_V3, r)
    ok = np.isfinite(got)
    assert ok.all()
    assert got.std() == pytest.approx(0.01 * r, rel=0.03)
    assert datasheet_sigma_m(np.array([1.0, 2.5, 20.0]), LIDARLITE_V3) == pytest.approx([0.025, 0.025, 0.2])


def test_that_the_return_range_scales_with_the_square_root_of_reflectance_and_incidence():
    # The inverse-square law of an extended diffuse target: 12 m on the 90 % board, 4 m at 10 %, 6.9 m at the
    # model's 30 % (the TFMini datasheets rate 10 % at 4-7 m: the law is the pessimistic end).
    rm = ReturnModel(0.9, target_reflectance=0.1)
    assert rm.effective_range_m(TFMINI_S.max_range_m) == pytest.approx(4.0)
    assert ReturnModel(0.9).effective_range_m(TFMINI_S.max_range_m) == pytest.approx(12 * math.sqrt(1 / 3))
    assert rm.effective_range_m(TFMINI_S.max_range_m, 0.25) == pytest.approx(2.0)


def test_that_no_returns_rise_from_zero_to_one_over_the_ramp_before_the_effective_range():
    rm = ReturnModel(0.7, target_reflectance=0.7, dropout_ramp_rel=0.1)  # effective range = 40 m head on
    p = dropout_probability(np.array([10.0, 35.9, 38.0, 40.0, 45.0, np.nan]), np.ones(6), LIDARLITE_V3, rm)
    assert p == pytest.approx([0.0, 0.0, 0.5, 1.0, 1.0, 1.0])
    # at 60 deg incidence the range shrinks by sqrt(cos 60): 40 m -> 28.3 m
    assert dropout_probability(np.array([28.3]), np.array([0.5]), LIDARLITE_V3, rm)[0] > 0.95


def test_that_the_drawn_no_returns_follow_the_probability_and_grazing_incidence_and_low_reflectance_cost_returns():
    noise = SensorNoise.of(SensorNoiseModel.DATASHEET, LIDARLITE_V3)  # rho 0.3: effective 26.2 m head on
    r_eff = noise.returns.effective_range_m(LIDARLITE_V3.max_range_m)
    mid = r_eff * (1 - noise.returns.dropout_ramp_rel / 2)
    got = measured_ranges(np.full(N, mid), noise, noise_streams(1))
    assert np.isnan(got).mean() == pytest.approx(0.5, abs=0.01)
    head_on = measured_ranges(np.full(N, 15.0), noise, noise_streams(2), 1.0)
    grazing = measured_ranges(np.full(N, 15.0), noise, noise_streams(2), math.cos(math.radians(80)))
    assert np.isnan(head_on).mean() == 0.0 and np.isnan(grazing).mean() == 1.0


def test_that_appendix_a_range_noise_is_2_5_cm_at_any_range_and_drops_nothing():
    for r in (3.0, 30.0):
        got = draws(SensorNoiseModel.APPENDIX_A, LIDARLITE_V3, r)
        assert np.isfinite(got).all() and got.std() == pytest.approx(0.025, rel=0.03)


def test_that_none_returns_the_true_ranges_untouched():
    r = np.array([1.234567, np.nan, 39.0])
    assert np.array_equal(measured_ranges(r, SensorNoise.of("none", LIDARLITE_V3), noise_streams(0)), r,
                          equal_nan=True)


def test_that_quantise_rounds_to_the_range_quantum():
    assert quantise(np.array([1.234, 1.236, np.nan]), 0.01) == pytest.approx([1.23, 1.24, np.nan], nan_ok=True)
    assert quantise(np.array([1.234]), 0.0)[0] == 1.234


def test_that_servo_angle_errors_have_the_stated_sigma():
    e = angle_errors(N, math.radians(1.0), np.random.default_rng(0))
    assert e.std() == pytest.approx(math.radians(1.0), rel=0.03) and abs(e.mean()) < 5 * math.radians(1.0) / N ** 0.5


def test_that_pose_errors_are_one_draw_per_message_interpolated_between_two_as_the_payload_does():
    t = np.arange(0, 400.0, 0.002)  # 500 Hz for 400 s: 20,000 messages at 50 Hz
    e = pose_errors_at(t, 0.02, 0.113, np.random.default_rng(0))
    at_messages = e[::10]  # samples that fall on a message carry its full draw
    assert at_messages.std() == pytest.approx(0.113, rel=0.03)
    f = np.arange(10) / 10  # ten samples per message period
    assert e.std() == pytest.approx(0.113 * math.sqrt(np.mean((1 - f) ** 2 + f ** 2)), rel=0.03)
    mid = e[5::10]  # half-way between two messages: (e_k + e_(k+1)) / 2
    assert mid.std() == pytest.approx(0.113 * math.sqrt(0.5), rel=0.03)
    assert np.abs(e).max() <= np.abs(at_messages).max() + 1e-12  # an interpolation never exceeds its knots
    late = e[9::10]  # 18 ms after a message: 0.1 e_k + 0.9 e_(k+1), the same draw as the next message's
    assert np.corrcoef(late[:-1, 0], at_messages[1:, 0])[0, 1] > 0.99


def test_that_each_error_source_has_its_own_stream_so_one_does_not_shift_another():
    a, b = noise_streams(7), noise_streams(7)
    b["servo"].normal(size=1000)  # draw servo errors in one run only
    assert a["range"].normal() == b["range"].normal()
    assert noise_streams(7)["range"].normal() != noise_streams(8)["range"].normal()


def test_that_the_per_sample_noisers_draw_what_the_batch_functions_draw():
    noise = SensorNoise.of(SensorNoiseModel.APPENDIX_A, LIDARLITE_V3)
    one = RangeNoiser(noise, noise_streams(3))
    got = np.array([one.measure(10.0) for _ in range(2000)])
    assert got == pytest.approx(measured_ranges(np.full(2000, 10.0), noise, noise_streams(3)))
    assert one.measure(None) is None and one.measure(math.nan) is None
    servo = ServoNoiser(noise, noise_streams(4))
    assert [servo.error() for _ in range(3)] == pytest.approx(angle_errors(3, noise.servo_sigma_rad,
                                                                           noise_streams(4)["servo"]))
    pose = PoseNoiser(noise, noise_streams(5))
    assert pose.position() == pytest.approx(tuple(noise_streams(5)["position"].normal(0, 0.113, 3)))


def test_that_a_datasheet_no_return_reaches_the_emulator_as_none():
    noise = SensorNoise.of(SensorNoiseModel.DATASHEET, TFMINI_S)
    one = RangeNoiser(noise, noise_streams(0), incidence=lambda: 1.0)
    assert one.measure(TFMINI_S.max_range_m) is None  # beyond the effective range at rho 0.3
    assert one.measure(2.0) is not None
