import math
from importlib.util import find_spec

import numpy as np
import pytest

from firmware_py.core.servo_model import ServoCalibration, ServoModel, servo_angles
from firmware_py.core.waveform import named_waveform
from firmware_py.drivers.servo import SweepServo
from firmware_py.hal.clock import SimClock

SIM = find_spec("sitl") is not None  # False on the payload-only install (Raspberry Pi): those tests skip
if SIM:
    from sitl.devices.servo_emu import EmulatedServo
needs_sim = pytest.mark.skipif(not SIM, reason="needs the simulator (sitl/), not in the payload-only install")


def test_that_calibration_maps_angles_to_pulses_and_back_within_the_range():
    cal = ServoCalibration()
    assert cal.pulse_us(0.0) == 1500
    assert cal.pulse_us(math.pi / 2) == pytest.approx(2000)
    assert cal.pulse_us(3.0) == 2000  # clamped
    assert cal.angle_rad(cal.pulse_us(0.4)) == pytest.approx(0.4)


@pytest.mark.parametrize("kwargs", [dict(min_us=1600), dict(us_per_rad=0), dict(slew_rad_s=0), dict(lag_s=-1),
                                    dict(center_us=math.nan)])
def test_that_bad_calibrations_are_refused(kwargs):
    with pytest.raises(ValueError):
        ServoCalibration(**kwargs)


def test_that_the_model_is_slew_limited_and_settles_on_the_target():
    m = ServoModel(ServoCalibration(slew_rad_s=5.0, lag_s=0.02))
    assert m.advance(0.1, 1.0) == pytest.approx(0.5, abs=1e-9)  # 0.1 s at 5 rad/s
    m.advance(1.0, 1.0)
    assert m.angle_rad == pytest.approx(1.0, abs=1e-6)


@needs_sim
def test_that_the_driven_servo_follows_eq_1_and_the_model_predicts_the_plant():
    wf = named_waveform("semi-triangular", k=3)
    clock = SimClock()
    plant = EmulatedServo(clock, angle0_rad=float(wf.angle(0.0)))
    servo = SweepServo(plant, wf)
    errs_model, errs_wave = [], []
    for k in range(1, 3000):  # 6 s at 500 Hz
        t_ns = k * 2_000_000
        clock.set_ns(t_ns)
        servo.update(t_ns * 1e-9)
        truth = plant.angle_at(t_ns)
        errs_model.append(abs(servo.angle_at(t_ns * 1e-9) - truth))
        errs_wave.append(abs(float(wf.angle(t_ns * 1e-9)) - truth))
    assert max(errs_model) < 1e-9  # same calibration: the prediction is the plant
    assert np.median(errs_wave) < math.radians(2.0)  # lead-compensated: the shaft tracks eq. (1)


@needs_sim
def test_that_a_slower_real_servo_shows_as_a_prediction_error():
    wf = named_waveform("semi-triangular")
    clock = SimClock()
    plant = EmulatedServo(clock, ServoCalibration(slew_rad_s=3.0), angle0_rad=float(wf.angle(0.0)))
    servo = SweepServo(plant, wf)
    worst = 0.0
    for k in range(1, 2000):
        clock.set_ns(k * 2_000_000)
        servo.update(k * 0.002)
        worst = max(worst, abs(servo.angle_at(k * 0.002) - plant.angle_at(k * 2_000_000)))
    assert worst > math.radians(5)


def test_that_the_batch_servo_model_equals_the_stepped_one():
    cal = ServoCalibration()
    cmd_t = np.arange(0, 2, 0.02)
    cmd = np.sin(cmd_t * 3)
    t = np.sort(np.random.default_rng(1).uniform(0, 2, 300))
    batch = servo_angles(t, cmd_t, cmd, cal)
    m, tp, target, k = ServoModel(cal), 0.0, 0.0, 0
    stepped = []
    for tq in t:
        while k < len(cmd_t) and cmd_t[k] <= tq:
            m.advance(cmd_t[k] - tp, target)
            tp, target, k = cmd_t[k], cmd[k], k + 1
        m.advance(tq - tp, target)
        tp = tq
        stepped.append(m.angle_rad)
    assert np.allclose(batch, stepped, atol=1e-12)


@pytest.mark.parametrize("lag_s", [0.02, 0.0])
def test_that_the_batch_model_matches_stepping_through_slew_limited_steps_in_any_query_order(lag_s):
    cal = ServoCalibration(slew_rad_s=2.0, lag_s=lag_s)
    cmd_t = np.arange(0.1, 3, 0.02)
    cmd = np.where((cmd_t // 0.5) % 2 == 0, 1.2, -1.2)  # square wave: long slews, then settling
    t = np.random.default_rng(2).uniform(-0.5, 3.2, 500)  # unsorted, some before the first command
    batch = servo_angles(t, cmd_t, cmd, cal, angle0_rad=0.3)
    order = np.argsort(t)
    m, tp, target, k = ServoModel(cal, 0.3), -0.5, 0.3, 0
    stepped = np.empty(len(t))
    for i in order:
        while k < len(cmd_t) and cmd_t[k] <= t[i]:
            m.advance(cmd_t[k] - tp, target)
            tp, target, k = cmd_t[k], cmd[k], k + 1
        m.advance(t[i] - tp, target)
        tp = t[i]
        stepped[i] = m.angle_rad
    assert np.allclose(batch, stepped, atol=1e-9)
    assert np.all(batch[t < 0.1] == 0.3)


class _Pulses:
    def set_pulse_us(self, pulse_us: float) -> None:
        pass


def test_that_an_angle_asked_after_a_later_pulse_is_the_angle_then_not_the_angle_now():
    """A paced loop that ran late updates the servo (a pulse at `now`) before it reads a frame of its
    backlog, measured up to tens of ms earlier: that reading must get the shaft's angle at its own time
    (the networked TFMini flight under load logged the later angle on 7 % of its samples)."""
    wf = named_waveform("semi-triangular")
    late = SweepServo(_Pulses(), wf)
    rng = np.random.default_rng(3)
    worst, moved = 0.0, 0.0
    for k in range(1, 400):  # 8 s of ticks every 20 ms; each reading 0-60 ms older than its tick
        t_tick = k * 0.02
        t_read = max(0.0, t_tick - rng.uniform(0.0, 0.06))
        late.update(t_tick)
        got = late.angle_at(t_read)
        ref = SweepServo(_Pulses(), wf)  # the same pulses, the angle asked before the later pulse
        for j in range(1, k + 1):
            if j * 0.02 <= t_read:
                ref.update(j * 0.02)
        want = ref.angle_at(t_read)
        worst = max(worst, abs(got - want))
        moved = max(moved, abs(late.angle_at(t_tick) - want))
    assert worst < 1e-9
    assert moved > math.radians(5)  # the angle now differs: the case can tell them apart
