"""Device bridge authentication, server side, on the wire: a keyed server serves only clients that pass the
challenge-response handshake; everyone else gets one AUTH answer, is disconnected and counted."""

from __future__ import annotations

import secrets
import socket
import struct
import threading

import pytest

from firmware_py.hal.bridge import (
    AUTH_VERSION,
    NONCE_SIZE,
    OP_AUTH_CHALLENGE,
    OP_AUTH_PROVE,
    OP_HELLO,
    OP_I2C_READ,
    STATUS_AUTH,
    STATUS_BAD_REQUEST,
    STATUS_OK,
    auth_proof,
)
from firmware_py.hal.clock import SimClock
from sitl.devices import bridge_server
from sitl.devices.bridge_server import DeviceBridgeServer
from sitl.devices.i2c_sim import SimI2CBus
from tests.sitl.devices.test_bridge_server import REG, Register, answer, ask, closed_by_server, connect, hello

KEY = bytes(range(1, 33))
OTHER = bytes(range(2, 34))


def make_server(key: bytes | None = KEY) -> DeviceBridgeServer:
    lock = threading.Lock()
    bus = SimI2CBus(SimClock())
    bus.attach(REG, Register(lock))
    return DeviceBridgeServer(bus, {}, lock=lock, key=key).start()


@pytest.fixture
def server():
    srv = make_server()
    yield srv
    srv.close()


def challenge(sock: socket.socket) -> bytes:
    status, nonce = ask(sock, OP_AUTH_CHALLENGE, struct.pack("<H", AUTH_VERSION))
    assert status == STATUS_OK and len(nonce) == NONCE_SIZE
    return nonce


def prove(sock: socket.socket, key: bytes, server_nonce: bytes) -> tuple[int, bytes, bytes]:
    client_nonce = secrets.token_bytes(NONCE_SIZE)
    status, body = ask(sock, OP_AUTH_PROVE, client_nonce + auth_proof(key, "client", server_nonce, client_nonce))
    return status, body, client_nonce


def test_that_the_handshake_with_the_right_key_proves_both_sides_then_serves(server):
    with connect(server) as s:
        ns = challenge(s)
        status, body, nc = prove(s, KEY, ns)
        assert status == STATUS_OK and body == auth_proof(KEY, "server", ns, nc)  # the server proved itself
        assert hello(s)[0] == STATUS_OK
        assert ask(s, OP_I2C_READ, struct.pack("<BH", REG, 1)) == (STATUS_OK, b"\x00")
        assert ask(s, OP_AUTH_CHALLENGE, struct.pack("<H", AUTH_VERSION))[0] == STATUS_BAD_REQUEST  # once only
        assert hello(s)[0] == STATUS_OK
    assert server.counters["authenticated"] == 1 and server.counters["dropped"] == 0


def test_that_requests_before_authenticating_are_refused_and_the_client_dropped(server):
    with connect(server) as s:
        status, body = hello(s)
        assert status == STATUS_AUTH and b"requires authentication" in body and b"\n" not in body
        assert closed_by_server(s)
    with connect(server) as s:  # a device request, pipelined behind nothing: the same
        status, _ = ask(s, OP_I2C_READ, struct.pack("<BH", REG, 1))
        assert status == STATUS_AUTH and closed_by_server(s)
    assert server.counters["unauthenticated"] == 2 and server.counters["dropped"] == 2
    assert server.counters["requests"] == 0  # no device was reached


def test_that_a_wrong_key_is_refused_counted_and_the_server_keeps_serving(server):
    with connect(server) as s:
        status, body, _ = prove(s, OTHER, challenge(s))
        assert (status, body) == (STATUS_AUTH, b"authentication failed: wrong key")
        assert closed_by_server(s)
    with connect(server) as good:
        assert prove(good, KEY, challenge(good))[0] == STATUS_OK
    assert server.counters["auth_failed"] == 1 and server.counters["authenticated"] == 1


def test_that_a_proof_without_a_challenge_or_replayed_from_an_old_one_is_refused(server):
    with connect(server) as s:
        status, _ = ask(s, OP_AUTH_PROVE, bytes(NONCE_SIZE + 32))
        assert status == STATUS_AUTH and closed_by_server(s)
    with connect(server) as s:  # a recorded handshake...
        ns = challenge(s)
        nc = secrets.token_bytes(NONCE_SIZE)
        recorded = nc + auth_proof(KEY, "client", ns, nc)
        assert ask(s, OP_AUTH_PROVE, recorded)[0] == STATUS_OK
    with connect(server) as s:  # ...played back on a new connection meets a new challenge
        challenge(s)
        assert ask(s, OP_AUTH_PROVE, recorded) == (STATUS_AUTH, b"authentication failed: wrong key")
    assert server.counters["auth_failed"] == 2 and server.counters["authenticated"] == 1


def test_that_the_server_proof_cannot_be_reflected_as_a_client_proof(server):
    with connect(server) as s:
        ns = challenge(s)
        nc = secrets.token_bytes(NONCE_SIZE)
        reflected = auth_proof(KEY, "server", ns, nc)  # what an eavesdropper of another handshake would hold
        assert ask(s, OP_AUTH_PROVE, nc + reflected)[0] == STATUS_AUTH


def test_that_a_bad_auth_version_is_a_bad_request_and_the_client_may_retry(server):
    with connect(server) as s:
        status, body = ask(s, OP_AUTH_CHALLENGE, struct.pack("<H", AUTH_VERSION + 1))
        assert status == STATUS_BAD_REQUEST and b"auth version" in body
        assert prove(s, KEY, challenge(s))[0] == STATUS_OK


def test_that_a_client_that_never_authenticates_is_dropped(monkeypatch):
    monkeypatch.setattr(bridge_server, "AUTH_TIMEOUT_S", 0.1)
    srv = make_server()
    try:
        with connect(srv) as idle:
            idle.settimeout(5.0)
            assert closed_by_server(idle)
        assert srv.counters["unauthenticated"] == 1 and srv.counters["dropped"] == 1
    finally:
        srv.close()


def test_that_a_server_without_a_key_says_so_and_serves_as_before():
    srv = make_server(key=None)
    try:
        assert not srv.authenticates
        with connect(srv) as s:
            status, body = ask(s, OP_AUTH_CHALLENGE, struct.pack("<H", AUTH_VERSION))
            assert status == STATUS_BAD_REQUEST and b"does not authenticate" in body
            assert hello(s)[0] == STATUS_OK  # still connected: a keyless client never sends AUTH anyway
        assert srv.counters["authenticated"] == srv.counters["unauthenticated"] == srv.counters["auth_failed"] == 0
    finally:
        srv.close()


def test_that_pipelined_requests_behind_a_failed_handshake_are_never_served(server):
    with connect(server) as s:
        frames = b"".join(struct.pack("<HB", len(p), op) + p for op, p in (
            (OP_AUTH_PROVE, bytes(NONCE_SIZE + 32)), (OP_HELLO, struct.pack("<H", 1)),
            (OP_I2C_READ, struct.pack("<BH", REG, 1))))
        s.sendall(frames)
        assert answer(s)[0] == STATUS_AUTH
        assert closed_by_server(s)
    assert server.counters["requests"] == 0


@pytest.mark.parametrize("key", [b"short", bytes(32), bytes(33)], ids=["short", "zeros", "long"])
def test_that_a_bad_server_key_is_a_value_error(key):
    with pytest.raises(ValueError, match="device bridge key"):
        DeviceBridgeServer(SimI2CBus(SimClock()), key=key)
