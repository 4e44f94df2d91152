"""Open a UART (a rangefinder's serial port) from its URL, so the driver above never knows which it is.

    serial:/dev/serial0[:BAUD]   a Linux serial device through pyserial (the Raspberry Pi's header UART
                                 is /dev/serial0; a USB adapter /dev/ttyUSB0); BAUD defaults to 115200,
                                 the TFMini family's factory rate
    SCHEME[:...]                 any backend another layer registered with `register_uart_backend`
                                 (the lockstep SITL's in-memory emulated sensor)

The port is opened non-blocking (pyserial `timeout=0`): `read(n)` returns at once with whatever has
arrived, up to n bytes. That is the whole `SerialPort` protocol a streaming rangefinder needs. A
pseudo-terminal is a real serial port here: the networked SITL serves its emulated TFMini on one, so
this very code path runs in the loop.
"""

from __future__ import annotations

import re
from typing import Protocol

from firmware_py.hal.registry import BackendRegistry

DEFAULT_BAUD = 115_200
STANDARD_BAUDS = (9600, 19200, 38400, 57600, 115200, 230400, 256000, 460800, 921600)
"""The rates the TFMini family accepts (its manuals: standard baud rates only)."""
_FORMS = "serial:/dev/PATH or serial:/dev/PATH:BAUD"


class SerialPort(Protocol):
    """A byte stream from a device: non-blocking reads."""

    def read(self, n: int) -> bytes:
        """Up to n bytes that have arrived; b'' if none (never blocks)."""

    def close(self) -> None: ...


def parse_uart_url(url: str) -> tuple[str, int]:
    """(device path, baud) of a `serial:` URL.

    Raises:
        ValueError: not serial:/dev/PATH[:BAUD] with a standard baud rate (the message names it).
    """
    if not isinstance(url, str):
        raise ValueError(f"serial port URL must be a string like {_FORMS}, got {url!r}")
    m = re.fullmatch(r"serial:(/dev/[^\s:]+)(?::(\d+))?", url.strip(), re.ASCII)
    if not m:
        raise ValueError(f"malformed serial port URL {url!r}: expected {_FORMS}")
    baud = int(m.group(2)) if m.group(2) else DEFAULT_BAUD
    if baud not in STANDARD_BAUDS:
        raise ValueError(f"serial port URL {url!r}: baud {baud} is not one of {', '.join(map(str, STANDARD_BAUDS))}")
    return m.group(1), baud


def _open_pyserial(url: str) -> SerialPort:
    import serial  # pyserial: a base dependency (the MAVLink serial links use it too)

    path, baud = parse_uart_url(url)
    try:
        return serial.Serial(path, baud, timeout=0, exclusive=True)
    except (serial.SerialException, OSError) as exc:
        raise OSError(f"cannot open serial port {path} at {baud} baud: {exc}") from exc


UART_BACKENDS: BackendRegistry[SerialPort] = BackendRegistry(
    "serial port", unknown="malformed serial port URL {url!r}: unknown scheme {scheme!r}", expected=_FORMS)
"""Every `open_uart` scheme: pyserial, and what other layers register."""
UART_BACKENDS.builtin("serial", _open_pyserial, check=parse_uart_url)


def open_uart(url: str) -> SerialPort:
    """Open the serial port a URL names (module docstring). ValueError for a bad URL, OSError if it
    cannot be opened."""
    return UART_BACKENDS.open(url)


def check_uart_url(url: str) -> None:
    """Refuse a malformed URL without opening anything."""
    UART_BACKENDS.check(url)


def register_uart_backend(scheme: str, factory) -> None:
    """Let another layer (the SITL) serve `scheme:...` URLs."""
    UART_BACKENDS.register(scheme, factory)
