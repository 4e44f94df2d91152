"""SmbusI2CBus against a fake smbus2 module (there is no /dev/i2c here)."""

import errno
import sys
import types
from typing import ClassVar

import pytest

from firmware_py.hal import I2CError
from firmware_py.hal.i2c_smbus import SmbusI2CBus

I2C_M_RD = 0x0001


class FakeMsg:
    """smbus2.i2c_msg: addr, flags, a buffer, bytes() of it."""

    def __init__(self, addr, flags, buf):
        self.addr, self.flags, self.buf = addr, flags, bytearray(buf)

    @staticmethod
    def read(addr, length):
        return FakeMsg(addr, I2C_M_RD, bytes(length))

    @staticmethod
    def write(addr, buf):
        return FakeMsg(addr, 0, bytes(buf))

    def __bytes__(self):
        return bytes(self.buf)

    def __len__(self):
        return len(self.buf)


class FakeSMBus:
    instances: ClassVar[list] = []
    open_error: ClassVar[OSError | None] = None

    def __init__(self, bus):
        if FakeSMBus.open_error is not None:
            raise FakeSMBus.open_error
        self.bus = bus
        self.ioctls = []  # one entry per i2c_rdwr call: [(flags, addr, data written or length read), ...]
        self.reply = b""
        self.fail = None
        self.closes = 0
        FakeSMBus.instances.append(self)

    def i2c_rdwr(self, *msgs):
        self.ioctls.append([(m.flags, m.addr, len(m) if m.flags & I2C_M_RD else bytes(m)) for m in msgs])
        if self.fail is not None:
            raise self.fail
        for m in msgs:
            if m.flags & I2C_M_RD:
                m.buf[:] = self.reply[:len(m.buf)]

    def close(self):
        self.closes += 1


@pytest.fixture
def fake_smbus2(monkeypatch):
    FakeSMBus.instances = []
    FakeSMBus.open_error = None
    mod = types.ModuleType("smbus2")
    mod.SMBus = FakeSMBus
    mod.i2c_msg = FakeMsg
    monkeypatch.setitem(sys.modules, "smbus2", mod)
    return mod


def test_that_the_module_imports_without_smbus2_and_opening_a_bus_says_what_is_missing(monkeypatch):
    monkeypatch.setitem(sys.modules, "smbus2", None)  # makes `import smbus2` raise ImportError
    with pytest.raises(RuntimeError, match="smbus2 is not installed"):
        SmbusI2CBus(1)


@pytest.mark.parametrize(("spec", "expected"), [
    (1, 1), ("/dev/i2c-3", "/dev/i2c-3"), ("i2c:/dev/i2c-1", "/dev/i2c-1"), ("i2c:2", 2), ("4", 4)])
def test_that_bus_numbers_and_dev_paths_reach_smbus2(fake_smbus2, spec, expected):
    SmbusI2CBus(spec)
    assert FakeSMBus.instances[-1].bus == expected


@pytest.mark.parametrize("spec", ["", "i2c:", "/tmp/i2c-1", "bus1", -1, True, 1.5])
def test_that_malformed_bus_names_are_value_errors_naming_them(fake_smbus2, spec):
    with pytest.raises(ValueError, match="I2C bus") as excinfo:
        SmbusI2CBus(spec)
    assert repr(spec) in str(excinfo.value) or str(spec) in str(excinfo.value)
    assert FakeSMBus.instances == []


def test_that_write_is_a_single_write_message_ended_by_a_stop(fake_smbus2):
    bus = SmbusI2CBus(1)
    bus.write(0x62, b"\x00\x04")
    assert FakeSMBus.instances[0].ioctls == [[(0, 0x62, b"\x00\x04")]]


def test_that_read_is_a_single_read_message(fake_smbus2):
    bus = SmbusI2CBus(1)
    FakeSMBus.instances[0].reply = b"\x04\xd2"
    assert bus.read(0x62, 2) == b"\x04\xd2"
    assert FakeSMBus.instances[0].ioctls == [[(I2C_M_RD, 0x62, 2)]]


def test_that_write_read_is_one_ioctl_with_two_messages_for_a_repeated_start(fake_smbus2):
    bus = SmbusI2CBus(1)
    FakeSMBus.instances[0].reply = b"\x20"
    assert bus.write_read(0x40, b"\x01", 1) == b"\x20"
    assert FakeSMBus.instances[0].ioctls == [[(0, 0x40, b"\x01"), (I2C_M_RD, 0x40, 1)]]


@pytest.mark.parametrize(("op", "call"), [
    ("write", lambda b: b.write(0x62, b"\x00\x04")),
    ("read", lambda b: b.read(0x62, 2)),
    ("write-read", lambda b: b.write_read(0x62, b"\x8f", 2)),
])
def test_that_every_oserror_becomes_an_i2cerror_naming_address_and_operation(fake_smbus2, op, call):
    bus = SmbusI2CBus(1)
    FakeSMBus.instances[0].fail = OSError(errno.EREMOTEIO, "Remote I/O error")
    with pytest.raises(I2CError) as excinfo:
        call(bus)
    assert excinfo.value.errno == errno.EREMOTEIO
    assert "0x62" in str(excinfo.value) and op in str(excinfo.value) and "/dev/i2c-1" in str(excinfo.value)
    assert isinstance(excinfo.value.__cause__, OSError)


def test_that_an_adapter_that_cannot_be_opened_is_an_i2cerror_with_a_hint(fake_smbus2):
    FakeSMBus.open_error = FileNotFoundError(errno.ENOENT, "No such file or directory")
    with pytest.raises(I2CError, match=r"/dev/i2c-7.*i2c_arm") as excinfo:
        SmbusI2CBus("/dev/i2c-7")
    assert excinfo.value.errno == errno.ENOENT


def test_that_close_is_idempotent_and_a_closed_bus_refuses_transfers(fake_smbus2):
    bus = SmbusI2CBus(1)
    bus.close()
    bus.close()
    assert FakeSMBus.instances[0].closes == 1
    with pytest.raises(I2CError, match="closed"):
        bus.write(0x62, b"\x00")
    assert FakeSMBus.instances[0].ioctls == []


@pytest.mark.parametrize(("call", "match"), [
    (lambda b: b.write(0x80, b"\x00"), "7-bit"),
    (lambda b: b.write(-1, b"\x00"), "7-bit"),
    (lambda b: b.read(0x62, 0), "length"),
    (lambda b: b.write_read(0x62, b"\x01", 0), "length"),
])
def test_that_bad_addresses_and_lengths_are_value_errors_before_any_transfer(fake_smbus2, call, match):
    bus = SmbusI2CBus(1)
    with pytest.raises(ValueError, match=match):
        call(bus)
    assert FakeSMBus.instances[0].ioctls == []
