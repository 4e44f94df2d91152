"""The networked-SITL device bridge, client side: the unchanged payload firmware, running as its own
process, reaches the SITL's emulated I2C devices and servo PWM over one TCP connection.

URL forms (routed by `open_i2c` and `open_pwm`):

    tcp:HOST:PORT                 an I2CBus on the bridge (e.g. tcp:127.0.0.1:5761)
    pwm:tcp:HOST:PORT:CHANNEL     PWM output CHANNEL (0-255) on the bridge

HOST may be a name, an IPv4 address or a bracketed IPv6 address ([::1]). Handles on the same
HOST:PORT share one connection per process (the I2C bus and the servo are served in order); the
socket closes when the last handle does.

Protocol (version 1), little-endian, strict request/response on one TCP stream:

    frame    = u16 length, u8 code, `length` payload bytes   (struct "<HB"; length <= MAX_PAYLOAD)
    request  code = op, response code = status

    op                   request payload               OK response payload
    0x01 HELLO           u16 version                   u16 version, u8 n, n x u8 I2C address,
                                                       u8 m, m x u8 PWM channel
    0x10 I2C_WRITE       u8 addr, data...              (empty)
    0x11 I2C_READ        u8 addr, u16 n                n bytes
    0x12 I2C_WRITE_READ  u8 addr, u16 n, data...       n bytes (combined transfer, repeated START)
    0x20 PWM_SET         u8 channel, f64 pulse_us      (empty)
    0x21 PWM_DISABLE     u8 channel                    (empty)

    status 0x00 OK; 0x01 NACK (the device did not answer: I2CError EREMOTEIO, as smbus2 reports it);
    0x02 BAD_REQUEST (malformed frame, unknown op or channel, wrong version); 0x03 ERROR (the device
    model raised). Non-OK payloads are a one-line UTF-8 message.

The client says HELLO on every (re)connect and refuses a server of another version. A server may
close a connection whose framing it cannot follow (e.g. a length above MAX_PAYLOAD).

Authentication (optional; both ends given the same 32-byte key, the MAVLink signing key file:
`firmware_py.core.keys.load_key`). A keyed client runs a challenge-response handshake right after
connecting, before HELLO, in the same request/response framing:

    op                   request payload               OK response payload
    0x02 AUTH_CHALLENGE  u16 auth version (1)          16-byte server nonce Ns (fresh, random)
    0x03 AUTH_PROVE      16-byte client nonce Nc,      32-byte server proof
                         32-byte client proof

    client proof = HMAC-SHA256(key, Ns || Nc || b"pilescan device bridge v1: client")
    server proof = HMAC-SHA256(key, Ns || Nc || b"pilescan device bridge v1: server")

The server checks the client's proof (constant time) and answers with its own, which the client
checks: neither side talks to an impostor, and since each side's nonce is fresh, a recorded
handshake cannot be replayed to either. The two labels keep a proof from being reflected back.
A keyed server answers any other request before a good AUTH_PROVE, and a bad proof, with status
0x04 AUTH (a one-line message) and closes the connection; it also drops a client that has not
authenticated within AUTH_TIMEOUT_S. A server without a key answers the AUTH ops with
BAD_REQUEST, which a keyed client reports as "this bridge does not authenticate" (it never falls
back to talking unauthenticated). The handshake authenticates the connection, not each frame: the
frames after it carry no MAC (the bridge is a SITL device link on a local network; someone who can
inject into an established TCP stream there is out of scope).

Failure policy: each request has a deadline (`timeout_s`). A refused connection, a timeout, a lost
connection or an unparseable answer raises I2CError (OSError) at once and drops the socket, so a late
answer can never be taken for the next request's; the next call reconnects (the SITL may restart).
The LIDAR driver counts such an error as a bus error and carries on, as with a flaky wire.

This module never imports `sitl`: the server (sitl.devices.bridge_server) imports these constants.
"""

from __future__ import annotations

import errno
import hashlib
import hmac
import re
import secrets
import socket
import struct
import threading
import time
from typing import Final

from firmware_py.core.keys import KEY_SIZE
from firmware_py.hal import I2CError, check_i2c_addr, check_pulse_us, check_read_len

VERSION: Final = 1
HEADER: Final = struct.Struct("<HB")
MAX_PAYLOAD: Final = 1024
"""Largest frame payload either side sends; also the longest I2C read (a LIDAR reads 2 bytes)."""

OP_HELLO: Final = 0x01
OP_AUTH_CHALLENGE: Final = 0x02
OP_AUTH_PROVE: Final = 0x03
OP_I2C_WRITE: Final = 0x10
OP_I2C_READ: Final = 0x11
OP_I2C_WRITE_READ: Final = 0x12
OP_PWM_SET: Final = 0x20
OP_PWM_DISABLE: Final = 0x21

STATUS_OK: Final = 0x00
STATUS_NACK: Final = 0x01
STATUS_BAD_REQUEST: Final = 0x02
STATUS_ERROR: Final = 0x03
STATUS_AUTH: Final = 0x04
"""Authentication required or failed; the server closes the connection after sending it."""

AUTH_VERSION: Final = 1
NONCE_SIZE: Final = 16
PROOF_SIZE: Final = 32
AUTH_TIMEOUT_S: Final = 5.0
"""A keyed server drops a client that has not authenticated this long after connecting."""
_PROOF_LABEL: Final = b"pilescan device bridge v1: "

HINT: Final = "is `pilescan-sitl serve --devices ...` running?"
I2C_FORM: Final = "tcp:HOST:PORT"
PWM_FORM: Final = "pwm:tcp:HOST:PORT:CHANNEL"
_HOST = r"(\[[\w:.%]+\]|[\w.-]+)"  # a name or IPv4, or a bracketed IPv6 (ASCII only)


def _endpoint(host: str, port: int) -> str:
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _parse(url: object, pattern: str, form: str, port_min: int) -> re.Match[str]:
    m = re.fullmatch(pattern, url.strip(), re.ASCII) if isinstance(url, str) else None
    if m is None or not port_min <= int(m.group(2)) <= 65535:
        raise ValueError(f"malformed device bridge URL {url!r}: expected {form} (port {port_min}-65535)")
    return m


def parse_tcp_url(url: str, *, allow_port_zero: bool = False) -> tuple[str, int]:
    """(host, port) of `tcp:HOST:PORT`; port 0 (any free port) only where a server binds.

    Raises:
        ValueError: a one-line message naming the URL and the expected form.
    """
    m = _parse(url, rf"tcp:{_HOST}:(\d{{1,5}})", I2C_FORM, 0 if allow_port_zero else 1)
    return m.group(1).strip("[]"), int(m.group(2))


def parse_pwm_url(url: str) -> tuple[str, int, int]:
    """(host, port, channel) of `pwm:tcp:HOST:PORT:CHANNEL` (ValueError naming the URL otherwise)."""
    m = _parse(url, rf"pwm:tcp:{_HOST}:(\d{{1,5}}):(\d{{1,3}})", PWM_FORM, 1)
    if int(m.group(3)) > 255:
        raise ValueError(f"malformed device bridge URL {url!r}: expected {PWM_FORM} (channel 0-255)")
    return m.group(1).strip("[]"), int(m.group(2)), int(m.group(3))


def check_bridge_key(key: bytes | None) -> bytes | None:
    """The key as bytes (None: no authentication); ValueError for anything but 32 non-zero bytes."""
    if key is None:
        return None
    if not isinstance(key, bytes | bytearray) or len(key) != KEY_SIZE:
        raise ValueError(f"device bridge key must be {KEY_SIZE} bytes (firmware_py.core.keys.load_key)")
    if not any(key):
        raise ValueError("device bridge key is all zeros")
    return bytes(key)


def auth_proof(key: bytes, role: str, server_nonce: bytes, client_nonce: bytes) -> bytes:
    """The handshake proof of `role` ("client" or "server") for these nonces (module docstring)."""
    if role not in ("client", "server"):
        raise ValueError(f"role must be 'client' or 'server', got {role!r}")
    msg = bytes(server_nonce) + bytes(client_nonce) + _PROOF_LABEL + role.encode("ascii")
    return hmac.new(key, msg, hashlib.sha256).digest()


_SHARED: dict[tuple[str, int, bytes | None], BridgeConnection] = {}
_SHARED_LOCK = threading.RLock()
"""Guards _SHARED and every connection's user count, so a handle never retains a closing connection."""


class BridgeConnection:
    """One TCP connection to a device bridge server, shared by the bus and PWM handles on it.

    Connects (authenticates, with a key) and says HELLO at once, so a wrong address or key fails at
    start-up with a clear message. Thread-safe: a lock spans each request and its response.

    Args:
        key: the 32-byte key: run the authentication handshake on every (re)connect and refuse a
            server that does not authenticate or cannot prove it holds the key. None: no handshake.

    Raises:
        I2CError: the server cannot be reached, speaks another protocol version, or fails
            authentication (errno EACCES: a wrong or missing key on either side).
    """

    def __init__(self, host: str, port: int, timeout_s: float = 1.0, *, key: bytes | None = None) -> None:
        if not (isinstance(timeout_s, int | float) and 0 < timeout_s < float("inf")):
            raise ValueError(f"device bridge timeout must be a positive number of seconds, got {timeout_s!r}")
        self._key = check_bridge_key(key)
        self.host, self.port, self.timeout_s = host, int(port), float(timeout_s)
        self.endpoint = _endpoint(host, self.port)
        self.i2c_addresses: tuple[int, ...] = ()
        self.pwm_channels: tuple[int, ...] = ()
        self.counters: dict[str, int] = dict.fromkeys(("requests", "connects", "failures"), 0)
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None
        self._users = 0
        self.closed = False
        with self._lock:
            self._connect()

    # -- transport -----------------------------------------------------------------------------

    def _connect(self) -> None:
        try:
            sock = socket.create_connection((self.host, self.port), timeout=self.timeout_s)
        except OSError as exc:
            self.counters["failures"] += 1
            reason = exc.strerror or str(exc) or type(exc).__name__
            code = exc.errno if isinstance(exc.errno, int) and exc.errno > 0 else errno.EHOSTUNREACH  # gaierror < 0
            raise I2CError(code,
                           f"cannot connect to the device bridge at {self.endpoint}: {reason}; {HINT}") from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock = sock
        self.counters["connects"] += 1
        try:
            if self._key is not None:
                self._authenticate(self._key)
            body = self._checked(OP_HELLO, *self._exchange(OP_HELLO, struct.pack("<H", VERSION)))
            self.i2c_addresses, self.pwm_channels = self._parse_hello(body)
        except I2CError:
            self._fail()  # never keep a connection whose version (or key) was not agreed
            raise

    @property
    def authenticated(self) -> bool:
        """Whether this connection runs the authentication handshake (it was given a key)."""
        return self._key is not None

    def _authenticate(self, key: bytes) -> None:
        """The challenge-response handshake (module docstring); I2CError EACCES if either side fails it."""
        status, body = self._exchange(OP_AUTH_CHALLENGE, struct.pack("<H", AUTH_VERSION))
        if status == STATUS_BAD_REQUEST:
            raise I2CError(errno.EACCES, f"the device bridge at {self.endpoint} does not authenticate (it was "
                                         f"started without a key): refused; give `pilescan-sitl serve --devices` "
                                         f"the same --signing-key")
        server_nonce = self._checked(OP_AUTH_CHALLENGE, status, body)
        if len(server_nonce) != NONCE_SIZE:
            raise I2CError(errno.EPROTO, f"device bridge at {self.endpoint} sent a {len(server_nonce)}-byte "
                                         f"challenge (expected {NONCE_SIZE})")
        client_nonce = secrets.token_bytes(NONCE_SIZE)
        proof = auth_proof(key, "client", server_nonce, client_nonce)
        server_proof = self._checked(OP_AUTH_PROVE, *self._exchange(OP_AUTH_PROVE, client_nonce + proof))
        if not hmac.compare_digest(server_proof, auth_proof(key, "server", server_nonce, client_nonce)):
            raise I2CError(errno.EACCES, f"the device bridge at {self.endpoint} could not prove it holds the key "
                                         f"(another key, or not the SITL you meant): refused")

    def _parse_hello(self, body: bytes) -> tuple[tuple[int, ...], tuple[int, ...]]:
        try:
            version, n = struct.unpack_from("<HB", body)
            addrs, m, channels = body[3:3 + n], body[3 + n], body[4 + n:]
            if version == VERSION and len(addrs) == n and len(channels) == m:
                return tuple(addrs), tuple(channels)
        except (struct.error, IndexError):
            pass
        raise I2CError(errno.EPROTO, f"{self.endpoint} is not a version {VERSION} device bridge "
                                     f"(HELLO answer {body[:16].hex() or 'empty'}); {HINT}")

    def _fail(self) -> None:
        """Drop the socket after a failure, so the next request reconnects instead of reading a stale answer."""
        if self._sock is not None:
            self.counters["failures"] += 1
            self._sock.close()
            self._sock = None

    def _recv_exactly(self, sock: socket.socket, n: int, deadline: float) -> bytes:
        buf = bytearray()
        while len(buf) < n:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError("timed out")
            sock.settimeout(remaining)
            chunk = sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionResetError(errno.ECONNRESET, "connection closed by the server")
            buf += chunk
        return bytes(buf)

    def _exchange(self, op: int, payload: bytes) -> tuple[int, bytes]:
        """Send one request and read its response, within timeout_s; I2CError (socket dropped) otherwise."""
        sock = self._sock
        assert sock is not None
        deadline = time.monotonic() + self.timeout_s
        try:
            sock.settimeout(self.timeout_s)
            sock.sendall(HEADER.pack(len(payload), op) + payload)
            length, status = HEADER.unpack(self._recv_exactly(sock, HEADER.size, deadline))
            body = self._recv_exactly(sock, length, deadline)
        except OSError as exc:  # socket.timeout is TimeoutError, an OSError
            self._fail()
            if isinstance(exc, TimeoutError):
                code, reason = errno.ETIMEDOUT, f"no answer within {self.timeout_s:g} s"
            else:
                code, reason = exc.errno or errno.EIO, exc.strerror or str(exc)
            raise I2CError(code, f"device bridge at {self.endpoint}: op 0x{op:02x} failed: {reason}") from None
        return status, body

    def _checked(self, op: int, status: int, body: bytes) -> bytes:
        if status == STATUS_OK:
            return body
        msg = body.decode("utf-8", "replace")
        if status == STATUS_NACK:
            raise I2CError(errno.EREMOTEIO, msg)
        if status == STATUS_BAD_REQUEST:
            raise I2CError(errno.EPROTO, f"device bridge at {self.endpoint} refused op 0x{op:02x}: {msg}")
        if status == STATUS_ERROR:
            raise I2CError(errno.EIO, f"device bridge at {self.endpoint}: device error: {msg}")
        if status == STATUS_AUTH:
            self._fail()  # the server closes the connection after this answer
            hint = ("give the payload the SITL's key (--signing-key FILE)" if self._key is None
                    else "both sides need the same key file")
            raise I2CError(errno.EACCES, f"device bridge at {self.endpoint} refused us: {msg}; {hint}")
        self._fail()
        raise I2CError(errno.EPROTO, f"device bridge at {self.endpoint}: unknown status 0x{status:02x}")

    def request(self, op: int, payload: bytes = b"") -> bytes:
        """One request's OK payload; I2CError for a NACK, a refusal, a device error or a lost link.

        Reconnects first if an earlier request failed.
        """
        with self._lock:
            if self.closed:
                raise I2CError(errno.EBADF, f"device bridge connection to {self.endpoint} is closed")
            self.counters["requests"] += 1
            if self._sock is None:
                self._connect()
            return self._checked(op, *self._exchange(op, payload))

    # -- sharing -------------------------------------------------------------------------------

    def retain(self) -> None:
        """One more handle uses this connection."""
        with _SHARED_LOCK:
            if self.closed:
                raise I2CError(errno.EBADF, f"device bridge connection to {self.endpoint} is closed")
            self._users += 1

    def release(self) -> None:
        """A handle is done with this connection; the last one closes it."""
        with _SHARED_LOCK:
            self._users = max(0, self._users - 1)
            if self._users == 0:
                self.close()

    def close(self) -> None:
        """Close the socket now (handles still open get I2CError EBADF). Idempotent."""
        with _SHARED_LOCK:
            if _SHARED.get((self.host, self.port, self._key)) is self:
                del _SHARED[(self.host, self.port, self._key)]
        with self._lock:
            self.closed = True
            if self._sock is not None:
                self._sock.close()
                self._sock = None


def shared_connection(host: str, port: int, timeout_s: float = 1.0, *, key: bytes | None = None) -> BridgeConnection:
    """This process's connection to HOST:PORT (with this key, or none), made on first use. Wrap it in a
    handle to keep it open. Handles given different keys never share a connection."""
    key = check_bridge_key(key)
    with _SHARED_LOCK:
        conn = _SHARED.get((host, port, key))
        if conn is None or conn.closed:
            conn = _SHARED[(host, port, key)] = BridgeConnection(host, port, timeout_s, key=key)
        return conn


class BridgeI2CBus:
    """An I2CBus whose transfers run on the SITL's simulated bus, behind a device bridge."""

    def __init__(self, conn: BridgeConnection) -> None:
        conn.retain()
        self.conn = conn
        self._closed = False

    def _request(self, op: int, payload: bytes) -> bytes:
        if self._closed:
            raise I2CError(errno.EBADF, f"device bridge I2C bus on {self.conn.endpoint} is closed")
        return self.conn.request(op, payload)

    @staticmethod
    def _check_data(data: bytes, room: int) -> bytes:
        data = bytes(data)
        if len(data) > room:
            raise ValueError(f"I2C write of {len(data)} bytes exceeds the device bridge's {room}-byte limit")
        return data

    def write(self, addr: int, data: bytes) -> None:
        data = self._check_data(data, MAX_PAYLOAD - 1)
        self._request(OP_I2C_WRITE, bytes((check_i2c_addr(addr),)) + data)

    def read(self, addr: int, n: int) -> bytes:
        check_i2c_addr(addr)
        if check_read_len(n) > MAX_PAYLOAD:
            raise ValueError(f"I2C read of {n} bytes exceeds the device bridge's {MAX_PAYLOAD}-byte limit")
        return self._sized(self._request(OP_I2C_READ, struct.pack("<BH", addr, n)), n)

    def write_read(self, addr: int, data: bytes, n: int) -> bytes:
        check_i2c_addr(addr)
        if check_read_len(n) > MAX_PAYLOAD:
            raise ValueError(f"I2C read of {n} bytes exceeds the device bridge's {MAX_PAYLOAD}-byte limit")
        data = self._check_data(data, MAX_PAYLOAD - 3)
        return self._sized(self._request(OP_I2C_WRITE_READ, struct.pack("<BH", addr, n) + data), n)

    def _sized(self, data: bytes, n: int) -> bytes:
        if len(data) != n:
            raise I2CError(errno.EPROTO, f"device bridge at {self.conn.endpoint} answered a read of {n} bytes "
                                         f"with {len(data)}")
        return data

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.conn.release()


class BridgePwm:
    """A PwmOutput on the SITL (e.g. its emulated servo), behind a device bridge.

    Failures of the link raise I2CError, an OSError like a sysfs write failure.
    """

    def __init__(self, conn: BridgeConnection, channel: int) -> None:
        if isinstance(channel, bool) or not isinstance(channel, int) or not 0 <= channel <= 255:
            raise ValueError(f"device bridge PWM channel must be an integer 0-255, got {channel!r}")
        if channel not in conn.pwm_channels:
            have = ", ".join(map(str, conn.pwm_channels)) or "none"
            raise ValueError(f"the device bridge at {conn.endpoint} has no PWM channel {channel} (it has: {have})")
        conn.retain()
        self.conn, self.channel = conn, channel
        self._closed = False

    def _request(self, op: int, payload: bytes) -> None:
        if self._closed:
            raise I2CError(errno.EBADF, f"device bridge PWM channel {self.channel} on {self.conn.endpoint} is closed")
        self.conn.request(op, payload)

    def set_pulse_us(self, pulse_us: float) -> None:
        self._request(OP_PWM_SET, struct.pack("<Bd", self.channel, check_pulse_us(pulse_us)))

    def disable(self) -> None:
        self._request(OP_PWM_DISABLE, bytes((self.channel,)))

    def close(self) -> None:
        """Disable the output (as the other PWM backends do) if the link allows, then let go of it."""
        if self._closed:
            return
        try:
            self.disable()
        except OSError:
            pass  # the SITL is gone: nothing left to disable
        finally:
            self._closed = True
            self.conn.release()


def open_bridge_i2c(url: str, timeout_s: float = 1.0, *, key: bytes | None = None) -> BridgeI2CBus:
    """`open_i2c('tcp:HOST:PORT')`: a bus handle on this process's shared connection to the bridge
    (authenticated with `key` when given)."""
    host, port = parse_tcp_url(url)
    with _SHARED_LOCK:
        return BridgeI2CBus(shared_connection(host, port, timeout_s, key=key))


def open_bridge_pwm(url: str, timeout_s: float = 1.0, *, key: bytes | None = None) -> BridgePwm:
    """`open_pwm('pwm:tcp:HOST:PORT:CHANNEL')`: a PWM handle on the shared connection to the bridge
    (authenticated with `key` when given)."""
    host, port, channel = parse_pwm_url(url)
    with _SHARED_LOCK:
        conn = shared_connection(host, port, timeout_s, key=key)
        try:
            return BridgePwm(conn, channel)
        except ValueError as exc:
            if conn._users == 0:
                conn.close()  # nobody else uses it: do not leave the socket open
            raise ValueError(f"bad PWM output {url!r}: {exc}") from None
