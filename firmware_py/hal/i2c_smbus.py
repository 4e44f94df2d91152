"""I2CBus on Linux through smbus2 (`/dev/i2c-N`, the Raspberry Pi's `i2c:/dev/i2c-1`).

Every transfer goes through the kernel's I2C_RDWR ioctl (`SMBus.i2c_rdwr`) with raw `i2c_msg`
messages rather than the SMBus helpers, because the helpers decide for us whether a register read
is one combined transfer (repeated START) or two: `write` and `read` are each one message, ended by
a STOP, and only `write_read` puts two messages in one ioctl (repeated START between them). The
LIDAR-Lite v3 does not support repeated START, so its driver uses `write` then `read`.

smbus2 is imported when a bus is opened, not when this module is, so the firmware imports (and its
tests run) on machines without it.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

from firmware_py.hal import I2CError, check_i2c_addr, check_read_len

_INSTALL_HINT = "smbus2 is not installed (pip install smbus2, or the project's 'hw' extra)"


def _smbus2() -> ModuleType:
    try:
        return importlib.import_module("smbus2")
    except ImportError as exc:
        raise RuntimeError(f"SmbusI2CBus needs {_INSTALL_HINT}") from exc


def _device(bus: int | str) -> int | str:
    """smbus2's bus argument from a bus number, '/dev/i2c-N', or 'i2c:/dev/i2c-N' / 'i2c:N'."""
    if isinstance(bus, bool) or not isinstance(bus, int | str):
        raise ValueError(f"I2C bus must be a bus number or a /dev path, got {bus!r}")
    if isinstance(bus, int):
        if bus < 0:
            raise ValueError(f"I2C bus number must be >= 0, got {bus}")
        return bus
    spec = bus.strip()
    if spec.startswith("i2c:"):
        spec = spec[4:]
    if spec.isdecimal():
        return int(spec)
    if spec.startswith("/dev/") and len(spec) > 5:
        return spec
    raise ValueError(f"I2C bus must be a bus number or a /dev path such as /dev/i2c-1, got {bus!r}")


_check_addr = check_i2c_addr
_check_count = check_read_len


class SmbusI2CBus:
    """An I2CBus on a Linux /dev/i2c-N adapter.

    Args:
        bus: bus number (1 for the Pi's header pins), '/dev/i2c-N', or the URL form 'i2c:/dev/i2c-N'.

    Raises:
        RuntimeError: smbus2 is not installed.
        I2CError: the adapter cannot be opened (no such device, no permission).
    """

    def __init__(self, bus: int | str) -> None:
        device = _device(bus)
        smbus2 = _smbus2()
        self.name = device if isinstance(device, str) else f"/dev/i2c-{device}"
        self._msg: Any = smbus2.i2c_msg
        try:
            self._bus: Any = smbus2.SMBus(device)
        except OSError as exc:
            raise I2CError(exc.errno, f"cannot open I2C adapter {self.name}: {exc.strerror or exc} "
                                      "(is I2C enabled, e.g. dtparam=i2c_arm=on, and are you in group i2c?)"
                           ) from exc
        self._closed = False

    def _transfer(self, op: str, addr: int, *msgs: Any) -> None:
        if self._closed:
            raise I2CError(f"I2C {op} at 0x{addr:02x} on {self.name}: bus is closed")
        try:
            self._bus.i2c_rdwr(*msgs)
        except OSError as exc:
            # EREMOTEIO/ENXIO is a NACK, ETIMEDOUT a stretched or stuck bus, EAGAIN lost arbitration.
            raise I2CError(exc.errno, f"I2C {op} at 0x{addr:02x} on {self.name} failed: "
                                      f"{exc.strerror or exc}") from exc

    def write(self, addr: int, data: bytes) -> None:
        """One write message (START, addr+W, data, STOP). Empty data is an address-only probe."""
        _check_addr(addr)
        self._transfer("write", addr, self._msg.write(addr, bytes(data)))

    def read(self, addr: int, n: int) -> bytes:
        """One read message of n bytes (START, addr+R, n bytes, STOP)."""
        _check_addr(addr)
        msg = self._msg.read(addr, _check_count(n))
        self._transfer(f"read of {n} bytes", addr, msg)
        return bytes(msg)

    def write_read(self, addr: int, data: bytes, n: int) -> bytes:
        """Write then read in one ioctl, with a repeated START between them (no STOP)."""
        _check_addr(addr)
        rd = self._msg.read(addr, _check_count(n))
        self._transfer(f"write-read of {n} bytes", addr, self._msg.write(addr, bytes(data)), rd)
        return bytes(rd)

    def close(self) -> None:
        """Release the adapter; idempotent."""
        if not self._closed:
            self._closed = True
            self._bus.close()

    def __enter__(self) -> SmbusI2CBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SmbusI2CBus({self.name!r})"
