"""The simulated I2C bus: wire time on the simulated clock, NACKs, fault injection, the sitl: scheme."""

import errno

import numpy as np
import pytest

from firmware_py.hal import I2CError
from firmware_py.hal.backends import open_i2c, unregister_i2c_backend
from firmware_py.hal.clock import SimClock
from sitl.devices.i2c_sim import SimI2CBus, register_sim_bus


class Register8:
    """A minimal register device that supports repeated START (the bus's default behaviour)."""

    def __init__(self):
        self.regs = bytearray(range(256))
        self.ptr = 0
        self.writes = []

    def on_write(self, data):
        self.writes.append(bytes(data))
        if data:
            self.ptr = data[0]
            for i, v in enumerate(data[1:]):
                self.regs[(self.ptr + i) & 0xFF] = v

    def on_read(self, n):
        return bytes(self.regs[(self.ptr + i) & 0xFF] for i in range(n))


class Combined(Register8):
    def on_write_read(self, data, n):
        return b"\xaa" * n


@pytest.fixture
def rig():
    clock = SimClock()
    bus = SimI2CBus(clock)
    dev = Register8()
    bus.attach(0x40, dev)
    return clock, bus, dev


@pytest.mark.parametrize(("bitrate", "byte_ns"), [(400_000, 22_500), (100_000, 90_000)])
def test_that_each_transfer_costs_nine_clocks_per_byte_address_included(bitrate, byte_ns):
    clock = SimClock()
    bus = SimI2CBus(clock, bitrate)
    bus.attach(0x40, Register8())
    bus.write(0x40, b"\x10\x01")
    assert clock.now_ns() == 3 * byte_ns
    bus.read(0x40, 2)
    assert clock.now_ns() == 6 * byte_ns
    bus.write_read(0x40, b"\x10", 2)
    assert clock.now_ns() == 11 * byte_ns


def test_that_devices_see_the_written_bytes_and_answer_reads(rig):
    _, bus, dev = rig
    bus.write(0x40, b"\x10\x7f\x80")
    assert dev.writes == [b"\x10\x7f\x80"]
    bus.write(0x40, b"\x10")
    assert bus.read(0x40, 3) == b"\x7f\x80\x12"


def test_that_a_transfer_to_an_address_without_a_device_is_nacked_after_the_address_byte(rig):
    clock, bus, _ = rig
    with pytest.raises(I2CError, match=r"0x41.*NACK") as excinfo:
        bus.read(0x41, 2)
    assert excinfo.value.errno == errno.EREMOTEIO
    assert clock.now_ns() == bus.wire_time_ns(1)
    assert bus.counters["nack"] == 1 and bus.counters["read"] == 0


def test_that_write_read_acts_as_a_repeated_start_unless_the_device_says_otherwise():
    clock = SimClock()
    bus = SimI2CBus(clock)
    plain, combined = Register8(), Combined()
    bus.attach(0x40, plain)
    bus.attach(0x41, combined)
    assert bus.write_read(0x40, b"\x20", 2) == b"\x20\x21"  # on_write then on_read
    assert plain.writes == [b"\x20"]
    assert bus.write_read(0x41, b"\x20", 2) == b"\xaa\xaa"  # the device's own combined behaviour
    assert combined.writes == []


def test_that_a_fault_burst_nacks_every_transfer_until_its_end(rig):
    clock, bus, _ = rig
    bus.fault_until_ns = 1_000_000
    failures = 0
    while clock.now_ns() < 1_000_000:
        with pytest.raises(I2CError, match="fault burst"):
            bus.write(0x40, b"\x00")
        failures += 1
    bus.write(0x40, b"\x00\x05")
    assert failures == -(-1_000_000 // bus.wire_time_ns(1))
    assert bus.counters["nack"] == failures and bus.counters["write"] == 1


def test_that_random_nacks_follow_the_probability_and_replay_with_the_seed():
    def pattern(seed):
        clock = SimClock()
        bus = SimI2CBus(clock, nack_probability=0.3, rng=np.random.default_rng(seed))
        bus.attach(0x40, Register8())
        out = []
        for _ in range(2000):
            try:
                bus.write(0x40, b"\x00")
                out.append(True)
            except I2CError:
                out.append(False)
        return out

    a = pattern(7)
    assert a == pattern(7)
    assert a != pattern(8)
    assert 0.26 < a.count(False) / len(a) < 0.34


def test_that_lockstep_world_stepping_sees_the_bus_time():
    stepped = []
    clock = SimClock(advance=stepped.append)
    bus = SimI2CBus(clock)
    bus.attach(0x40, Register8())
    bus.write(0x40, b"\x00\x01")
    bus.read(0x40, 1)
    assert stepped == [67_500, 112_500]


@pytest.mark.parametrize(("call", "match"), [
    (lambda b: b.attach(0x40, Register8()), "already"),
    (lambda b: b.attach(0x80, Register8()), "7-bit"),
    (lambda b: b.attach(0x42, object()), "on_write"),
    (lambda b: b.detach(0x42), "no device"),
    (lambda b: b.read(0x40, 0), "length"),
    (lambda b: setattr(b, "nack_probability", 1.5), "1.5"),
    (lambda b: SimI2CBus(b.clock, 0), "bitrate"),
])
def test_that_bad_arguments_are_value_errors(rig, call, match):
    _, bus, _ = rig
    with pytest.raises(ValueError, match=match):
        call(bus)


def test_that_a_closed_bus_refuses_transfers(rig):
    _, bus, _ = rig
    bus.close()
    with pytest.raises(I2CError, match="closed"):
        bus.write(0x40, b"\x00")


def test_that_open_i2c_sitl_hands_out_handles_that_close_separately(rig):
    _, bus, dev = rig
    register_sim_bus(bus, scheme="sitltest")
    try:
        h1, h2 = open_i2c("sitltest"), open_i2c("sitltest:payload")
        h1.write(0x40, b"\x30\x99")
        h1.close()
        with pytest.raises(I2CError, match="closed"):
            h1.read(0x40, 1)
        h2.write(0x40, b"\x30")
        assert h2.read(0x40, 1) == b"\x99"
        assert dev.writes[0] == b"\x30\x99"
    finally:
        unregister_i2c_backend("sitltest")
