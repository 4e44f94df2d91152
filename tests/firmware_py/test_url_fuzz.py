"""Fuzzing every URL and option-string parser the three programs use: any string gives a parsed value or a
one-line ValueError (UserError where documented), never TypeError, IndexError, an int() message that does not
name the input, or a half-opened device. Hardware and sockets are replaced by recorders, so a string that
parses opens nothing real.
"""

from __future__ import annotations

from importlib.util import find_spec

import pytest
from hypothesis import HealthCheck, given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.cli import hal_urls
from firmware_py.core.cli import UserError
from firmware_py.core.storage import Storage
from firmware_py.core.stream_format import parse_stream_url
from firmware_py.hal import backends, bridge, check_i2c_addr, pwm
from firmware_py.hal import mavlink_link as ml
from firmware_py.payload_config import PayloadConfig
from tests.fuzz_budget import budget

SIM = find_spec("sitl") is not None  # False on the payload-only install (Raspberry Pi): those tests skip
if SIM:
    from sitl.devices.bridge_server import parse_bridge_url
    from sitl.mavlink import transport as mv
needs_sim = pytest.mark.skipif(not SIM, reason="needs the simulator (sitl/), not in the payload-only install")

FUZZ = budget(300, deadline=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

SCHEMES = ["i2c", "tcp", "udp", "udpin", "udpout", "serial", "pwm", "pwm:tcp", "pwm:sysfs", "pwm:pca9685",
           "pwm:mavlink", "pwm:Sysfs", "sitl", "spi", "I2C", "TCP", "", " udp", "udp "]
PIECES = st.one_of(
    st.text(max_size=10),
    st.integers(-10, 10**6).map(str),
    st.sampled_from(["", " ", "0", "1", "15", "16", "255", "256", "65535", "65536", "99999", "0x40", "0x1000",
                     "0b1", "-1", "-0", "+5", "1_0", "1e3", "١٢", "²", "[::1]", "[::1", "::1", "[", "]", "localhost",
                     "127.0.0.1", "0.0.0.0", "/dev/i2c-1", "/dev/ttyAMA0", "/dev/ i2c", "\n", "\t", "ß", "x" * 300]),
)
urls = st.one_of(
    st.text(max_size=40),
    st.builds(lambda pre, scheme, parts, post: pre + ":".join([scheme, *parts]) + post,
              st.sampled_from(["", "", " ", "\n"]), st.sampled_from(SCHEMES), st.lists(PIECES, max_size=5),
              st.sampled_from(["", "", " ", "\t", ":"])),
)
"""Random text, and text shaped like our URLs (scheme, then colon-separated pieces of every kind)."""


def one_line_value_error(exc: BaseException) -> None:
    assert type(exc) in (ValueError, UserError), f"{type(exc).__name__}: {exc}"
    assert str(exc) and "\n" not in str(exc)


def parsed_or_value_error(fn, *args, **kwargs):
    """fn(*args) or None after checking that it failed with a clean one-line ValueError."""
    try:
        return fn(*args, **kwargs)
    except (ValueError, UserError) as exc:
        one_line_value_error(exc)
        return None


def check_port(port: int, allow_zero: bool = False) -> None:
    assert type(port) is int and (0 if allow_zero else 1) <= port <= 65535


def check_host(host: str) -> None:
    assert isinstance(host, str) and host and host == host.strip() and not any(c.isspace() for c in host)


# ----- the hardware recorders ------------------------------------------------------------------------

class Opened:
    """What a backend was asked to open (nothing real is)."""

    def __init__(self, kind: str, *args) -> None:
        self.kind, self.args = kind, args

    def write(self, addr: int, data: bytes) -> None:
        check_i2c_addr(addr)  # the real buses check the same way

    def close(self) -> None:
        pass


class FakeLink:
    def __init__(self) -> None:
        self.mav = mavlink.MAVLink(None)

    def send(self, msg) -> None:
        pass


@pytest.fixture(scope="module")
def no_hardware():
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(backends, "SmbusI2CBus", lambda bus: Opened("smbus", bus))
        mp.setattr(backends, "I2C_BACKENDS", backends.I2C_BACKENDS.builtins_only())
        mp.setattr(bridge, "open_bridge_i2c", lambda url, key=None: Opened("bridge-i2c", *bridge.parse_tcp_url(url)))
        mp.setattr(pwm, "SysfsPwm", lambda chip, ch: Opened("sysfs", chip, ch))
        mp.setattr(pwm, "PWM_BACKENDS", pwm.PWM_BACKENDS.builtins_only())
        mp.setattr(bridge, "open_bridge_pwm", lambda url, key=None: Opened("bridge-pwm", *bridge.parse_pwm_url(url)))
        mp.setattr(ml, "MAVLINK_BACKENDS", ml.MAVLINK_BACKENDS.builtins_only())
        mp.setattr(ml, "PymavlinkLink", lambda url, *_a, **_k: Opened("pymavlink", *ml.mavutil_device(url)))
        if SIM:
            mp.setattr(mv, "UdpTransport", lambda url: Opened("udp", *mv.parse_udp_url(url)))
        yield


# ----- I2C ---------------------------------------------------------------------------------------------

@FUZZ
@given(url=urls)
def test_that_i2c_urls_parse_or_fail_in_one_line(url):
    bus = parsed_or_value_error(backends.parse_i2c_url, url)
    if isinstance(bus, int):
        assert bus >= 0 and int(url.strip()[4:]) == bus
    elif bus is not None:
        assert bus.startswith("/dev/") and bus == url.strip()[4:]


@FUZZ
@given(url=urls)
def test_that_open_i2c_opens_only_well_formed_urls(no_hardware, url):
    bus = parsed_or_value_error(backends.open_i2c, url)
    if bus is not None:
        assert bus.kind in ("smbus", "bridge-i2c")
        if bus.kind == "bridge-i2c":
            check_host(bus.args[0])
            check_port(bus.args[1])


# ----- PWM ---------------------------------------------------------------------------------------------

@FUZZ
@given(url=urls)
def test_that_open_pwm_opens_only_well_formed_urls(no_hardware, url):
    out = parsed_or_value_error(pwm.open_pwm, url, i2c_opener=backends.open_i2c, link=FakeLink(),
                                mav=mavlink.MAVLink(None))
    if out is None:
        return
    if isinstance(out, pwm.Pca9685Pwm):
        assert 0 <= out.addr <= 0x7F and 0 <= out.channel <= 15 and out.bus.kind in ("smbus", "bridge-i2c")
    elif isinstance(out, pwm.MavlinkServoPwm):
        assert 0 < out.servo_n <= 32
    elif out.kind == "sysfs":
        assert all(type(v) is int for v in out.args)
    else:
        assert out.kind == "bridge-pwm" and 0 <= out.args[2] <= 255


@FUZZ
@given(url=urls)
def test_that_open_pwm_without_a_bus_or_link_refuses_those_outputs_cleanly(no_hardware, url):
    out = parsed_or_value_error(pwm.open_pwm, url)
    assert out is None or out.kind in ("sysfs", "bridge-pwm")


@FUZZ
@given(url=urls)
def test_that_the_hal_url_checks_accept_every_url_that_opens(no_hardware, url):
    for check, opened in ((backends.check_i2c_url, parsed_or_value_error(backends.open_i2c, url)),
                          (pwm.check_pwm_url, parsed_or_value_error(pwm.open_pwm, url, i2c_opener=backends.open_i2c,
                                                                    link=FakeLink(), mav=mavlink.MAVLink(None))),
                          (ml.check_mavlink_url, parsed_or_value_error(ml.open_mavlink, url))):
        try:
            check(url)
        except ValueError as exc:
            one_line_value_error(exc)
            assert opened is None, f"{check.__name__} refused {url!r}, which opens"


# ----- the device bridge -------------------------------------------------------------------------------

@FUZZ
@given(url=urls, allow_zero=st.booleans())
def test_that_device_bridge_urls_parse_or_fail_in_one_line(url, allow_zero):
    got = parsed_or_value_error(bridge.parse_tcp_url, url, allow_port_zero=allow_zero)
    if got is not None:
        check_host(got[0])
        check_port(got[1], allow_zero)
        assert not SIM or got == parse_bridge_url(url)
    ch = parsed_or_value_error(bridge.parse_pwm_url, url)
    if ch is not None:
        check_host(ch[0])
        check_port(ch[1])
        assert 0 <= ch[2] <= 255


@FUZZ
@given(url=urls)
def test_that_hal_sitl_urls_are_a_user_error_or_two_bridge_urls(url):
    try:
        i2c, pwm_url = hal_urls(url)
    except UserError as exc:
        one_line_value_error(exc)
        return
    got = parsed_or_value_error(bridge.parse_tcp_url, i2c)  # always parses: hal_urls checks the host the bridge's way
    assert got is None or got[1] == bridge.parse_pwm_url(pwm_url)[1]


@pytest.mark.parametrize("hal", ["sitl:a/b:5761", "sitl:\x1b:1"])
def test_that_hal_urls_only_accepts_hosts_the_device_bridge_accepts(hal):
    try:
        i2c, pwm_url = hal_urls(hal)
    except UserError:
        return
    bridge.parse_tcp_url(i2c)
    bridge.parse_pwm_url(pwm_url)


# ----- MAVLink -----------------------------------------------------------------------------------------

@FUZZ
@given(url=urls)
def test_that_mavlink_urls_translate_or_fail_naming_the_url(url):
    got = parsed_or_value_error(ml.mavutil_device, url)
    if got is not None:
        device, baud = got
        assert isinstance(device, str) and device and type(baud) is int
        if baud:
            assert 50 <= baud <= 20_000_000
        else:
            scheme, _host, port = device.split(":", 1)[0], *device.split(":", 1)[1].rsplit(":", 1)
            assert scheme in ("udpin", "udpout", "tcp")
            check_port(int(port), allow_zero=scheme == "udpin")


@FUZZ
@given(url=urls)
def test_that_open_mavlink_opens_only_well_formed_urls(no_hardware, url):
    link = parsed_or_value_error(ml.open_mavlink, url)
    assert link is None or link.kind == "pymavlink"


@needs_sim
@FUZZ
@given(url=urls)
def test_that_the_sitl_autopilot_transport_urls_parse_or_fail_in_one_line(no_hardware, url):
    got = parsed_or_value_error(mv.parse_udp_url, url)
    if got is not None:
        kind, host, port = got
        assert kind in ("udpin", "udpout") and host
        check_port(port, allow_zero=kind == "udpin")
    transport = parsed_or_value_error(mv.make_transport, url)
    assert (transport is None) == (got is None)


# ----- the live stream, the storage, the payload's whole URL set -------------------------------------

@FUZZ
@given(url=urls, allow_zero=st.booleans())
def test_that_stream_urls_parse_or_fail_in_one_line(url, allow_zero):
    got = parsed_or_value_error(parse_stream_url, url, allow_port_zero=allow_zero)
    if got is not None:
        assert isinstance(got[0], str)  # non-empty (see the test below)
        check_port(got[1], allow_zero)


@pytest.mark.parametrize("url", ["udp:[:14600", "udp:]:14600", "udp:[]:14600"])
def test_that_a_stream_url_never_parses_to_an_empty_host(url):
    host, _ = parsed_or_value_error(parse_stream_url, url) or ("?", 0)
    check_host(host)


storage_text = st.one_of(
    st.text(max_size=30),
    st.builds(lambda parts, seps: "".join(p + s for p, s in zip(parts, seps, strict=False)),
              st.lists(st.one_of(st.floats().map(repr), PIECES, st.sampled_from(["1e999", "-5", ".", "e", "+-1"])),
                       min_size=1, max_size=4),
              st.lists(st.sampled_from(["x", "X", "*", " x ", "", "xx"]), min_size=4, max_size=4)),
)


@FUZZ
@given(text=storage_text)
def test_that_storage_sizes_parse_or_fail_in_one_line(text):
    s = parsed_or_value_error(Storage.parse, text)
    if s is not None:
        assert all(0.5 <= v <= 10_000 for v in (s.length_m, s.width_m, s.height_m))


@FUZZ
@given(mavlink_url=urls, i2c_url=urls, pwm_url=urls, stream_url=st.one_of(st.none(), urls))
def test_that_the_payload_config_refuses_bad_urls_with_one_value_error(mavlink_url, i2c_url, pwm_url, stream_url):
    """PayloadConfig checks the URLs it can before anything is opened (registered schemes are checked later)."""
    parsed_or_value_error(PayloadConfig, mavlink_url=mavlink_url, i2c_url=i2c_url, pwm_url=pwm_url,
                          stream_url=stream_url)
