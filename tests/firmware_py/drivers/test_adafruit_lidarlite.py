"""A driver nobody here wrote, Adafruit's CircuitPython `adafruit_lidarlite.LIDARLite`, against the
same emulated part as ours: if both read the same centimetres, the emulator models the part rather
than our driver's assumptions about it.

Adafruit's driver talks to a `busio.I2C`; `BusioShim` is one, mapped onto the SimI2CBus. Its
`writeto_then_readfrom` is a SPLIT write then read (a STOP between them). Blinka's Linux busio does
a combined transfer (repeated START, `read_i2c_block_data`) unless called with `stop=True`, and
Adafruit's I2CDevice does not pass `stop`. The v3 manual says the part does not support repeated
START: its register reads would not be answered (the emulator, like a Pi kernel in combined mode,
reads 0xff), and Adafruit's status poll (no deadline) would spin on a busy bit that is always set.
So a shim that works with this part must split, as ArduPilot's `set_split_transfers(true)` does;
the last test shows the combined read failing on the emulator.
"""

import importlib
import sys
import types

import pytest

from firmware_py.drivers.lidarlite import PRESET_DEFAULT, LidarLite, LidarLiteConfig, ReadStatus
from firmware_py.hal.clock import SimClock

pytest.importorskip("sitl", reason="the firmware against the simulator (sitl/): not in the payload-only install")
from sitl.devices.i2c_sim import SimI2CBus
from sitl.devices.lidarlite_emu import EmulatedLidarLite


class BusioShim:
    """The part of `busio.I2C` that adafruit_bus_device uses, on a SimI2CBus."""

    def __init__(self, bus):
        self.bus = bus
        self._locked = False
        self.combined = 0

    def try_lock(self):
        if self._locked:
            return False
        self._locked = True
        return True

    def unlock(self):
        self._locked = False

    def writeto(self, address, buffer, *, start=0, end=None):
        self.bus.write(address, bytes(buffer[start:end]))

    def readfrom_into(self, address, buffer, *, start=0, end=None):
        end = len(buffer) if end is None else end
        buffer[start:end] = self.bus.read(address, end - start)

    def writeto_then_readfrom(self, address, buffer_out, buffer_in, *, out_start=0, out_end=None, in_start=0,
                              in_end=None, stop=False):
        # Split on purpose, whatever `stop` says: the LIDAR-Lite v3 has no repeated START.
        self.writeto(address, buffer_out, start=out_start, end=out_end)
        self.readfrom_into(address, buffer_in, start=in_start, end=in_end)


@pytest.fixture
def adafruit_lidarlite(monkeypatch):
    # Blinka provides `micropython` and `digitalio`; where it cannot be installed (or fails to detect
    # the board), the two names the driver imports are shimmed.
    for name, attrs in (("micropython", {"const": lambda x: x}),
                        ("digitalio", {"Direction": types.SimpleNamespace(INPUT=0, OUTPUT=1)})):
        try:
            importlib.import_module(name)
        except Exception:  # ImportError, or Blinka refusing an unknown board
            monkeypatch.setitem(sys.modules, name, types.SimpleNamespace(**attrs))
    return pytest.importorskip(
        "adafruit_lidarlite",
        reason="Adafruit's driver is not installed (pip install adafruit-circuitpython-lidarlite "
               "adafruit-circuitpython-busdevice)")


class Rig:
    """One emulated part on one bus, with Adafruit's driver and ours both attached to it."""

    def __init__(self, module, monkeypatch, range_m):
        self.range_m = range_m
        self.clock = SimClock()
        self.bus = SimI2CBus(self.clock)
        self.part = EmulatedLidarLite(self.clock, lambda t_ns: self.range_m)
        self.bus.attach(0x62, self.part)
        # Adafruit's driver sleeps with time.sleep (0.5 s at start-up, 1 ms after each write):
        # in simulated time that is the clock advancing.
        monkeypatch.setattr(module, "time", types.SimpleNamespace(
            sleep=lambda s: self.clock.advance_by_ns(round(s * 1e9))))
        self.shim = BusioShim(self.bus)
        self.adafruit = module.LIDARLite(self.shim)  # CONFIG_DEFAULT
        self.ours = LidarLite(self.bus, self.clock, LidarLiteConfig(preset=PRESET_DEFAULT))


@pytest.mark.parametrize("true_m", [0.8, 3.21, 7.891, 15.5, 31.07])
def test_that_adafruits_driver_reads_the_same_centimetres_as_ours(adafruit_lidarlite, monkeypatch, true_m):
    rig = Rig(adafruit_lidarlite, monkeypatch, true_m)
    theirs_cm = rig.adafruit.distance
    ours = rig.ours.read()
    assert ours.status == ReadStatus.OK
    assert theirs_cm == round(ours.range_m * 100) == round(true_m * 100)
    assert rig.part.counters["acquisitions"] == 2
    assert rig.part.counters["combined_transfers"] == 0


def test_that_both_drivers_agree_over_a_changing_scene(adafruit_lidarlite, monkeypatch):
    rig = Rig(adafruit_lidarlite, monkeypatch, 1.0)
    for true_m in (2.0, 9.99, 4.56, 27.3, 0.61):
        rig.range_m = true_m
        theirs_cm = rig.adafruit.distance
        assert theirs_cm == round(rig.ours.read().range_m * 100) == round(true_m * 100)


def test_that_no_echo_is_an_error_for_adafruit_and_no_return_for_ours(adafruit_lidarlite, monkeypatch):
    rig = Rig(adafruit_lidarlite, monkeypatch, None)
    with pytest.raises(RuntimeError, match="NO_PEAK"):
        _ = rig.adafruit.distance
    assert rig.ours.read().status == ReadStatus.NO_RETURN


def test_that_the_split_shim_reads_the_part_where_a_combined_transfer_reads_garbage(adafruit_lidarlite, monkeypatch):
    rig = Rig(adafruit_lidarlite, monkeypatch, 12.34)
    rig.ours.read()
    split = bytearray(2)
    rig.shim.writeto_then_readfrom(0x62, b"\x8f", split)
    assert int.from_bytes(split, "big") == 1234
    assert rig.bus.write_read(0x62, b"\x8f", 2) == b"\xff\xff"  # what a repeated-START busio would get
