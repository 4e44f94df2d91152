"""The LIDAR-Lite v3 driver against the emulated part on the simulated I2C bus, in simulated time."""

import math
from importlib.util import find_spec

import pytest

from firmware_py.drivers.lidarlite import (
    COUNTER_NAMES,
    PRESET_DEFAULT,
    PRESET_FAST_500HZ,
    PRESETS,
    LidarLite,
    LidarLiteConfig,
    Preset,
    Reading,
    ReadStatus,
    busy_deadline_ns,
    preset_by_name,
)
from firmware_py.hal import I2CError
from firmware_py.hal.clock import SimClock

SIM = find_spec("sitl") is not None  # False on the payload-only install (Raspberry Pi): those tests skip
if SIM:
    from sitl.devices.i2c_sim import SimI2CBus
    from sitl.devices.lidarlite_emu import ACQ_CONFIG_REG, SIG_COUNT_VAL, THRESHOLD_BYPASS, EmulatedLidarLite
needs_sim = pytest.mark.skipif(not SIM, reason="needs the simulator (sitl/), not in the payload-only install")

TICK_NS = 2_000_000  # 500 Hz


class SpyBus:
    """Records every transfer the driver makes, then passes it on."""

    def __init__(self, bus):
        self.bus = bus
        self.calls = []

    def write(self, addr, data):
        self.calls.append(("write", addr, bytes(data)))
        self.bus.write(addr, data)

    def read(self, addr, n):
        self.calls.append(("read", addr, n))
        return self.bus.read(addr, n)

    def write_read(self, addr, data, n):
        self.calls.append(("write_read", addr, bytes(data)))
        return self.bus.write_read(addr, data, n)

    def close(self):
        self.bus.close()


class Rig:
    """Clock, bus, emulated part at 0x62 and the driver; `self.range_m` is what the beam sees."""

    def __init__(self, range_m=10.0, preset=PRESET_DEFAULT, range_at=None, **config):
        pytest.importorskip("sitl", reason="the emulated part (sitl/): not in the payload-only install")
        self.range_m = range_m
        self.clock = SimClock()
        self.sim_bus = SimI2CBus(self.clock)
        self.part = EmulatedLidarLite(self.clock, range_at or (lambda t_ns: self.range_m))
        self.sim_bus.attach(0x62, self.part)
        self.bus = SpyBus(self.sim_bus)
        self.lidar = LidarLite(self.bus, self.clock, LidarLiteConfig(preset=preset, **config))

    def writes(self, data):
        return sum(1 for op, _, d in self.bus.calls if op == "write" and d == data)


@pytest.mark.parametrize("preset", [PRESET_DEFAULT, PRESET_FAST_500HZ], ids=lambda p: p.name)
@pytest.mark.parametrize("true_m", [0.5, 1.234, 7.891, 12.0, 23.456])
def test_that_readings_give_the_true_range_to_one_centimetre(preset, true_m):
    rig = Rig(true_m, preset)
    reading = rig.lidar.read()
    assert reading.status == ReadStatus.OK
    assert reading.range_m == pytest.approx(round(true_m * 100) / 100, abs=1e-9)
    assert abs(reading.range_m - true_m) <= 0.005 + 1e-9


@pytest.mark.parametrize(("preset", "true_m"), [(PRESET_DEFAULT, None), (PRESET_DEFAULT, math.inf),
                                                (PRESET_FAST_500HZ, 30.0), (PRESET_DEFAULT, 45.0)])
def test_that_no_echo_is_a_no_return_reading_never_a_sentinel_distance(preset, true_m):
    rig = Rig(true_m, preset)
    reading = rig.lidar.read()
    assert reading.status == ReadStatus.NO_RETURN
    assert reading.range_m is None
    assert not reading.ok
    assert rig.lidar.counters().no_return == 1 and rig.lidar.counters().ok == 0


def test_that_a_reading_is_stamped_at_the_trigger_where_the_range_belongs():
    sampled = []

    def range_at(t_ns):  # the target recedes at 1 m/s
        sampled.append(t_ns)
        return 5.0 + t_ns * 1e-9

    rig = Rig(preset=PRESET_FAST_500HZ, range_at=range_at)
    rig.clock.sleep_until_ns(250_000_000)
    reading = rig.lidar.read()
    assert reading.t_ns == sampled[-1] == rig.part.last_acquisition.t_start_ns
    assert reading.range_m == pytest.approx(5.0 + reading.t_ns * 1e-9, abs=0.005)
    assert rig.clock.now_ns() > reading.t_ns + 1_000_000  # collected well after the trigger


def test_that_bias_correction_is_requested_once_per_hundred_measurements():
    rig = Rig(8.0, PRESET_FAST_500HZ)
    first = len(rig.bus.calls)
    rig.lidar.read()
    assert ("write", 0x62, b"\x00\x04") in rig.bus.calls[first:]  # the first measurement is bias-corrected
    for _ in range(999):
        rig.lidar.read()
    assert rig.writes(b"\x00\x04") == 10
    assert rig.writes(b"\x00\x03") == 990
    assert rig.part.counters["bias_acquisitions"] == rig.lidar.counters().bias == 10


def test_that_the_driver_only_makes_split_transfers():
    rig = Rig(6.0, PRESET_FAST_500HZ, readback_every=5, reset_after_no_valid=3)
    for _ in range(10):
        rig.lidar.read()
    rig.range_m = None
    for _ in range(3):  # a reset and a re-configuration too
        rig.lidar.read()
    assert rig.lidar.counters().resets == 1
    ops = [c[0] for c in rig.bus.calls]
    assert "write_read" not in ops
    assert rig.part.counters["combined_transfers"] == 0
    for i, (op, _, n) in enumerate(rig.bus.calls):
        if op == "read":  # every read follows its own one-byte register-address write
            prev_op, _, prev_data = rig.bus.calls[i - 1]
            assert prev_op == "write" and len(prev_data) == 1
            if n == 2:
                assert prev_data == b"\x8f"  # distance: 0x0f with the auto-increment bit


def test_that_a_stuck_busy_part_times_out_within_the_deadline_and_the_next_reading_works():
    rig = Rig(9.87, PRESET_FAST_500HZ)
    rig.part.stuck_busy = True
    reading = rig.lidar.read()
    assert reading.status == ReadStatus.TIMEOUT and reading.range_m is None
    deadline = rig.lidar.config.timeout_ns
    assert deadline < 5 * TICK_NS
    one_poll_ns = rig.sim_bus.wire_time_ns(4)
    assert deadline <= rig.clock.now_ns() - reading.t_ns <= deadline + one_poll_ns
    assert reading.polls > 10
    assert rig.lidar.counters().timeouts == 1
    rig.part.stuck_busy = False
    after = rig.lidar.read()
    assert after.status == ReadStatus.OK and after.range_m == pytest.approx(9.87)


def test_that_a_nack_burst_gives_counted_bus_errors_then_readings_recover():
    rig = Rig(4.56, PRESET_FAST_500HZ)
    rig.sim_bus.fault_until_ns = rig.clock.now_ns() + 10 * TICK_NS + TICK_NS // 2
    start = rig.clock.now_ns()
    readings = []
    for k in range(20):
        rig.clock.sleep_until_ns(start + k * TICK_NS)
        readings.append(rig.lidar.read())
    statuses = [r.status for r in readings]
    assert statuses[:11] == [ReadStatus.BUS_ERROR] * 11
    assert statuses[11:] == [ReadStatus.OK] * 9
    assert all(r.range_m == pytest.approx(4.56) for r in readings[11:])
    assert rig.lidar.counters().bus_errors == 11 and rig.lidar.counters().ok == 9
    assert isinstance(rig.lidar.last_error, I2CError) and "0x62" in str(rig.lidar.last_error)
    assert rig.lidar.counters().resets == 0  # 11 < 20 consecutive failures


def test_that_random_nacks_become_bus_errors_and_every_reading_is_accounted_for():
    rig = Rig(3.21, PRESET_FAST_500HZ)
    rig.sim_bus.nack_probability = 0.02
    readings = [rig.lidar.read() for _ in range(300)]
    c = rig.lidar.counters()
    assert c.ok + c.no_return + c.timeouts + c.bus_errors == c.readings == 300
    assert c.bus_errors == sum(r.status == ReadStatus.BUS_ERROR for r in readings) > 0
    assert all(r.range_m == pytest.approx(3.21) for r in readings if r.ok)


def test_that_a_power_glitch_is_caught_by_register_read_back_and_the_preset_reapplied():
    rig = Rig(11.0, PRESET_FAST_500HZ, readback_every=50)
    for _ in range(20):
        rig.lidar.read()
    rig.part.power_glitch()
    assert rig.part.regs[SIG_COUNT_VAL] == 0x80  # the part forgot the fast preset
    for _ in range(40):
        rig.lidar.read()
    assert rig.lidar.counters().reconfigs == 1
    assert (rig.part.regs[SIG_COUNT_VAL], rig.part.regs[ACQ_CONFIG_REG], rig.part.regs[THRESHOLD_BYPASS]) == (
        PRESET_FAST_500HZ.sig_count_val, PRESET_FAST_500HZ.acq_config, PRESET_FAST_500HZ.threshold_bypass)
    for _ in range(50):
        rig.lidar.read()
    assert rig.lidar.counters().reconfigs == 1  # nothing differs any more


def test_that_a_run_of_no_returns_resets_the_part_and_reapplies_the_preset():
    rig = Rig(None, PRESET_FAST_500HZ, reset_after_no_valid=10)
    for _ in range(9):
        rig.lidar.read()
    assert rig.lidar.counters().resets == 0
    rig.lidar.read()
    assert rig.lidar.counters().resets == rig.part.counters["resets"] == 1
    # The reset does not block the loop: readings on the 500 Hz tick grid come back RESETTING, with
    # no bus traffic, until the part has had its reload time; then the preset goes back on.
    rig.range_m = 2.5
    t_reset = rig.clock.now_ns()
    transfers = len(rig.bus.calls)
    during = _read_on_ticks(rig, 10)
    assert all(r.status == ReadStatus.RESETTING for r in during) and len(rig.bus.calls) == transfers
    assert rig.clock.now_ns() - t_reset < 22_000_000 and rig.lidar.counters().resetting == 10
    after = _read_on_ticks(rig, 5)
    assert after[-1].status == ReadStatus.OK and after[-1].range_m == pytest.approx(2.5)
    first_ok = next(r for r in during + after if r.status == ReadStatus.OK)
    assert first_ok.t_ns - t_reset >= LidarLiteConfig().reset_wait_ns  # waited for the part to reload
    assert rig.part.regs[SIG_COUNT_VAL] == PRESET_FAST_500HZ.sig_count_val


def test_that_an_explicit_reset_still_waits_for_the_part():
    rig = Rig(2.5, PRESET_FAST_500HZ)
    t0 = rig.clock.now_ns()
    assert rig.lidar.reset()
    assert rig.clock.now_ns() - t0 >= 22_000_000 and rig.lidar.read().range_m == pytest.approx(2.5)


def test_that_twenty_zero_centimetre_readings_reset_the_part_as_px4_does():
    rig = Rig(0.004, PRESET_FAST_500HZ)  # reads 0 cm: PX4's known stuck state
    readings = [rig.lidar.read() for _ in range(20)]
    assert all(r.status == ReadStatus.NO_RETURN for r in readings)
    assert rig.lidar.counters().resets == 1


def test_that_a_reset_warning_says_why(caplog):
    rig = Rig(0.004, PRESET_FAST_500HZ)
    with caplog.at_level("WARNING", logger="firmware_py.drivers.lidarlite"):
        for _ in range(20):
            rig.lidar.read()
    assert "resetting the LIDAR-Lite at 0x62: 20 readings in a row failed (last: 0 cm)" in caplog.text


def test_that_a_healthy_part_seeing_nothing_for_a_long_time_is_never_reset():
    # A drone standing on the floor before take-off, or a lens cover: the part answers "no signal",
    # as a working part does. By default no run of such answers resets it (10 s at 500 Hz here).
    rig = Rig(None, PRESET_FAST_500HZ)
    for _ in range(5000):
        rig.lidar.read()
    assert rig.lidar.counters().no_return == 5000
    assert rig.lidar.counters().resets == 0 and rig.part.counters["resets"] == 0


def test_that_a_sweep_past_far_walls_does_not_reset_the_part():
    rig = Rig(None, PRESET_FAST_500HZ)  # 1 cm no-returns, e.g. 0.6 s of beam beyond range
    for _ in range(300):
        rig.lidar.read()
    assert rig.lidar.counters().no_return == 300
    assert rig.lidar.counters().resets == 0


def test_that_the_fast_preset_sustains_500_hz_in_simulated_time():
    ranges = [3.0, 12.5, None, 24.9, 0.9, 17.3]
    rig = Rig(preset=PRESET_FAST_500HZ, range_at=lambda t_ns: ranges[(t_ns // TICK_NS) % len(ranges)])
    start = rig.clock.now_ns() + TICK_NS
    late = []
    readings = []
    for k in range(1000):
        tick = start + k * TICK_NS
        rig.clock.sleep_until_ns(tick)
        readings.append(rig.lidar.read())
        if rig.clock.now_ns() >= tick + TICK_NS:
            late.append(k)
    assert late == []
    assert all(r.status in (ReadStatus.OK, ReadStatus.NO_RETURN) for r in readings)
    no_echo = [ranges[(r.t_ns // TICK_NS) % len(ranges)] is None for r in readings]
    assert [r.status == ReadStatus.NO_RETURN for r in readings] == no_echo and any(no_echo)
    assert rig.lidar.counters().bias == 10
    assert rig.writes(b"\x02") >= 1  # the SIG_COUNT_VAL read-back ran inside the budget too


def test_that_the_default_preset_could_not_sustain_500_hz():
    rig = Rig(None, PRESET_DEFAULT)  # no return: every count integrated
    reading = rig.lidar.read()
    assert reading.status == ReadStatus.NO_RETURN
    assert rig.clock.now_ns() - reading.t_ns > TICK_NS


def test_that_measure_start_returns_at_once_and_measure_finish_collects_later():
    rig = Rig(6.66, PRESET_FAST_500HZ)
    t_ns = rig.lidar.measure_start()
    assert rig.clock.now_ns() == t_ns and rig.lidar.measuring
    with pytest.raises(RuntimeError, match="twice"):
        rig.lidar.measure_start()
    rig.clock.sleep_until_ns(t_ns + 1_500_000)  # other work while the part integrates
    reading = rig.lidar.measure_finish()
    assert reading.t_ns == t_ns and reading.range_m == pytest.approx(6.66)
    assert reading.polls == 1  # already done: a single status read
    assert not rig.lidar.measuring
    with pytest.raises(RuntimeError, match="without measure_start"):
        rig.lidar.measure_finish()


class ScriptedBus:
    """Answers STATUS with `status` and the distance registers with `distance` (no real part)."""

    def __init__(self, status, distance):
        self.status, self.distance, self.reg = status, distance, None

    def write(self, addr, data):
        self.reg = data[0] if len(data) == 1 else None

    def read(self, addr, n):
        return bytes([self.status]) if self.reg == 0x01 else self.distance[:n]

    def write_read(self, addr, data, n):
        raise AssertionError("the LIDAR-Lite driver must not use repeated start")

    def close(self):
        pass


@pytest.mark.parametrize(("status", "distance", "expected", "range_m"), [
    (0x20, b"\x04\xd2", ReadStatus.OK, 12.34),
    (0x20, b"\x00\x01", ReadStatus.NO_RETURN, None),
    (0x20, b"\x00\x00", ReadStatus.NO_RETURN, None),
    (0x28, b"\x04\xd2", ReadStatus.NO_RETURN, None),  # invalid-signal flag: stale registers
    (0x20, b"\xff\xff", ReadStatus.BUS_ERROR, None),  # 655 m: bytes no part can measure
])
def test_that_distances_map_to_statuses_and_impossible_bytes_are_bus_errors(status, distance, expected, range_m):
    lidar = LidarLite(ScriptedBus(status, distance), SimClock(), LidarLiteConfig())
    reading = lidar.read()
    assert reading.status == expected
    assert reading.range_m == (pytest.approx(range_m) if range_m is not None else None)
    assert lidar.counters().implausible == (1 if distance == b"\xff\xff" else 0)


@needs_sim
def test_that_an_absent_part_fails_loudly_at_construction():
    clock = SimClock()
    with pytest.raises(I2CError, match="0x62"):
        LidarLite(SimI2CBus(clock), clock)


def test_that_presets_carry_the_garmin_library_values():
    assert {n: (p.sig_count_val, p.acq_config, p.threshold_bypass) for n, p in PRESETS.items()} == {
        "default": (0x80, 0x08, 0x00), "short-range-high-speed": (0x1D, 0x08, 0x00),
        "default-range-higher-speed": (0x80, 0x00, 0x00), "max-range": (0xFF, 0x08, 0x00),
        "high-sensitivity": (0x80, 0x08, 0x80), "low-sensitivity": (0x80, 0x08, 0xB0),
        "fast-500hz": (0x14, 0x08, 0x00)}
    assert preset_by_name("fast-500hz") is PRESET_FAST_500HZ
    with pytest.raises(ValueError, match="'turbo'"):
        preset_by_name("turbo")
    # the fast preset's worst case (no return, bias correction) leaves room for the bus in 2 ms
    assert PRESET_FAST_500HZ.worst_acquisition_ns(bias=True) < 1_500_000 < PRESET_DEFAULT.worst_acquisition_ns(False)


@pytest.mark.parametrize(("make", "match"), [
    (lambda: LidarLiteConfig(address=0x80), "0x80|128"),
    (lambda: LidarLiteConfig(bias_every=0), "bias_every.*0"),
    (lambda: LidarLiteConfig(poll_interval_ns=0), "poll_interval_ns.*0"),
    (lambda: LidarLiteConfig(busy_timeout_ns=-5), "busy_timeout_ns.*-5"),
    (lambda: LidarLiteConfig(reset_after_failures=0), "reset_after_failures.*0"),
    (lambda: LidarLiteConfig(max_range_m=math.nan), "max_range_m.*nan"),
    (lambda: LidarLiteConfig(preset="fast-500hz"), "fast-500hz"),
    (lambda: Preset("x", 0, 0x08, 0), "SIG_COUNT_VAL"),
    (lambda: Preset("x", 0x80, 0x100, 0), "ACQ_CONFIG_REG.*256"),
    (lambda: Preset("x", 0x80, 0x08, -1), "THRESHOLD_BYPASS.*-1"),
    (lambda: Reading(None, ReadStatus.OK, 0, 0), "OK reading"),
    (lambda: Reading(1.0, ReadStatus.NO_RETURN, 0, 0), "NO_RETURN"),
])
def test_that_bad_configuration_and_records_are_value_errors_naming_the_value(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def _read_on_ticks(rig, n):
    out = []
    for _ in range(n):
        rig.clock.sleep_until_ns((rig.clock.now_ns() // TICK_NS + 1) * TICK_NS)
        out.append(rig.lidar.read())
    return out


def test_that_the_first_busy_poll_learns_the_acquisition_time():
    rig = Rig(12.0, PRESET_FAST_500HZ, bias_every=1000)
    first, *rest = _read_on_ticks(rig, 50)
    assert first.polls >= 4  # nothing learned yet: from the shortest possible acquisition, 0.1 ms grid
    assert all(r.status == ReadStatus.OK for r in rest)
    assert max(r.polls for r in rest[2:]) <= 2  # then one poll before the learned time, one after


def test_that_a_shorter_acquisition_is_still_collected_and_relearned():
    rig = Rig(12.0, PRESET_FAST_500HZ, bias_every=1000)
    _read_on_ticks(rig, 20)
    rig.range_m = 0.6  # a strong short-range return ends integration early
    readings = _read_on_ticks(rig, 20)
    assert all(r.status == ReadStatus.OK and r.range_m == pytest.approx(0.6) for r in readings)
    # Each reading collected within one poll interval of what it learned; latency shrinks back.
    lat = [rig.part.last_acquisition.t_done_ns - rig.part.last_acquisition.t_start_ns]
    assert lat[0] < PRESET_FAST_500HZ.worst_acquisition_ns(bias=False)
    assert rig.lidar._done_after_ns[False] - lat[0] <= 2 * rig.lidar.config.poll_interval_ns


def test_that_one_late_collection_does_not_push_later_polls_past_the_worst_case():
    rig = Rig(12.0, PRESET_FAST_500HZ, bias_every=1000)
    _read_on_ticks(rig, 5)
    t_ns = rig.lidar.measure_start()
    rig.clock.sleep_until_ns(t_ns + 5_000_000)  # the process was descheduled for 5 ms
    assert rig.lidar.measure_finish().status == ReadStatus.OK
    assert rig.lidar._done_after_ns[False] <= PRESET_FAST_500HZ.worst_acquisition_ns(bias=False)
    nxt = _read_on_ticks(rig, 1)[0]
    assert rig.clock.now_ns() - nxt.t_ns < TICK_NS  # the next reading still fits its 2 ms tick


def test_that_the_busy_deadline_fits_the_loop_period_without_cutting_off_a_healthy_part():
    d = busy_deadline_ns(PRESET_FAST_500HZ, 500.0)
    assert PRESET_FAST_500HZ.worst_acquisition_ns(bias=True) < d < TICK_NS
    slow = busy_deadline_ns(PRESET_DEFAULT, 100.0)
    assert slow >= PRESET_DEFAULT.worst_acquisition_ns(bias=True) + 100_000
    with pytest.raises(ValueError, match=r"up to 2[0-9]{2} Hz or a faster preset"):
        busy_deadline_ns(PRESET_DEFAULT, 500.0)


def test_that_resets_back_off_while_the_part_stays_stuck_and_come_back_after_a_good_reading():
    rig = Rig(9.87, PRESET_FAST_500HZ)
    rig.part.stuck_busy = True
    while rig.lidar.counters().timeouts < 620:
        _read_on_ticks(rig, 1)
    assert rig.lidar.counters().resets == 5  # after 20, 40, 80, 160 and 320 more failures, not 31 times
    assert 4 * 11 <= rig.lidar.counters().resetting <= 4 * 14  # ~25 ms of 2 ms ticks each: not blocked
    rig.part.stuck_busy = False
    back = _read_on_ticks(rig, 15)  # the fifth reset reloads first
    assert {r.status for r in back[:-1]} <= {ReadStatus.RESETTING, ReadStatus.OK} and back[-1].status == ReadStatus.OK
    rig.part.stuck_busy = True
    _read_on_ticks(rig, 20)
    assert rig.lidar.counters().resets == 6  # the next fault is met at the base threshold again


def test_that_the_counters_are_a_snapshot_that_later_readings_do_not_change():
    rig = Rig(3.21, PRESET_FAST_500HZ)
    rig.lidar.read()
    before = rig.lidar.counters()
    rig.lidar.read()
    assert before.ok == 1 and rig.lidar.counters().ok == 2
    with pytest.raises(AttributeError):
        before.ok = 5


def test_that_the_counters_as_a_dict_name_every_counter_in_order():
    rig = Rig(3.21, PRESET_FAST_500HZ)
    rig.lidar.read()
    d = rig.lidar.counters().as_dict()
    assert tuple(d) == COUNTER_NAMES and d["ok"] == 1 and sum(d.values()) == 1 + d["bias"]
