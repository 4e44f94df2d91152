"""Open an I2C bus from its URL, so the drivers above never know which backend they run on.

    i2c:/dev/i2c-N   a Linux adapter through smbus2 (the Raspberry Pi header is i2c:/dev/i2c-1)
    i2c:N            the same, by bus number
    tcp:HOST:PORT    the SITL's simulated bus over the networked-SITL device bridge (firmware_py.hal.bridge)
    SCHEME[:...]     any backend another layer registered with `register_i2c_backend`

The SITL registers its simulated bus (`sitl`) here: firmware_py never imports sitl, the SITL
imports firmware_py and hands it a factory, as crazyflie's `get_link_driver(uri)` picks a link.
The schemes live in `I2C_BACKENDS`, a `firmware_py.hal.registry.BackendRegistry` (the rules every
URL-selected backend follows).

`open_i2c(url, key=...)`: the key authenticates the device bridge (`tcp:`), the one bus that is a
network link; a local bus (`i2c:`, a registered in-process backend) has no link to authenticate and
ignores it, so a program can pass its key whatever bus it was given.
"""

from __future__ import annotations

import re
from collections.abc import Callable

from firmware_py.hal import I2CBus
from firmware_py.hal.i2c_smbus import SmbusI2CBus
from firmware_py.hal.registry import BackendRegistry

I2CFactory = Callable[[str], I2CBus]
"""Makes a bus from the full URL (so a backend can read its own options after the scheme)."""

_FORMS = "i2c:/dev/i2c-N or i2c:N"


def parse_i2c_url(url: str) -> int | str:
    """The smbus2 bus argument of an `i2c:` URL: a bus number or a /dev path.

    Raises:
        ValueError: the URL is not i2c:/dev/i2c-N or i2c:N (the message names it).
    """
    if not isinstance(url, str):
        raise ValueError(f"I2C bus URL must be a string like {_FORMS}, got {url!r}")
    m = re.fullmatch(r"i2c:(?:(\d+)|(/dev/\S+))", url.strip(), re.ASCII)  # ASCII digits only, as the bridge
    if not m:
        raise ValueError(f"malformed I2C bus URL {url!r}: expected {_FORMS}")
    return int(m.group(1)) if m.group(1) is not None else m.group(2)


def _open_smbus(url: str) -> I2CBus:
    return SmbusI2CBus(parse_i2c_url(url))


def _open_bridge(url: str, key: bytes | None = None) -> I2CBus:
    """The device bridge, imported on first use (only a networked SITL run needs sockets here)."""
    from firmware_py.hal.bridge import open_bridge_i2c
    return open_bridge_i2c(url, key=key)


def _check_bridge(url: str) -> None:
    from firmware_py.hal.bridge import parse_tcp_url
    parse_tcp_url(url)


I2C_BACKENDS: BackendRegistry[I2CBus] = BackendRegistry(
    "I2C bus", credential="key", unknown="malformed I2C bus URL {url!r}: unknown scheme {scheme!r}", expected=_FORMS)
"""Every `open_i2c` scheme: the built-in smbus2 adapter and device bridge, and what other layers register."""
I2C_BACKENDS.builtin("i2c", _open_smbus, check=parse_i2c_url)
I2C_BACKENDS.builtin("tcp", _open_bridge, takes_credential=True, check=_check_bridge)


def register_i2c_backend(scheme: str, factory: I2CFactory) -> None:
    """Let another layer provide `SCHEME:...` buses (re-registering a scheme replaces it; the
    built-in `i2c` and `tcp` cannot be replaced)."""
    I2C_BACKENDS.register(scheme, factory)


def unregister_i2c_backend(scheme: str) -> None:
    """Forget a registered scheme (a SITL run tearing down); unknown schemes are ignored."""
    I2C_BACKENDS.unregister(scheme)


def registered_i2c_schemes() -> list[str]:
    """Every scheme open_i2c accepts, the built-in ones first."""
    return I2C_BACKENDS.schemes()


def check_i2c_url(url: str) -> None:
    """Refuse a malformed or unknown I2C bus URL without opening anything (ValueError naming it);
    a registered scheme's options are checked when it is opened."""
    _check_text(url)
    I2C_BACKENDS.check(url)


def _check_text(url: object) -> None:
    if not isinstance(url, str) or not url.strip():
        raise ValueError(f"I2C bus URL must be a non-empty string like {_FORMS}, got {url!r}")


def open_i2c(url: str, *, key: bytes | None = None) -> I2CBus:
    """An I2CBus from its URL (see the module docstring).

    Args:
        key: the 32-byte key the device bridge (`tcp:`) authenticates with; ignored by local buses.

    Raises:
        ValueError: a malformed URL or an unknown scheme (the message names the URL), or a bad key.
        RuntimeError: `i2c:` without smbus2 installed.
        I2CError: the adapter cannot be opened (EACCES: the device bridge refused or failed authentication).
    """
    _check_text(url)
    return I2C_BACKENDS.open(url, key)
