"""The emulated LIDAR-Lite v3 register file, driven through the simulated bus like the real part."""

import math

import numpy as np
import pytest

from firmware_py.drivers.lidarlite import StatusFlag, acquisition_time_ns
from firmware_py.hal.clock import SimClock
from sitl.devices.i2c_sim import SimI2CBus
from sitl.devices.lidarlite_emu import (
    ACQ_CONFIG_REG,
    FULL_DELAY_HIGH,
    LAST_DELAY_HIGH,
    MEASURE_DELAY,
    POWER_CONTROL,
    REF_COUNT_VAL,
    SIG_COUNT_VAL,
    STATUS,
    THRESHOLD_BYPASS,
    UNIT_ID_HIGH,
    VELOCITY,
    EmulatedLidarLite,
)

ADDR = 0x62


class Rig:
    def __init__(self, range_m=10.0, **kw):
        self.range_m = range_m
        self.sampled = []
        self.clock = SimClock()
        self.bus = SimI2CBus(self.clock)
        self.part = EmulatedLidarLite(self.clock, self._range_at, **kw)
        self.bus.attach(ADDR, self.part)

    def _range_at(self, t_ns):
        self.sampled.append(t_ns)
        return self.range_m

    def reg(self, reg, n=1):
        """A split register read, as the part needs."""
        self.bus.write(ADDR, bytes([reg]))
        data = self.bus.read(ADDR, n)
        return data[0] if n == 1 else data

    def set(self, reg, value):
        self.bus.write(ADDR, bytes([reg, value]))

    def measure(self, cmd=0x03):
        self.set(0x00, cmd)
        return self.part.last_acquisition

    def wait_done(self):
        self.clock.set_ns(self.part.last_acquisition.t_done_ns)

    def distance_cm(self):
        hi, lo = self.reg(0x8F, 2)
        return hi << 8 | lo


def test_that_registers_power_on_with_the_manual_values():
    rig = Rig(unit_id=0xBEEF)
    assert rig.reg(SIG_COUNT_VAL) == 0x80
    assert rig.reg(ACQ_CONFIG_REG) == 0x08
    assert rig.reg(THRESHOLD_BYPASS) == 0x00
    assert rig.reg(REF_COUNT_VAL) == 0x05
    assert rig.reg(MEASURE_DELAY) == 0x14
    assert rig.reg(POWER_CONTROL) == 0x80
    assert rig.reg(STATUS) == StatusFlag.HEALTH
    assert rig.reg(UNIT_ID_HIGH | 0x80, 2) == b"\xbe\xef"


def test_that_an_acquisition_is_busy_for_exactly_the_modelled_time():
    rig = Rig(None)  # no return: every count integrated
    acq = rig.measure(0x03)
    assert acq.t_done_ns - acq.t_start_ns == acquisition_time_ns(0x80, 0x08) == 3_493_000
    assert rig.reg(STATUS) & StatusFlag.BUSY
    rig.clock.set_ns(acq.t_done_ns - 1)
    assert rig.part.busy
    rig.clock.set_ns(acq.t_done_ns)
    assert not rig.part.busy
    assert rig.reg(STATUS) == StatusFlag.HEALTH | StatusFlag.INVALID_SIGNAL


def test_that_acquisition_time_grows_with_sig_count_val_and_bias_correction_costs_extra():
    durations = []
    for count in (0x10, 0x80, 0xFF):
        rig = Rig(None)
        rig.set(SIG_COUNT_VAL, count)
        acq = rig.measure(0x03)
        durations.append(acq.t_done_ns - acq.t_start_ns)
    assert durations == sorted(durations) and len(set(durations)) == 3
    rig = Rig(None)
    plain = rig.measure(0x03)
    rig.wait_done()
    biased = rig.measure(0x04)
    assert biased.bias and not plain.bias
    assert biased.t_done_ns - biased.t_start_ns > plain.t_done_ns - plain.t_start_ns


def test_that_a_strong_return_ends_integration_early_and_quick_termination_earlier():
    rig = Rig(2.0)
    full = rig.measure().counts
    rig.wait_done()
    rig.set(ACQ_CONFIG_REG, 0x00)  # quick termination enabled
    quick = rig.measure().counts
    assert quick < full < 0x80
    assert Rig(12.0).measure().counts == 0x80  # a weak far return integrates every count


def test_that_the_distance_registers_hold_the_range_in_centimetres_read_with_auto_increment():
    rig = Rig(12.345)
    rig.measure()
    rig.wait_done()
    assert rig.distance_cm() == 1235  # rounded to 1 cm
    hi_twice = rig.reg(FULL_DELAY_HIGH, 2)  # no auto-increment bit: the same register again
    assert hi_twice == bytes([1235 >> 8, 1235 >> 8])


@pytest.mark.parametrize(("count", "range_m", "cm"), [
    (0x80, None, 1), (0x80, math.nan, 1), (0x80, 39.5, 3950), (0x80, 41.0, 1), (0x14, 24.0, 2400), (0x14, 30.0, 1)])
def test_that_no_return_reads_one_centimetre_with_the_invalid_signal_flag(count, range_m, cm):
    rig = Rig(range_m)
    rig.set(SIG_COUNT_VAL, count)
    rig.measure()
    rig.wait_done()
    assert rig.distance_cm() == cm
    assert bool(rig.reg(STATUS) & StatusFlag.INVALID_SIGNAL) == (cm == 1)


def test_that_the_range_is_sampled_when_the_acquisition_starts():
    rig = Rig(5.0)
    rig.clock.set_ns(1_000_000)
    rig.set(0x00, 0x03)
    assert rig.sampled == [rig.clock.now_ns()] == [1_000_000 + rig.bus.wire_time_ns(3)]
    assert rig.part.last_acquisition.t_start_ns == rig.sampled[0]


def test_that_the_previous_distance_stays_readable_until_the_next_acquisition_ends():
    rig = Rig(5.0)
    rig.measure()
    rig.wait_done()
    rig.range_m = 9.0
    rig.measure()
    assert rig.distance_cm() == 500  # Garmin's ShortRangeHighSpeed reads this while measuring
    rig.wait_done()
    assert rig.distance_cm() == 900
    assert rig.reg(LAST_DELAY_HIGH | 0x80, 2) == (500).to_bytes(2, "big")
    assert rig.reg(VELOCITY) == 127  # +400 cm, clamped to a signed byte


def test_that_range_noise_is_gaussian_with_the_given_sigma_and_seeded():
    def run(sigma, seed):
        rig = Rig(10.0, range_noise_sigma_m=sigma, rng=np.random.default_rng(seed))
        cms = []
        for _ in range(2000):
            cms.append(rig.measure().distance_cm)
            rig.wait_done()
        return np.array(cms) / 100.0

    noisy = run(0.025, 3)
    assert np.std(noisy) == pytest.approx(0.025, rel=0.1)
    assert np.mean(noisy) == pytest.approx(10.0, abs=0.003)
    assert np.array_equal(noisy, run(0.025, 3))
    assert np.all(run(0.0, 3) == 10.0)


def test_that_a_combined_transfer_returns_garbage_like_the_real_part():
    rig = Rig(7.0)
    rig.measure()
    rig.wait_done()
    assert rig.bus.write_read(ADDR, b"\x8f", 2) == b"\xff\xff"
    assert rig.part.counters["combined_transfers"] == 1
    assert rig.distance_cm() == 700  # the split read still works


def test_that_a_reset_is_busy_22_ms_then_reloads_defaults_losing_writes_meanwhile():
    rig = Rig(3.0)
    rig.set(SIG_COUNT_VAL, 0x14)
    rig.set(0x00, 0x00)
    t_reset = rig.clock.now_ns()
    assert rig.reg(STATUS) & StatusFlag.BUSY
    rig.set(SIG_COUNT_VAL, 0x20)  # too early: lost when the part reloads
    rig.clock.set_ns(t_reset + 22_000_000 - 1)
    assert rig.part.busy
    rig.clock.set_ns(t_reset + 22_000_000)
    assert not rig.part.busy
    assert rig.reg(SIG_COUNT_VAL) == 0x80
    assert rig.part.counters["resets"] == 1 and rig.part.counters["ignored_writes"] == 1


def test_that_stuck_busy_holds_busy_until_cleared():
    rig = Rig(4.0, stuck_busy=True)
    acq = rig.measure()
    rig.clock.set_ns(acq.t_done_ns + 50_000_000)
    assert rig.reg(STATUS) & StatusFlag.BUSY
    rig.part.stuck_busy = False
    assert not rig.reg(STATUS) & StatusFlag.BUSY
    assert rig.distance_cm() == 400


def test_that_a_power_glitch_restores_power_on_values_and_loses_the_acquisition():
    rig = Rig(4.0)
    rig.set(SIG_COUNT_VAL, 0x14)
    rig.set(THRESHOLD_BYPASS, 0xB0)
    rig.measure()
    rig.part.power_glitch()
    assert (rig.reg(SIG_COUNT_VAL), rig.reg(THRESHOLD_BYPASS)) == (0x80, 0x00)
    assert not rig.part.busy
    assert rig.distance_cm() == 0
    assert rig.part.counters["power_glitches"] == 1


def test_that_garbage_reads_return_random_bytes_at_the_set_probability():
    rig = Rig(garbage_reads=0.5, rng=np.random.default_rng(5))
    values = [rig.reg(SIG_COUNT_VAL) for _ in range(400)]
    garbage = sum(v != 0x80 for v in values)
    assert 150 < garbage <= rig.part.counters["garbage_reads"] < 250
    rig.part.garbage_reads = 0.0
    assert all(rig.reg(SIG_COUNT_VAL) == 0x80 for _ in range(50))


def test_that_read_only_registers_ignore_writes():
    rig = Rig(6.0)
    rig.measure()
    rig.wait_done()
    rig.set(STATUS, 0xFF)
    rig.set(FULL_DELAY_HIGH, 0x7F)
    assert rig.reg(STATUS) == StatusFlag.HEALTH
    assert rig.distance_cm() == 600
    assert rig.part.counters["ignored_writes"] == 2


@pytest.mark.parametrize(("kw", "match"), [
    ({"range_noise_sigma_m": -0.01}, "sigma.*-0.01"),
    ({"range_noise_sigma_m": math.inf}, "sigma.*inf"),
    ({"garbage_reads": 2.0}, "garbage.*2.0"),
    ({"unit_id": 70_000}, "unit id.*70000"),
    ({"range_at": 5.0}, "range_at"),
])
def test_that_bad_construction_arguments_are_value_errors_naming_the_value(kw, match):
    args = {"range_at": lambda t: 1.0, **kw}
    with pytest.raises(ValueError, match=match):
        EmulatedLidarLite(SimClock(), **args)


def test_that_a_noise_models_range_and_no_return_reach_the_registers():
    from firmware_py.core.sensor import LIDARLITE_V3
    from firmware_py.core.sensor_noise import SensorNoise
    from sitl.sensing.noise import RangeNoiser, noise_streams

    def run(range_m, cos_i, seed=1):
        noiser = RangeNoiser(SensorNoise.of("datasheet", LIDARLITE_V3), noise_streams(seed), incidence=lambda: cos_i)
        rig = Rig(range_m, range_noise=noiser)
        out = []
        for _ in range(1000):
            acq = rig.measure()
            rig.wait_done()
            out.append((acq.distance_cm, acq.status))
        return out

    head_on = run(10.0, 1.0)
    cm = np.array([c for c, _ in head_on]) / 100.0
    assert all(not s & StatusFlag.INVALID_SIGNAL for _, s in head_on)
    assert np.std(cm) == pytest.approx(0.1, rel=0.1)  # 1 % of 10 m, quantised to 1 cm
    assert all(c == 1 and s & StatusFlag.INVALID_SIGNAL for c, s in run(10.0, 0.05))  # grazing: no echo
    assert run(10.0, 1.0) == head_on  # seeded
