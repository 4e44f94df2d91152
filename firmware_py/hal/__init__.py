"""Hardware abstraction layer: the small protocols the payload's drivers are written against.

Hardware backends (smbus2 I2C, Linux sysfs PWM, PCA9685, MAVLink over serial/UDP) and the SITL's
emulated devices both implement these, chosen by URL-like strings (DESIGN section 7), so the
drivers above never know which they run on.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:  # only annotated here: the HAL protocols import no implementation
    from firmware_py.hal.signing import MavlinkSigner


class I2CError(OSError):
    """A failed bus transfer (NACK, arbitration lost, timeout): what smbus2 raises as OSError."""


def check_i2c_addr(addr: int) -> int:
    """A 7-bit address, or ValueError naming the bad value (every I2CBus backend checks the same way)."""
    if isinstance(addr, bool) or not isinstance(addr, int) or not 0 <= addr <= 0x7F:
        raise ValueError(f"I2C address must be a 7-bit integer 0x00-0x7f, got {addr!r}")
    return addr


def check_read_len(n: int) -> int:
    """A read length >= 1, or ValueError naming the bad value."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"I2C read length must be an integer >= 1, got {n!r}")
    return n


def check_pulse_us(pulse_us: float, lo: float = 500.0, hi: float = 2500.0) -> float:
    """A servo pulse width within what any hobby servo output can send, or ValueError naming it."""
    if not (math.isfinite(pulse_us) and lo <= pulse_us <= hi):
        raise ValueError(f"servo pulse must be {lo:g}-{hi:g} us, got {pulse_us}")
    return float(pulse_us)


class I2CBus(Protocol):
    """An I2C master. Addresses are 7-bit. Every method raises I2CError on a failed transfer."""

    def write(self, addr: int, data: bytes) -> None:
        """One write transfer (START, addr+W, data..., STOP)."""

    def read(self, addr: int, n: int) -> bytes:
        """One read transfer of n bytes (START, addr+R, n bytes, STOP)."""

    def write_read(self, addr: int, data: bytes, n: int) -> bytes:
        """A combined transfer with a repeated START between the write and the read.

        Only for devices that support it; the LIDAR-Lite v3 does not (use write then read).
        """

    def close(self) -> None: ...


class PwmOutput(Protocol):
    """One servo/ESC PWM channel at a fixed frame rate (50 Hz for hobby servos)."""

    def set_pulse_us(self, pulse_us: float) -> None:
        """Command a pulse width in microseconds; ValueError outside the backend's range."""

    def disable(self) -> None:
        """Stop pulsing (the servo goes limp)."""

    def close(self) -> None: ...


class Clock(Protocol):
    """Monotonic time for the payload. In SITL lockstep, sleeping is what advances the world."""

    def now_ns(self) -> int: ...

    def sleep_until_ns(self, t_ns: int) -> None:
        """Return at (or just after) monotonic time t_ns; at once if that is already past."""


class MavlinkLink(Protocol):
    """A MAVLink 2 connection to the autopilot (pymavlink message objects in and out).

    Besides send/recv, what the payload program reads of a link (so it never probes with getattr):
    its encoder `mav` (source ids and sequence; the MAVLink servo output builds its commands with
    it), its signing state `signer` (None when unsigned) and `signing_active`, and its counters
    `stats` (rx_/tx_ message, error and, when signed, refused-frame counts by name).
    """

    mav: Any
    """The pymavlink `MAVLink` encoder of our end."""

    signer: MavlinkSigner | None
    """The link's signing state (`firmware_py.hal.signing.MavlinkSigner`), None when unsigned."""

    stats: Mapping[str, int]

    @property
    def signing_active(self) -> bool:
        """Whether we sign what we send and check what we receive."""

    def send(self, msg: Any) -> None: ...

    def recv(self) -> list[Any]:
        """All complete messages received so far (never blocks; bad bytes are dropped and counted)."""

    def close(self) -> None: ...
