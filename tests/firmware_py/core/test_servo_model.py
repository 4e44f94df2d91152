"""The servo model's batch path split in two: the pulses stepped once (`command_states`, `sweep_states`), any
queries answered from them (`angles_at`); the stepping against the payload's own is in
tests/firmware_py/drivers/test_servo.py."""

import numpy as np

from firmware_py.core.servo_model import (
    ServoCalibration,
    angles_at,
    command_states,
    modelled_sweep,
    servo_angles,
    sweep_states,
)
from firmware_py.core.waveform import Waveform

WAVE = Waveform(0.95, 0.67, 1.2, 0.3, 1)
SLOW = ServoCalibration(slew_rad_s=2.5, lag_s=0.03)  # slower than the sweep asks: the shaft turns back early


def test_that_states_stepped_to_a_later_horizon_answer_the_same_queries_to_the_bit():
    t = np.sort(np.random.default_rng(0).uniform(-0.5, 40.0, 5000))  # some before the first pulse
    for until_s in (t.max(), t.max() + 0.013, t.max() + 7.0):
        assert np.array_equal(angles_at(t, sweep_states(WAVE, SLOW, until_s), SLOW), modelled_sweep(WAVE, SLOW, t))
    later = sweep_states(WAVE, SLOW, 60.0, gain=1.05, offset_rad=0.02)
    assert np.array_equal(angles_at(t, later, SLOW), modelled_sweep(WAVE, SLOW, t, gain=1.05, offset_rad=0.02))


def test_that_the_split_is_servo_angles_and_keeps_the_shaft_at_rest_before_the_first_command():
    cmd_t = np.array([0.5, 0.1, 0.3])  # out of order: stepped in time order
    cmd = np.array([0.4, -0.2, 0.1])
    t = np.array([0.0, 0.1, 0.2, 0.35, 0.9])
    states = command_states(cmd_t, cmd, SLOW, angle0_rad=0.25)
    assert np.array_equal(states.cmd_t_s, [0.1, 0.3, 0.5]) and states.start_rad[0] == 0.25
    got = angles_at(t, states, SLOW)
    assert np.array_equal(got, servo_angles(t, cmd_t, cmd, SLOW, 0.25)) and got[0] == 0.25
