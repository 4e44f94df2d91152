"""The device bridge server: whatever a client sends, it answers or drops that client, and keeps serving."""

import socket
import struct
import threading

import pytest
from hypothesis import HealthCheck, given
from hypothesis import strategies as st

from firmware_py.hal import I2CError
from firmware_py.hal.bridge import (
    HEADER,
    MAX_PAYLOAD,
    OP_HELLO,
    OP_I2C_READ,
    OP_I2C_WRITE,
    OP_I2C_WRITE_READ,
    OP_PWM_DISABLE,
    OP_PWM_SET,
    STATUS_BAD_REQUEST,
    STATUS_ERROR,
    STATUS_NACK,
    STATUS_OK,
    VERSION,
)
from firmware_py.hal.clock import SimClock
from sitl.devices.bridge_server import DeviceBridgeServer, parse_bridge_url
from sitl.devices.i2c_sim import SimI2CBus
from tests.fuzz_budget import budget

REG = 0x40
BOOM = 0x41


class Register:
    """One byte of storage; checks the server holds the SITL's lock around every call."""

    def __init__(self, lock):
        self.lock, self.value = lock, 0

    def on_write(self, data):
        assert self.lock.locked()
        if data:
            self.value = data[-1]

    def on_read(self, n):
        assert self.lock.locked()
        return bytes([self.value]) * n


class Boom:
    def on_write(self, data):
        raise RuntimeError("model blew up\nsecond line")

    def on_read(self, n):
        return b""  # a wrong length: the bus raises RuntimeError


class RecordingPwm:
    def __init__(self):
        self.calls = []

    def set_pulse_us(self, pulse_us):
        self.calls.append(pulse_us)

    def disable(self):
        self.calls.append(None)

    def close(self):
        pass


def make_server():
    lock = threading.Lock()
    bus = SimI2CBus(SimClock())
    bus.attach(REG, Register(lock))
    bus.attach(BOOM, Boom())
    pwm = RecordingPwm()
    return DeviceBridgeServer(bus, {3: pwm}, lock=lock).start(), pwm


@pytest.fixture
def server():
    srv, pwm = make_server()
    srv.pwm = pwm
    yield srv
    srv.close()


def connect(srv):
    sock = socket.create_connection(srv.address, timeout=2.0)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


def recv_exactly(sock, n):
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        if not chunk:
            raise EOFError(f"connection closed after {len(buf)} of {n} bytes")
        buf += chunk
    return buf


def ask(sock, op, payload=b""):
    sock.sendall(HEADER.pack(len(payload), op) + payload)
    return answer(sock)


def answer(sock):
    length, status = HEADER.unpack(recv_exactly(sock, HEADER.size))
    return status, recv_exactly(sock, length)


def closed_by_server(sock):
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True


def hello(sock):
    return ask(sock, OP_HELLO, struct.pack("<H", VERSION))


def test_that_hello_lists_devices_and_channels_and_transfers_work(server):
    with connect(server) as s:
        status, body = hello(s)
        assert status == STATUS_OK and body == struct.pack("<HB", VERSION, 2) + bytes([REG, BOOM, 1, 3])
        assert ask(s, OP_I2C_WRITE, bytes([REG, 0x00, 0x5A])) == (STATUS_OK, b"")
        assert ask(s, OP_I2C_READ, struct.pack("<BH", REG, 3)) == (STATUS_OK, b"\x5a" * 3)
        assert ask(s, OP_I2C_WRITE_READ, struct.pack("<BH", REG, 1) + b"\x07") == (STATUS_OK, b"\x07")
        assert ask(s, OP_PWM_SET, struct.pack("<Bd", 3, 1500.5)) == (STATUS_OK, b"")
        assert ask(s, OP_PWM_DISABLE, b"\x03") == (STATUS_OK, b"")
    assert server.pwm.calls == [1500.5, None]
    assert server.counters["requests"] == 6 and server.counters["clients"] == 1


def test_that_device_failures_are_nack_or_a_one_line_error(server, caplog):
    with connect(server) as s:
        status, body = ask(s, OP_I2C_READ, struct.pack("<BH", 0x10, 2))
        assert status == STATUS_NACK and b"0x10: NACK (no device)" in body
        status, body = ask(s, OP_I2C_WRITE, bytes([BOOM, 1]))
        assert (status, body) == (STATUS_ERROR, b"RuntimeError: model blew up second line")
        status, body = ask(s, OP_I2C_READ, struct.pack("<BH", BOOM, 2))
        assert status == STATUS_ERROR and b"returned 0 bytes" in body
        assert hello(s)[0] == STATUS_OK  # still connected
    assert server.counters["nacks"] == 1 and server.counters["errors"] == 2
    assert "op 0x10 raised" in caplog.text


@pytest.mark.parametrize(("op", "payload", "why"), [
    (0x7E, b"", b"unknown op 0x7e"),
    (OP_HELLO, struct.pack("<H", VERSION + 1), b"not supported"),
    (OP_HELLO, b"\x01", b"HELLO needs 2"),
    (OP_I2C_WRITE, b"", b"at least 1"),
    (OP_I2C_WRITE, b"\x80\x00", b"not 7-bit"),
    (OP_I2C_READ, struct.pack("<BH", REG, 0), b"read length 0"),
    (OP_I2C_READ, struct.pack("<BH", REG, MAX_PAYLOAD + 1), b"read length"),
    (OP_I2C_READ, struct.pack("<BHB", REG, 1, 0), b"needs 3"),
    (OP_I2C_WRITE_READ, b"\x40\x01", b"at least 3"),
    (OP_PWM_SET, struct.pack("<Bd", 3, float("nan")), b"500-2500"),
    (OP_PWM_SET, struct.pack("<Bd", 3, 2600.0), b"500-2500"),
    (OP_PWM_SET, struct.pack("<Bd", 4, 1500.0), b"no PWM channel 4 (have: 3)"),
    (OP_PWM_SET, struct.pack("<Bf", 3, 1500.0), b"needs 9"),
    (OP_PWM_DISABLE, b"", b"needs 1"),
])
def test_that_malformed_requests_are_bad_requests_and_the_client_stays(server, op, payload, why):
    with connect(server) as s:
        status, body = ask(s, op, payload)
        assert status == STATUS_BAD_REQUEST and why in body
        assert hello(s)[0] == STATUS_OK
    assert server.counters["bad_requests"] == 1 and server.pwm.calls == []


def test_that_a_huge_length_is_refused_and_that_client_dropped(server):
    with connect(server) as bad, connect(server) as good:
        bad.sendall(b"\xff\xff\xff garbage")
        status, body = answer(bad)
        assert status == STATUS_BAD_REQUEST and b"exceeds" in body
        assert closed_by_server(bad)
        assert hello(good)[0] == STATUS_OK
    assert server.counters["dropped"] == 1 and server.counters["clients"] == 2


def test_that_a_truncated_frame_does_not_block_other_clients(server):
    with connect(server) as slow, connect(server) as good:
        slow.sendall(HEADER.pack(3, OP_I2C_READ) + bytes([REG]))  # two payload bytes short
        assert hello(good)[0] == STATUS_OK
        slow.sendall(struct.pack("<H", 1))  # the rest arrives later: the frame completes
        assert answer(slow) == (STATUS_OK, b"\x00")
        slow.sendall(HEADER.pack(10, OP_I2C_WRITE) + b"\x40")
    with connect(server) as again:  # the half frame died with its connection
        assert hello(again)[0] == STATUS_OK
    assert server.counters["requests"] == 3


def test_that_a_frame_sent_byte_by_byte_and_pipelined_requests_are_answered_in_order(server):
    with connect(server) as s:
        frames = (HEADER.pack(2, OP_I2C_WRITE) + bytes([REG, 9]) + HEADER.pack(3, OP_I2C_READ)
                  + struct.pack("<BH", REG, 1) + HEADER.pack(0, 0x55))
        for b in frames[:4]:
            s.sendall(bytes([b]))
        s.sendall(frames[4:])
        assert answer(s) == (STATUS_OK, b"")
        assert answer(s) == (STATUS_OK, b"\x09")
        assert answer(s)[0] == STATUS_BAD_REQUEST


def test_that_the_server_closes_idempotently_and_refuses_afterwards():
    srv, _ = make_server()
    address = srv.address
    with connect(srv) as s:
        assert hello(s)[0] == STATUS_OK
        srv.close()
        assert closed_by_server(s)
    srv.close()
    assert not srv._thread.is_alive()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(address, timeout=2.0).close()
    with pytest.raises(RuntimeError):
        srv.start()


def test_that_it_is_a_context_manager_and_unstarted_close_works():
    bus = SimI2CBus(SimClock())
    with DeviceBridgeServer(bus) as srv, connect(srv) as s:
        assert hello(s) == (STATUS_OK, struct.pack("<HB", VERSION, 0) + b"\x00")
    assert not srv._thread.is_alive()
    DeviceBridgeServer(bus).close()


def test_that_pwm_channels_are_checked():
    with pytest.raises(ValueError, match="0-255"):
        DeviceBridgeServer(SimI2CBus(SimClock()), {256: RecordingPwm()})


@pytest.mark.parametrize(("url", "expected"), [("tcp:127.0.0.1:5761", ("127.0.0.1", 5761)),
                                               ("tcp:0.0.0.0:0", ("0.0.0.0", 0)), ("tcp:[::1]:9", ("::1", 9))])
def test_that_bridge_urls_parse(url, expected):
    assert parse_bridge_url(url) == expected


@pytest.mark.parametrize("url", ["", "tcp:", "tcp:h", "tcp:h:65536", "tcp:h:-1", "udp:h:1", "tcp:h:1:2", 5761])
def test_that_malformed_bridge_urls_are_one_line_value_errors(url):
    with pytest.raises(ValueError, match="expected tcp:HOST:PORT") as excinfo:
        parse_bridge_url(url)
    assert repr(url) in str(excinfo.value) and "\n" not in str(excinfo.value)


def test_that_an_i2c_error_from_a_pwm_output_is_a_nack():
    class Flaky(RecordingPwm):
        def set_pulse_us(self, pulse_us):
            raise I2CError(121, "PCA9685 at 0x40: NACK")

    with DeviceBridgeServer(SimI2CBus(SimClock()), {0: Flaky()}) as srv, connect(srv) as s:
        assert ask(s, OP_PWM_SET, struct.pack("<Bd", 0, 1500.0)) == (STATUS_NACK, b"PCA9685 at 0x40: NACK")


# --------------------------------------------------------------------------- hypothesis

@pytest.fixture(scope="module")
def shared_server():
    srv, _ = make_server()
    yield srv
    srv.close()


_frame = st.builds(lambda op, p: HEADER.pack(len(p), op) + p,
                   st.sampled_from([OP_HELLO, OP_I2C_WRITE, OP_I2C_READ, OP_I2C_WRITE_READ, OP_PWM_SET,
                                    OP_PWM_DISABLE, 0x00, 0xFF]), st.binary(max_size=12))
"""A well-framed request with a random payload: reaches the op handlers rather than the framing."""


@budget(30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(st.binary(max_size=64), _frame), min_size=1, max_size=4))
def test_that_random_bytes_never_kill_the_server(shared_server, chunks):
    with connect(shared_server) as s:
        try:  # the server may drop us (a huge length) before everything is sent
            for chunk in chunks:
                s.sendall(chunk)
            s.shutdown(socket.SHUT_WR)  # the server sees EOF, answers what it could parse, and drops us
            while s.recv(4096):
                pass
        except OSError:  # broken pipe, reset
            pass
    assert shared_server._thread.is_alive()
    with connect(shared_server) as s:
        assert hello(s)[0] == STATUS_OK


@budget(30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(_frame, min_size=1, max_size=8))
def test_that_pipelined_well_framed_requests_get_one_answer_each_in_order(shared_server, frames):
    with connect(shared_server) as s:
        s.sendall(b"".join(frames))
        answers = [answer(s) for _ in frames]
        assert hello(s)[0] == STATUS_OK  # the connection is still in step after them
    for (status, body), frame in zip(answers, frames, strict=True):
        assert status in (STATUS_OK, STATUS_NACK, STATUS_BAD_REQUEST, STATUS_ERROR)
        assert status == STATUS_OK or (body and b"\n" not in body)
        if status == STATUS_OK and frame[2] in (OP_I2C_READ, OP_I2C_WRITE_READ):
            assert len(body) == struct.unpack_from("<H", frame, 4)[0]


@pytest.fixture(scope="module")
def quiet_server():
    """Well-behaved devices only (no Boom), never started: requests go straight to handle_request."""
    lock = threading.Lock()
    bus = SimI2CBus(SimClock())
    bus.attach(REG, Register(lock))
    srv = DeviceBridgeServer(bus, {3: RecordingPwm()}, lock=lock)
    yield srv
    srv.close()


_ops = st.one_of(st.sampled_from([OP_HELLO, OP_I2C_WRITE, OP_I2C_READ, OP_I2C_WRITE_READ, OP_PWM_SET, OP_PWM_DISABLE]),
                 st.integers(0, 255))
_payloads = st.one_of(
    st.binary(max_size=MAX_PAYLOAD + 8),
    st.builds(lambda a, n, rest: struct.pack("<BH", a, n) + rest, st.sampled_from([REG, 0x62, 0x7F, 0x80, 0xFF]),
              st.sampled_from([0, 1, 2, MAX_PAYLOAD, MAX_PAYLOAD + 1, 0xFFFF]), st.binary(max_size=8)),
    st.builds(lambda ch, us: struct.pack("<Bd", ch, us), st.sampled_from([0, 3, 255]), st.floats()),
    st.builds(lambda v: struct.pack("<H", v), st.sampled_from([VERSION, 0, 2, 0xFFFF])),
)


@budget(200, deadline=None)
@given(op=_ops, payload=_payloads)
def test_that_any_request_to_good_devices_gets_a_status_never_an_internal_error(quiet_server, op, payload):
    """ERROR is for a device model that raised; with well-behaved devices every answer is OK, NACK (nobody at
    that address) or BAD_REQUEST, and the counters say which."""
    before = dict(quiet_server.counters)
    status, body = quiet_server.handle_request(op, payload)
    after = quiet_server.counters
    assert status in (STATUS_OK, STATUS_NACK, STATUS_BAD_REQUEST), body
    assert len(body) <= MAX_PAYLOAD and (status == STATUS_OK or (body and b"\n" not in body))
    assert after["requests"] == before["requests"] + 1 and after["errors"] == before["errors"]
    assert after["nacks"] - before["nacks"] == (status == STATUS_NACK)
    assert after["bad_requests"] - before["bad_requests"] == (status == STATUS_BAD_REQUEST)
