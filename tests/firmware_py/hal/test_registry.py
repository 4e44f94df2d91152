"""One registry, one rule set: I2C buses, PWM outputs and MAVLink links pick their backend by scheme the same way."""

import pytest

from firmware_py.hal import backends, pwm
from firmware_py.hal import mavlink_link as ml
from firmware_py.hal.registry import BackendRegistry, Credential


@pytest.fixture
def clean(monkeypatch):
    """The three module registries with their built-ins and nothing registered."""
    monkeypatch.setattr(backends, "I2C_BACKENDS", backends.I2C_BACKENDS.builtins_only())
    monkeypatch.setattr(pwm, "PWM_BACKENDS", pwm.PWM_BACKENDS.builtins_only())
    monkeypatch.setattr(ml, "MAVLINK_BACKENDS", ml.MAVLINK_BACKENDS.builtins_only())


# (register, unregister, open, a URL of scheme "emu", a built-in scheme) for each kind of backend.
KINDS = {
    "i2c": (backends.register_i2c_backend, backends.unregister_i2c_backend, backends.open_i2c, "emu:bus0", "tcp"),
    "pwm": (pwm.register_pwm_backend, pwm.unregister_pwm_backend, pwm.open_pwm, "pwm:emu:0", "sysfs"),
    "mavlink": (ml.register_mavlink_backend, ml.unregister_mavlink_backend, ml.open_mavlink, "emu:x", "udp"),
}


@pytest.mark.parametrize("kind", KINDS)
def test_that_every_kind_opens_a_registered_scheme_with_the_whole_url(clean, kind):
    register, unregister, opener, url, _ = KINDS[kind]
    seen = []
    register("emu", lambda u: seen.append(u) or "opened")
    assert opener(f" {url} ") == "opened" and seen == [url]
    unregister("emu")
    with pytest.raises(ValueError, match="'emu'"):
        opener(url)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("scheme", ["", "Emu", "e mu", "9emu", "emu:", "émù", None])
def test_that_every_kind_refuses_the_same_malformed_schemes(clean, kind, scheme):
    register = KINDS[kind][0]
    with pytest.raises(ValueError, match="scheme"):
        register(scheme, lambda u: None)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("scheme", ["emu", "emu2", "e+m.u-x"])
def test_that_every_kind_accepts_the_same_well_formed_schemes(clean, kind, scheme):
    register, unregister = KINDS[kind][:2]
    register(scheme, lambda u: None)
    unregister(scheme)


@pytest.mark.parametrize("kind", KINDS)
def test_that_no_kind_lets_a_built_in_be_replaced_or_removed(clean, kind):
    register, unregister, _, _, builtin = KINDS[kind]
    with pytest.raises(ValueError, match="built-in"):
        register(builtin, lambda u: None)
    with pytest.raises(ValueError, match="built-in"):
        unregister(builtin)


@pytest.mark.parametrize("kind", KINDS)
def test_that_every_kind_refuses_a_factory_that_cannot_be_called(clean, kind):
    with pytest.raises(ValueError, match="callable"):
        KINDS[kind][0]("emu", "not a factory")


@pytest.mark.parametrize(("kind", "known"), [
    ("i2c", "known: i2c, tcp, emu"), ("pwm", "known: sysfs, pca9685, mavlink, tcp, emu"),
    ("mavlink", "known: serial, udp, udpin, udpout, tcp, emu")])
def test_that_an_unknown_scheme_names_the_url_and_lists_every_known_scheme(clean, kind, known):
    register, _, opener, url, _ = KINDS[kind]
    register("emu", lambda u: None)
    bad = url.replace("emu", "warp")
    with pytest.raises(ValueError) as excinfo:
        opener(bad)
    assert repr(bad) in str(excinfo.value) and known in str(excinfo.value)


def test_that_a_key_reaches_only_the_factories_that_take_it_and_local_ones_run_without(clean):
    seen = {}
    backends.register_i2c_backend("keyed", lambda url, key=None: seen.setdefault("keyed", key))
    backends.register_i2c_backend("local", lambda url: "local bus")
    pwm.register_pwm_backend("keyed", lambda url, key=None: seen.setdefault("pwm", key))
    assert backends.open_i2c("keyed:x", key=b"k" * 32) == b"k" * 32
    assert backends.open_i2c("local:x", key=b"k" * 32) == "local bus"
    assert pwm.open_pwm("pwm:keyed:1", key=b"p" * 32) == b"p" * 32


def test_that_a_required_credential_is_never_dropped():
    reg = BackendRegistry("link", credential="signing", policy=Credential.REQUIRED)
    reg.register("signs", lambda url, signing=None: ("signed", signing))
    reg.register("plain", lambda url: "plain")
    assert reg.open("signs:x", "cfg") == ("signed", "cfg")
    assert reg.open("plain:x") == "plain"
    with pytest.raises(ValueError, match="does not support signing"):
        reg.open("plain:x", "cfg")


def test_that_module_options_go_to_the_built_ins_only():
    reg = BackendRegistry("thing")
    reg.builtin("own", lambda url, bus=None: ("own", bus))
    reg.register("other", lambda url: "other")
    assert reg.open("own:1", bus="b") == ("own", "b")
    assert reg.open("other:1", bus="b") == "other"


@pytest.mark.parametrize(("check", "url"), [
    (backends.check_i2c_url, "i2c:x"), (backends.check_i2c_url, "tcp:host"), (backends.check_i2c_url, "spi:0"),
    (pwm.check_pwm_url, "pwm:sysfs:0"), (pwm.check_pwm_url, "pwm:mavlink:33"), (pwm.check_pwm_url, "pwm:warp:1"),
    (ml.check_mavlink_url, "serial:"), (ml.check_mavlink_url, "udp:host"), (ml.check_mavlink_url, "warp:1")])
def test_that_a_check_refuses_a_malformed_or_unknown_url_naming_it(clean, check, url):
    with pytest.raises(ValueError) as excinfo:
        check(url)
    assert repr(url) in str(excinfo.value)


def test_that_a_check_accepts_a_registered_scheme_without_opening_it(clean):
    opened = []
    ml.register_mavlink_backend("emu", opened.append)
    backends.register_i2c_backend("emu", opened.append)
    pwm.register_pwm_backend("emu", opened.append)
    ml.check_mavlink_url("emu:anything")
    backends.check_i2c_url("emu:anything")
    pwm.check_pwm_url("pwm:emu:anything")
    assert opened == []


def test_that_builtins_only_leaves_the_original_registry_alone():
    reg = BackendRegistry("thing")
    reg.builtin("own", lambda url: "own")
    reg.register("other", lambda url: "other")
    fresh = reg.builtins_only()
    assert fresh.schemes() == ["own"] and reg.schemes() == ["own", "other"]
