"""A simulated I2C bus: the payload's drivers talk to emulated devices through the same I2CBus
protocol they use on the drone, and every transfer costs its wire time on the simulated clock.

Timing: each byte is 9 clocks (8 data bits + ACK), the address byte included, at `bitrate_hz`
(START/STOP and clock stretching are not charged). A transfer advances the clock by its whole wire
time and then hands the data to the device, so a device sees the time at which the STOP (or, for a
read, the last byte) went out. A NACKed transfer costs the address byte only.

Faults, for tests and fault-injection runs (seeded, so a (seed, schedule) pair replays exactly):
`nack_probability` NACKs transfers at random; `fault_until_ns` NACKs every transfer until that
simulated time (a burst, e.g. a loose connector or an EMI event).
"""

from __future__ import annotations

import errno
import math
from typing import Protocol, runtime_checkable

import numpy as np

from firmware_py.hal import I2CError, check_i2c_addr, check_read_len
from firmware_py.hal.backends import register_i2c_backend
from firmware_py.hal.clock import SimClock

BITS_PER_BYTE = 9
_WIRE_TABLE = 64
"""Transfers shorter than this many bytes look their wire time up (the common ones: 1-3 bytes)."""


@runtime_checkable
class SimI2CDevice(Protocol):
    """A device on the simulated bus.

    A device may also define `on_write_read(data, n) -> bytes` for a combined transfer (repeated
    START); without it the bus behaves like a part that supports repeated START: on_write(data)
    then on_read(n).
    """

    def on_write(self, data: bytes) -> None:
        """A write transfer's data bytes (may be empty: an address-only probe)."""

    def on_read(self, n: int) -> bytes:
        """The n bytes a read transfer clocks out."""


_check_addr = check_i2c_addr
_check_count = check_read_len


class SimI2CBus:
    """An I2CBus on a SimClock, with devices attached at 7-bit addresses.

    Args:
        clock: the simulated clock each transfer advances (SimClock.advance_by_ns).
        bitrate_hz: SCL frequency (400 kHz is the LIDAR-Lite's maximum).
        nack_probability: chance that any transfer is NACKed (0 = never).
        rng: generator for the random NACKs (default: seeded 0, so runs repeat).
    """

    def __init__(self, clock: SimClock, bitrate_hz: int = 400_000, *, nack_probability: float = 0.0,
                 rng: np.random.Generator | None = None) -> None:
        if isinstance(bitrate_hz, bool) or not isinstance(bitrate_hz, int) or not 1_000 <= bitrate_hz <= 5_000_000:
            raise ValueError(f"I2C bitrate must be an integer 1 kHz-5 MHz, got {bitrate_hz!r}")
        self.clock = clock
        self.bitrate_hz = bitrate_hz
        self._closed = False
        self._fault_until_ns = -1
        self._nack_probability = 0.0
        self.nack_probability = nack_probability
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.devices: dict[int, SimI2CDevice] = {}
        self.counters: dict[str, int] = dict.fromkeys(("write", "read", "write_read", "nack", "bytes"), 0)
        self._wire_ns = [self.wire_time_ns(n) for n in range(_WIRE_TABLE)]
        self._advance_by_ns = clock.advance_by_ns

    def _update_plain(self) -> None:
        # True while no transfer can fail (open bus, no NACKs configured, no burst): the 500 Hz fast
        # path of write/read tests this one flag instead of three conditions per transfer.
        self._plain = not self._closed and self._nack_probability == 0.0 and self._fault_until_ns < 0

    @property
    def fault_until_ns(self) -> int:
        """NACK every transfer until this simulated time (-1: no burst)."""
        return self._fault_until_ns

    @fault_until_ns.setter
    def fault_until_ns(self, t_ns: int) -> None:
        self._fault_until_ns = int(t_ns)
        self._update_plain()

    @property
    def nack_probability(self) -> float:
        return self._nack_probability

    @nack_probability.setter
    def nack_probability(self, p: float) -> None:
        if not (isinstance(p, int | float) and math.isfinite(p) and 0.0 <= p <= 1.0):
            raise ValueError(f"NACK probability must be in [0, 1], got {p!r}")
        self._nack_probability = float(p)
        self._update_plain()

    def attach(self, addr: int, device: SimI2CDevice) -> None:
        """Put a device at a 7-bit address (ValueError if the address is taken)."""
        _check_addr(addr)
        if addr in self.devices:
            raise ValueError(f"I2C address 0x{addr:02x} already has a device ({self.devices[addr]!r})")
        if not isinstance(device, SimI2CDevice):
            raise ValueError(f"a simulated I2C device needs on_write(data) and on_read(n), got {device!r}")
        self.devices[addr] = device

    def detach(self, addr: int) -> SimI2CDevice:
        """Remove and return the device at addr (a part unplugged or browned out)."""
        try:
            return self.devices.pop(_check_addr(addr))
        except KeyError:
            raise ValueError(f"no device at I2C address 0x{addr:02x}") from None

    def wire_time_ns(self, n_bytes: int) -> int:
        """Time on the wire for n bytes (address bytes included), 9 clocks each."""
        return n_bytes * BITS_PER_BYTE * 1_000_000_000 // self.bitrate_hz

    def _device(self, op: str, addr: int, n: int | None = None) -> SimI2CDevice:
        """The addressed device, or an I2CError after charging the NACKed address byte."""
        device = self.devices.get(addr) if type(addr) is int else None  # attached ones were checked at attach()
        if device is None:
            _check_addr(addr)
        if n is not None and (self._closed or device is None or self._fault_until_ns >= 0
                              or self._nack_probability > 0.0):
            op = f"{op} of {n} bytes"  # only for the error messages below
        if self._closed:
            raise I2CError(errno.EBADF, f"I2C {op} at 0x{addr:02x}: simulated bus is closed")
        reason = None
        if device is None:
            reason = "no device"
        elif self.clock.now_ns() < self._fault_until_ns:
            reason = "fault burst"
        elif self._nack_probability > 0.0 and self.rng.random() < self._nack_probability:
            reason = "random NACK"
        if reason is not None or device is None:
            self.counters["nack"] += 1
            self.clock.advance_by_ns(self.wire_time_ns(1))
            raise I2CError(errno.EREMOTEIO, f"I2C {op} at 0x{addr:02x}: NACK ({reason})")
        return device

    def _charge(self, n_bytes: int) -> None:
        self.counters["bytes"] += n_bytes
        self.clock.advance_by_ns(n_bytes * BITS_PER_BYTE * 1_000_000_000 // self.bitrate_hz)

    def write(self, addr: int, data: bytes) -> None:
        # 4 writes a sample at 500 Hz: the common case (an attached device, an open bus, no NACKs
        # configured) skips the checks of _device.
        device = self.devices.get(addr) if self._plain and type(addr) is int else None
        if device is None:
            device = self._device("write", addr)
        if type(data) is not bytes:
            data = bytes(data)
        counters = self.counters
        counters["write"] += 1
        n = 1 + len(data)
        counters["bytes"] += n
        self._advance_by_ns(self._wire_ns[n] if n < _WIRE_TABLE else self.wire_time_ns(n))
        device.on_write(data)

    def read(self, addr: int, n: int) -> bytes:
        device = self.devices.get(addr) if self._plain and type(addr) is int and type(n) is int \
            and 0 < n < _WIRE_TABLE - 1 else None
        if device is None:
            _check_count(n)
            device = self._device("read", addr, n)
        counters = self.counters
        counters["read"] += 1
        counters["bytes"] += 1 + n
        self._advance_by_ns(self._wire_ns[1 + n] if 1 + n < _WIRE_TABLE else self.wire_time_ns(1 + n))
        data = device.on_read(n)
        return data if type(data) is bytes and len(data) == n else self._checked(data, n, addr)

    def write_read(self, addr: int, data: bytes, n: int) -> bytes:
        _check_count(n)
        device = self._device("write-read", addr, n)
        data = bytes(data)
        self.counters["write_read"] += 1
        self._charge(1 + len(data) + 1 + n)
        combined = getattr(device, "on_write_read", None)
        if combined is not None:
            return self._checked(combined(data, n), n, addr)
        device.on_write(data)
        return self._checked(device.on_read(n), n, addr)

    @staticmethod
    def _checked(data: bytes, n: int, addr: int) -> bytes:
        data = bytes(data)
        if len(data) != n:
            raise RuntimeError(f"simulated device at 0x{addr:02x} returned {len(data)} bytes for a read of {n}")
        return data

    def close(self) -> None:
        self._closed = True
        self._update_plain()

    def handle(self) -> SimBusHandle:
        """A separately closable view of this bus (what `open_i2c('sitl')` hands out)."""
        return SimBusHandle(self)


class SimBusHandle:
    """One opener's view of a shared SimI2CBus: closing it does not close the bus for others,
    as closing one /dev/i2c-N file descriptor leaves the adapter to the rest."""

    def __init__(self, bus: SimI2CBus) -> None:
        self.bus = bus
        self._closed = False

    def _open(self) -> SimI2CBus:
        if self._closed:
            raise I2CError(errno.EBADF, "simulated I2C bus handle is closed")
        return self.bus

    def write(self, addr: int, data: bytes) -> None:
        self._open().write(addr, data)

    def read(self, addr: int, n: int) -> bytes:
        return self._open().read(addr, n)

    def write_read(self, addr: int, data: bytes, n: int) -> bytes:
        return self._open().write_read(addr, data, n)

    def close(self) -> None:
        self._closed = True


def register_sim_bus(bus: SimI2CBus, scheme: str = "sitl") -> None:
    """Make `open_i2c('sitl')` (or `'sitl:anything'`) open handles on this simulated bus."""
    register_i2c_backend(scheme, lambda url: bus.handle())
