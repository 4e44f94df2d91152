"""open_i2c: URLs pick the backend; other layers register schemes without firmware_py importing them."""

import subprocess
import sys
import types

import pytest

from firmware_py.hal import backends
from firmware_py.hal.backends import (
    open_i2c,
    parse_i2c_url,
    register_i2c_backend,
    registered_i2c_schemes,
    unregister_i2c_backend,
)
from firmware_py.hal.i2c_smbus import SmbusI2CBus


class FakeSMBus:
    def __init__(self, bus):
        self.bus = bus

    def close(self):
        pass


@pytest.fixture
def fake_smbus2(monkeypatch):
    mod = types.ModuleType("smbus2")
    mod.SMBus = FakeSMBus
    mod.i2c_msg = object()
    monkeypatch.setitem(sys.modules, "smbus2", mod)


@pytest.fixture
def clean_registry(monkeypatch):
    monkeypatch.setattr(backends, "I2C_BACKENDS", backends.I2C_BACKENDS.builtins_only())


@pytest.mark.parametrize(("url", "expected"), [
    ("i2c:/dev/i2c-1", "/dev/i2c-1"), ("i2c:1", 1), ("i2c:0", 0), (" i2c:12 ", 12), ("i2c:/dev/i2c-22", "/dev/i2c-22")])
def test_that_i2c_urls_parse_to_a_bus_number_or_dev_path(url, expected):
    assert parse_i2c_url(url) == expected


@pytest.mark.parametrize("url", ["i2c:/dev/i2c-1", "i2c:1"])
def test_that_i2c_urls_open_smbus2_on_that_adapter(fake_smbus2, url):
    bus = open_i2c(url)
    assert isinstance(bus, SmbusI2CBus)
    assert bus._bus.bus == parse_i2c_url(url)


@pytest.mark.parametrize("url", ["i2c", "i2c:", "i2c:abc", "i2c:/tmp/i2c-1", "i2c:-1", "i2c:1:2", "I2C:1", "spi:0",
                                 "", "   ", "sitl"])
def test_that_malformed_urls_are_value_errors_naming_the_url(clean_registry, url):
    with pytest.raises(ValueError) as excinfo:
        open_i2c(url)
    assert repr(url) in str(excinfo.value)


def test_that_a_registered_backend_opens_its_scheme_and_gets_the_whole_url(clean_registry):
    seen = []
    sentinel = object()

    def factory(url):
        seen.append(url)
        return sentinel

    register_i2c_backend("sitl", factory)
    assert open_i2c("sitl") is sentinel
    assert open_i2c("sitl:bus0") is sentinel
    assert seen == ["sitl", "sitl:bus0"]
    assert registered_i2c_schemes() == ["i2c", "tcp", "sitl"]
    unregister_i2c_backend("sitl")
    with pytest.raises(ValueError, match="unknown scheme 'sitl'"):
        open_i2c("sitl")


@pytest.mark.parametrize(("scheme", "factory", "match"), [
    ("i2c", lambda url: None, "built-in"),
    ("tcp", lambda url: None, "built-in"),
    ("Sitl", lambda url: None, "scheme"),
    ("", lambda url: None, "scheme"),
    ("si tl", lambda url: None, "scheme"),
    ("sitl", "not callable", "callable"),
])
def test_that_bad_registrations_are_refused(clean_registry, scheme, factory, match):
    with pytest.raises(ValueError, match=match):
        register_i2c_backend(scheme, factory)
    assert registered_i2c_schemes() == ["i2c", "tcp"]


def test_that_firmware_py_hal_and_driver_never_import_sitl_or_ground():
    code = ("import sys, firmware_py.hal.backends, firmware_py.hal.i2c_smbus, firmware_py.drivers.lidarlite\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('sitl', 'ground')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
