import math

import numpy as np
import pytest

from firmware_py.core.waveform import (
    N_PHASES,
    Waveform,
    frequency_for_peak_rate,
    initial_position,
    named_waveform,
    servo_angle,
    servo_rate,
)


def test_that_table1_peak_rate_gives_the_papers_frequencies():
    # Table 1: 5 rad/s peak -> f = 0.67 Hz at C = 0.95; Sec. 4.2: sinusoid -> 0.5 Hz.
    assert frequency_for_peak_rate(5.0, 0.95) == pytest.approx(0.67, abs=0.005)
    assert frequency_for_peak_rate(5.0, 0.0) == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("c", [0.0, 0.5, 0.95])
@pytest.mark.parametrize("k", [0, 3, 10, 17])
def test_that_rate_is_the_derivative_of_angle(c, k):
    wf = named_waveform("semi-triangular" if c else "sinusoidal", k=k)
    wf = Waveform(shape_c=c, frequency_hz=wf.frequency_hz, phase_rad=wf.phase_rad, direction=wf.direction)
    t = np.linspace(0, 3, 30001)
    numeric = np.gradient(wf.angle(t), t)
    assert np.allclose(wf.rate(t)[5:-5], numeric[5:-5], atol=2e-3 * wf.peak_rate_rad_s)
    assert np.max(np.abs(wf.rate(t))) == pytest.approx(wf.peak_rate_rad_s, rel=1e-4)


def test_that_the_sweep_reaches_plus_minus_90_degrees():
    wf = named_waveform("semi-triangular")
    a = wf.angle(np.linspace(0, 1 / wf.frequency_hz, 10001))
    assert a.max() == pytest.approx(math.pi / 2, abs=1e-6)
    assert a.min() == pytest.approx(-math.pi / 2, abs=1e-6)


def test_that_small_c_tends_to_the_sinusoid():
    t = np.linspace(0, 2, 101)
    assert np.allclose(servo_angle(t, 1e-7, 0.5), servo_angle(t, 0.0, 0.5), atol=1e-9)
    assert np.allclose(servo_rate(t, 1e-7, 0.5), servo_rate(t, 0.0, 0.5), atol=1e-9)


def test_that_the_20_initial_positions_are_distinct_and_pair_up_in_opposite_directions():
    starts = []
    for k in range(2 * N_PHASES):
        wf = named_waveform("semi-triangular", k=k)
        starts.append((round(float(wf.angle(0.0)), 9), int(np.sign(wf.rate(0.0)))))
    assert len(set(starts)) == 2 * N_PHASES
    for k in range(N_PHASES):
        assert starts[k][0] == starts[k + N_PHASES][0]
        assert starts[k][1] == -starts[k + N_PHASES][1]


def test_that_sweep_direction_follows_the_rate_sign():
    wf = named_waveform("sinusoidal", k=4)
    t = np.linspace(0, 4, 999)
    assert np.array_equal(wf.sweep_direction(t), np.where(wf.rate(t) >= 0, 1, -1))


@pytest.mark.parametrize("name", ["semi-triangular", "sinusoidal"])
@pytest.mark.parametrize("k", [0, 7, 10, 19])
def test_that_the_scalar_sweep_direction_equals_the_vectorised_one(name, k):
    wf = named_waveform(name, k=k)
    t = np.linspace(0, 4, 997)
    assert [wf.sweep_direction_at(float(x)) for x in t] == wf.sweep_direction(t).tolist()


@pytest.mark.parametrize("kwargs", [dict(shape_c=1.0), dict(shape_c=-0.1), dict(frequency_hz=0),
                                    dict(frequency_hz=math.nan), dict(direction=0),
                                    dict(amplitude_rad=2.0), dict(phase_rad=math.inf)])
def test_that_bad_waveforms_are_refused(kwargs):
    with pytest.raises(ValueError):
        Waveform(**kwargs)


def test_that_bad_names_and_positions_are_refused():
    with pytest.raises(ValueError, match="unknown waveform"):
        named_waveform("square")
    with pytest.raises(ValueError, match=r"0\.\.19"):
        initial_position(20)
    with pytest.raises(ValueError):
        frequency_for_peak_rate(-1, 0.95)
