"""The device bridge client: the payload's unchanged drivers on the SITL's emulated devices over TCP."""

import errno
import socket
import threading
from importlib.util import find_spec

import pytest

from firmware_py.drivers.lidarlite import LidarLite, ReadStatus
from firmware_py.hal import I2CError
from firmware_py.hal import bridge as br
from firmware_py.hal.backends import open_i2c
from firmware_py.hal.bridge import BridgeConnection, BridgeI2CBus, parse_pwm_url, parse_tcp_url
from firmware_py.hal.clock import SimClock
from firmware_py.hal.pwm import open_pwm

SIM = find_spec("sitl") is not None  # False on the payload-only install (Raspberry Pi): those tests skip
if SIM:
    from sitl.devices.bridge_server import DeviceBridgeServer
    from sitl.devices.i2c_sim import SimI2CBus
    from sitl.devices.lidarlite_emu import EmulatedLidarLite
    from sitl.devices.servo_emu import EmulatedServo

LIDAR = 0x62
ECHO = 0x20


class RecordingPwm:
    def __init__(self):
        self.calls = []

    def set_pulse_us(self, pulse_us):
        self.calls.append(("set", pulse_us))

    def disable(self):
        self.calls.append(("disable",))

    def close(self):
        self.calls.append(("close",))


class Echo:
    """Answers a combined transfer with the bytes written, so concurrent callers can check pairing."""

    def on_write(self, data):
        pass

    def on_read(self, n):
        return bytes(n)

    def on_write_read(self, data, n):
        return data[:n]


class Rig:
    def __init__(self, port=0):
        self.clock = SimClock()
        self.bus = SimI2CBus(self.clock)
        self.part = EmulatedLidarLite(self.clock, lambda t_ns: 7.25)
        self.bus.attach(LIDAR, self.part)
        self.bus.attach(ECHO, Echo())
        self.servo = EmulatedServo(self.clock)
        self.recorder = RecordingPwm()
        self.lock = threading.Lock()
        self.server = self.serve(port)

    def serve(self, port):
        self.server = DeviceBridgeServer(self.bus, {0: self.servo, 1: self.recorder}, port=port,
                                         lock=self.lock).start()
        return self.server

    @property
    def host_port(self):
        return self.server.address

    def url(self, channel=None):
        host, port = self.host_port
        return f"tcp:{host}:{port}" if channel is None else f"pwm:tcp:{host}:{port}:{channel}"


@pytest.fixture
def rig():
    pytest.importorskip("sitl", reason="the SITL's bridge server (sitl/): not in the payload-only install")
    rig = Rig()
    yield rig
    for conn in list(br._SHARED.values()):
        conn.close()
    rig.server.close()


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_that_the_lidar_driver_reads_the_emulated_distance_over_the_bridge(rig):
    bus = open_i2c(rig.url())
    assert isinstance(bus, BridgeI2CBus)
    assert bus.conn.i2c_addresses == (ECHO, LIDAR) and bus.conn.pwm_channels == (0, 1)
    lidar = LidarLite(bus, rig.clock)
    readings = [lidar.read() for _ in range(3)]
    assert [r.status for r in readings] == [ReadStatus.OK] * 3
    assert [r.range_m for r in readings] == [7.25] * 3
    assert rig.part.counters["acquisitions"] == 3 and lidar.counters().bus_errors == 0
    bus.close()


def test_that_a_missing_device_is_a_nack_i2c_error_and_the_connection_stays(rig):
    bus = open_i2c(rig.url())
    with pytest.raises(I2CError, match=r"0x10: NACK \(no device\)") as excinfo:
        bus.write(0x10, b"\x00")
    assert excinfo.value.errno == errno.EREMOTEIO
    with pytest.raises(I2CError, match="NACK"):
        bus.read(0x11, 2)
    assert rig.server.counters["nacks"] == 2
    bus.write(LIDAR, b"\x02")
    assert bus.read(LIDAR, 1) == b"\x80"  # SIG_COUNT_VAL's power-on value
    assert bus.conn.counters["connects"] == 1
    bus.close()


def test_that_a_combined_transfer_reads_the_idle_level_as_on_the_real_part(rig):
    bus = open_i2c(rig.url())
    assert bus.write_read(LIDAR, b"\x8f", 2) == b"\xff\xff"
    assert rig.part.counters["combined_transfers"] == 1
    bus.close()


def test_that_pwm_reaches_the_emulated_servo_and_other_channels(rig):
    servo = open_pwm(rig.url(0))
    servo.set_pulse_us(1800)
    assert rig.servo.pulses == 1 and rig.servo.enabled
    assert rig.servo._target == pytest.approx(rig.servo.cal.angle_rad(1800))
    other = open_pwm(rig.url(1))
    assert other.conn is servo.conn
    other.set_pulse_us(1234.5)
    other.disable()
    other.close()  # disables again, as the other backends' close() does
    assert rig.recorder.calls == [("set", 1234.5), ("disable",), ("disable",)]
    servo.disable()
    assert not rig.servo.enabled
    servo.close()


@pytest.mark.parametrize("pulse", [499.9, 2500.1, float("nan"), float("inf"), -1500])
def test_that_a_bad_pulse_is_refused_without_a_request(rig, pulse):
    pwm = open_pwm(rig.url(1))
    before = rig.server.counters["requests"]
    with pytest.raises(ValueError, match="500-2500"):
        pwm.set_pulse_us(pulse)
    assert rig.server.counters["requests"] == before and rig.recorder.calls == []
    pwm.close()


def test_that_a_channel_the_server_lacks_is_refused_at_open(rig):
    url = rig.url(7)
    with pytest.raises(ValueError, match=r"no PWM channel 7 \(it has: 0, 1\)") as excinfo:
        open_pwm(url)
    assert repr(url) in str(excinfo.value)
    assert br._SHARED == {}  # its connection was not left open


@pytest.mark.parametrize("url", ["tcp:", "tcp:host", "tcp:host:", "tcp:host:0", "tcp:host:65536", "tcp:host:http",
                                 "tcp:a b:1", "tcp:::1:80", "tcp:host:1:2", "tcp:[::1:80"])
def test_that_malformed_i2c_urls_are_value_errors_naming_url_and_form(url):
    with pytest.raises(ValueError) as excinfo:
        open_i2c(url)
    msg = str(excinfo.value)
    assert repr(url) in msg and "tcp:HOST:PORT" in msg and "\n" not in msg


@pytest.mark.parametrize("url", ["pwm:tcp", "pwm:tcp:host:1", "pwm:tcp:host:1:256", "pwm:tcp:host:0:0",
                                 "pwm:tcp:host:x:0", "pwm:tcp:host:1:-1", "pwm:tcp::1:0"])
def test_that_malformed_pwm_urls_are_value_errors_naming_url_and_form(url):
    with pytest.raises(ValueError) as excinfo:
        open_pwm(url)
    msg = str(excinfo.value)
    assert repr(url) in msg and "pwm:tcp:HOST:PORT:CHANNEL" in msg and "\n" not in msg


def test_that_good_urls_parse():
    assert parse_tcp_url(" tcp:127.0.0.1:5761 ") == ("127.0.0.1", 5761)
    assert parse_tcp_url("tcp:sitl-box.local:1") == ("sitl-box.local", 1)
    assert parse_tcp_url("tcp:[::1]:65535") == ("::1", 65535)
    assert parse_tcp_url("tcp:0.0.0.0:0", allow_port_zero=True) == ("0.0.0.0", 0)
    assert parse_pwm_url("pwm:tcp:localhost:5761:0") == ("localhost", 5761, 0)
    assert parse_pwm_url("pwm:tcp:[::1]:5761:255") == ("::1", 5761, 255)


def test_that_a_refused_connection_names_the_endpoint_and_the_sitl_command():
    port = free_port()
    for opener, url in ((open_i2c, f"tcp:127.0.0.1:{port}"), (open_pwm, f"pwm:tcp:127.0.0.1:{port}:0")):
        with pytest.raises(OSError) as excinfo:
            opener(url)
        assert isinstance(excinfo.value, I2CError)
        assert f"127.0.0.1:{port}" in str(excinfo.value) and "pilescan-sitl serve --devices" in str(excinfo.value)
    assert br._SHARED == {}


def test_that_a_lost_server_is_an_i2c_error_and_a_restarted_one_is_reconnected(rig):
    bus = open_i2c(rig.url())
    lidar = LidarLite(bus, rig.clock)
    assert lidar.read().status == ReadStatus.OK
    host, port = rig.host_port
    rig.server.close()
    with pytest.raises(I2CError, match=f"{host}:{port}"):
        bus.read(LIDAR, 1)
    with pytest.raises(I2CError, match="pilescan-sitl serve"):  # reconnecting fails while it is down
        bus.read(LIDAR, 1)
    assert lidar.read().status == ReadStatus.BUS_ERROR  # the driver counts it and carries on
    try:
        rig.serve(port)
    except OSError as exc:
        pytest.skip(f"port {port} was taken before the server could restart on it: {exc}")
    assert lidar.read().status == ReadStatus.OK
    assert bus.conn.counters["connects"] == 2
    bus.close()


def test_that_a_request_without_an_answer_times_out_and_the_next_one_gets_its_own_answer(rig):
    release = threading.Event()

    class Stuck:
        def on_write(self, data):
            release.wait(5)

        def on_read(self, n):
            return b"\x42" * n

    rig.bus.attach(0x30, Stuck())
    conn = BridgeConnection(*rig.host_port, timeout_s=0.2)
    bus = BridgeI2CBus(conn)
    with pytest.raises(I2CError, match=r"no answer within 0\.2 s") as excinfo:
        bus.write(0x30, b"\x01")
    assert excinfo.value.errno == errno.ETIMEDOUT
    release.set()
    assert bus.read(0x30, 2) == b"\x42\x42"  # a new connection: the late OK of the write is never read
    assert conn.counters["connects"] == 2
    bus.close()
    assert conn.closed


def test_that_bus_and_pwm_share_one_connection_and_closing_one_leaves_the_other(rig):
    bus = open_i2c(rig.url())
    pwm = open_pwm(rig.url(0))
    assert bus.conn is pwm.conn and rig.server.client_count == 1
    pwm.close()
    bus.write(LIDAR, b"\x02")
    assert bus.read(LIDAR, 1) == b"\x80"
    pwm2 = open_pwm(rig.url(1))
    bus.close()
    with pytest.raises(I2CError, match="closed") as excinfo:
        bus.read(LIDAR, 1)
    assert excinfo.value.errno == errno.EBADF
    pwm2.set_pulse_us(1500)
    assert rig.recorder.calls == [("set", 1500.0)]
    conn = pwm2.conn
    pwm2.close()
    assert conn.closed and br._SHARED == {}
    again = open_i2c(rig.url())  # a fresh connection after the last user closed
    assert again.conn is not conn and again.read(LIDAR, 1)
    again.close()


def test_that_threads_sharing_a_connection_each_get_their_own_answers(rig):
    bus = open_i2c(rig.url())
    failures = []

    def worker(k):
        for i in range(50):
            data = bytes((k, i, k ^ i))
            if bus.write_read(ECHO, data, 3) != data:
                failures.append((k, i))

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert failures == [] and rig.server.counters["requests"] == 1 + 4 * 50
    bus.close()


def test_that_bad_arguments_are_value_errors_before_any_request(rig):
    bus = open_i2c(rig.url())
    before = rig.server.counters["requests"]
    for call in (lambda: bus.write(0x80, b""), lambda: bus.read(LIDAR, 0), lambda: bus.read(LIDAR, 1025),
                 lambda: bus.write(LIDAR, bytes(2000)), lambda: bus.write_read(-1, b"", 1)):
        with pytest.raises(ValueError):
            call()
    assert rig.server.counters["requests"] == before
    bus.close()


def test_that_a_server_of_another_protocol_is_refused(monkeypatch, rig):
    monkeypatch.setattr(br, "VERSION", 2)
    with pytest.raises(I2CError, match="version 2 not supported") as excinfo:
        BridgeConnection(*rig.host_port)
    assert excinfo.value.errno == errno.EPROTO
