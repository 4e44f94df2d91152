"""Device bridge authentication, client side: the right key works, a wrong key or a key on one side only is
refused with a clear error (one line and exit 2 from `pilescan-payload`), and an impostor server is refused."""

from __future__ import annotations

import errno
import secrets
import threading

import numpy as np
import pytest

from firmware_py.cli import build_parser, config_from_args, main
from firmware_py.core.cli import ExitCode
from firmware_py.core.samplelog import read_samplelog
from firmware_py.drivers.lidarlite import LidarLite
from firmware_py.hal import I2CError
from firmware_py.hal import bridge as br
from firmware_py.hal.backends import open_i2c
from firmware_py.hal.bridge import STATUS_OK, BridgeConnection, BridgeI2CBus, check_bridge_key
from firmware_py.hal.clock import MonotonicClock, SimClock
from firmware_py.hal.pwm import open_pwm

pytest.importorskip("sitl", reason="the firmware against the simulator (sitl/): not in the payload-only install")
from sitl.devices.bridge_server import DeviceBridgeServer
from sitl.devices.i2c_sim import SimI2CBus
from sitl.devices.lidarlite_emu import EmulatedLidarLite
from sitl.devices.servo_emu import EmulatedServo

KEY = bytes(range(1, 33))
OTHER = bytes(range(2, 34))
LIDAR = 0x62
NOBODY = "udpout:127.0.0.1:9"  # the discard port: no autopilot there


class WallSimClock(MonotonicClock):
    """The emulator on the payload's own clock (a CLI run), as the networked SITL paces it."""

    def advance_by_ns(self, dt_ns: int) -> None:
        pass


class Rig:
    """A device bridge serving an emulated LIDAR-Lite (7.25 m) and servo, with or without a key."""

    def __init__(self, key: bytes | None, clock=None, server_cls=DeviceBridgeServer) -> None:
        self.clock = clock or SimClock()
        bus = SimI2CBus(self.clock)
        bus.attach(LIDAR, EmulatedLidarLite(self.clock, lambda _t: 7.25))
        self.servo = EmulatedServo(self.clock)
        self.server = server_cls(bus, {0: self.servo}, lock=threading.Lock(), key=key).start()

    def url(self, channel: int | None = None) -> str:
        host, port = self.server.address
        return f"tcp:{host}:{port}" if channel is None else f"pwm:tcp:{host}:{port}:{channel}"

    def close(self) -> None:
        for conn in list(br._SHARED.values()):
            conn.close()
        self.server.close()


@pytest.fixture
def keyed():
    rig = Rig(KEY)
    yield rig
    rig.close()


@pytest.fixture
def open_rig():
    rig = Rig(None)
    yield rig
    rig.close()


def test_that_the_right_key_authenticates_and_the_devices_work_as_before(keyed):
    bus = open_i2c(keyed.url(), key=KEY)
    assert isinstance(bus, BridgeI2CBus) and bus.conn.authenticated
    lidar = LidarLite(bus, keyed.clock)
    assert [lidar.read().range_m for _ in range(2)] == [7.25, 7.25]
    servo = open_pwm(keyed.url(0), key=KEY)
    assert servo.conn is bus.conn  # one authenticated connection for both, as without a key
    servo.set_pulse_us(1700)
    assert keyed.servo.pulses == 1
    servo.close()
    bus.close()
    assert keyed.server.counters["authenticated"] == 1
    assert keyed.server.counters["auth_failed"] == keyed.server.counters["unauthenticated"] == 0


def test_that_a_reconnect_authenticates_again(keyed):
    bus = open_i2c(keyed.url(), key=KEY)
    bus.conn._fail()  # as after a lost connection
    bus.write(LIDAR, b"\x02")
    assert bus.read(LIDAR, 1) == b"\x80"  # SIG_COUNT_VAL's power-on value
    assert bus.conn.counters["connects"] == 2 and keyed.server.counters["authenticated"] == 2
    bus.close()


def test_that_a_wrong_key_is_refused_by_the_server_and_counted(keyed):
    for opener, url in ((open_i2c, keyed.url()), (open_pwm, keyed.url(0))):
        with pytest.raises(I2CError, match="authentication failed: wrong key") as excinfo:
            opener(url, key=OTHER)
        assert excinfo.value.errno == errno.EACCES and "same key" in str(excinfo.value)
        assert "\n" not in str(excinfo.value)
    assert keyed.server.counters["auth_failed"] == 2 and keyed.server.counters["authenticated"] == 0
    assert br._SHARED == {}  # nothing kept open
    assert keyed.servo.pulses == 0


def test_that_a_client_without_a_key_is_refused_by_a_keyed_server_with_a_hint(keyed):
    with pytest.raises(I2CError, match="requires authentication") as excinfo:
        open_i2c(keyed.url())
    assert excinfo.value.errno == errno.EACCES and "--signing-key" in str(excinfo.value)
    assert keyed.server.counters["unauthenticated"] == 1


def test_that_a_keyed_client_refuses_a_server_that_does_not_authenticate(open_rig):
    with pytest.raises(I2CError, match="does not authenticate") as excinfo:
        open_i2c(open_rig.url(), key=KEY)
    assert excinfo.value.errno == errno.EACCES and "--signing-key" in str(excinfo.value)
    assert open_rig.servo.pulses == 0 and br._SHARED == {}


def test_that_without_keys_nothing_changes(open_rig):
    bus = open_i2c(open_rig.url())
    bus.write(LIDAR, b"\x02")
    assert not bus.conn.authenticated and bus.read(LIDAR, 1) == b"\x80"
    assert open_rig.server.counters["authenticated"] == 0 and not open_rig.server.authenticates
    bus.close()


class ImpostorServer(DeviceBridgeServer):
    """Takes any proof and answers with garbage: what a server without the key could do at best."""

    def _auth(self, client, op, payload):
        status, body = super()._auth(client, op, payload)
        if op == br.OP_AUTH_PROVE:
            client.authenticated = True
            return STATUS_OK, secrets.token_bytes(br.PROOF_SIZE)
        return status, body


def test_that_a_server_that_cannot_prove_the_key_is_refused():
    rig = Rig(OTHER, server_cls=ImpostorServer)
    try:
        with pytest.raises(I2CError, match="could not prove it holds the key") as excinfo:
            BridgeConnection(*rig.server.address, key=KEY)
        assert excinfo.value.errno == errno.EACCES
    finally:
        rig.close()


def test_that_connections_with_different_keys_are_not_shared(open_rig):
    host, port = open_rig.server.address
    plain = br.shared_connection(host, port)
    assert br.shared_connection(host, port) is plain
    with pytest.raises(I2CError, match="does not authenticate"):
        br.shared_connection(host, port, key=KEY)  # would have been handed the plain one if shared by address
    plain.close()


@pytest.mark.parametrize("key", [b"", b"short", bytes(32), "0" * 32, bytes(33)],
                         ids=["empty", "short", "zeros", "str", "long"])
def test_that_bad_keys_are_value_errors_before_connecting(key):
    with pytest.raises(ValueError, match="device bridge key"):
        check_bridge_key(key)
    with pytest.raises(ValueError, match="device bridge key"):
        BridgeConnection("127.0.0.1", 9, key=key)


# ----- pilescan-payload: --signing-key reaches the bridge; a key mismatch is one line and exit 4 -----------

def key_file(tmp_path, key: bytes = KEY):
    path = tmp_path / f"{key[0]}.key"
    path.write_text(key.hex() + "\n")
    path.chmod(0o600)
    return path


def parse(*argv: str):
    return config_from_args(build_parser().parse_args(["--out", "x.pslog", *argv]))


def test_that_the_signing_key_goes_to_the_bridge_only_with_bridge_urls(tmp_path):
    key = str(key_file(tmp_path))
    cfg = parse("--signing-key", key, "--hal", "sitl:127.0.0.1:5770")
    assert cfg.device_key == KEY and KEY.hex() not in repr(cfg)
    assert parse("--signing-key", key, "--i2c", "tcp:h:1", "--pwm", "pwm:sysfs:0:0").device_key == KEY
    assert parse("--signing-key", key).device_key is None  # real hardware: nothing to authenticate
    assert parse("--hal", "sitl:127.0.0.1:5770").device_key is None


def run_payload(capsys, tmp_path, rig, *extra: str) -> tuple[int, str]:
    host, port = rig.server.address
    out = tmp_path / "x.pslog"
    rc = main(["--out", str(out), "--mavlink", NOBODY, "--hal", f"sitl:{host}:{port}", "--rate", "100", *extra])
    err = capsys.readouterr().err
    # The bridge server runs in this process here (in the SITL's, in use): its own log lines are not the payload's.
    return rc, "".join(line for line in err.splitlines(keepends=True) if "warning: device bridge:" not in line)


@pytest.mark.parametrize(("server_key", "client_key", "words"), [
    (KEY, OTHER, "wrong key"),
    (KEY, None, "requires authentication"),
    (None, KEY, "does not authenticate"),
], ids=["wrong-key", "no-key-on-the-payload", "no-key-on-the-sitl"])
def test_that_a_key_mismatch_is_one_line_and_exit_4(capsys, tmp_path, server_key, client_key, words):
    rig = Rig(server_key)
    try:
        extra = ["--signing-key", str(key_file(tmp_path, client_key))] if client_key else []
        rc, err = run_payload(capsys, tmp_path, rig, "--duration", "0.2", *extra)
    finally:
        rig.close()
    assert rc == ExitCode.RUNTIME, err  # the device could not be had
    assert err.count("\n") == 1 and "Traceback" not in err and err.startswith("pilescan-payload: error: ")
    assert words in err and "cannot open I2C bus tcp:" in err
    assert not (tmp_path / "x.pslog").exists()  # refused before the log was created


def test_that_the_payload_flies_on_an_authenticated_bridge(capsys, tmp_path):
    rig = Rig(KEY, clock=WallSimClock())
    try:
        rc, err = run_payload(capsys, tmp_path, rig, "--duration", "0.3", "--signing-key", str(key_file(tmp_path)))
    finally:
        rig.close()
    assert rc == 0, err
    assert "device bridge authenticated" in err
    assert rig.server.counters["authenticated"] == 1 and rig.server.counters["auth_failed"] == 0
    log = read_samplelog(tmp_path / "x.pslog")
    assert log.intact and len(log.samples) > 5
    assert rig.servo.pulses > 0  # the servo was driven over the authenticated connection
    assert np.any(np.isclose(log.samples["range_m"], 7.25))  # and the LiDAR read (no autopilot: no poses)
