"""The networked-SITL device bridge, server side: serves the SITL's simulated I2C bus and PWM outputs
to payload processes that open `tcp:HOST:PORT` / `pwm:tcp:HOST:PORT:CHANNEL`.

The wire protocol is defined once, in firmware_py.hal.bridge (its module docstring documents it).

One daemon thread runs a selector over the listening socket and every client; each client's requests
are answered in order. The SITL steps the vehicle in another thread and the emulated LiDAR ray-casts
the vehicle's pose, so every device call is made holding the caller's `lock`.

Whatever a client sends, the thread survives: a frame it can parse but not accept (unknown op, wrong
size, bad address or channel, wrong version) gets BAD_REQUEST and the connection stays; a length
above MAX_PAYLOAD gets BAD_REQUEST and the connection is closed (the stream cannot be resynchronised).

With `key=` (the 32-byte MAVLink signing key, `pilescan-sitl serve --signing-key FILE`) a client must
pass the challenge-response handshake (firmware_py.hal.bridge's docstring) before anything else: a
request before it, a wrong proof, or no handshake within AUTH_TIMEOUT_S gets status AUTH (when it
sent something) and the connection is closed; `counters` count them (`unauthenticated`,
`auth_failed`; `authenticated` the handshakes passed). The handshake authenticates the connection,
not each frame.
"""

from __future__ import annotations

import contextlib
import hmac
import logging
import math
import secrets
import selectors
import socket
import struct
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from firmware_py.hal import I2CError, PwmOutput
from firmware_py.hal.bridge import (
    AUTH_TIMEOUT_S,
    AUTH_VERSION,
    HEADER,
    MAX_PAYLOAD,
    NONCE_SIZE,
    OP_AUTH_CHALLENGE,
    OP_AUTH_PROVE,
    OP_HELLO,
    OP_I2C_READ,
    OP_I2C_WRITE,
    OP_I2C_WRITE_READ,
    OP_PWM_DISABLE,
    OP_PWM_SET,
    PROOF_SIZE,
    STATUS_AUTH,
    STATUS_BAD_REQUEST,
    STATUS_ERROR,
    STATUS_NACK,
    STATUS_OK,
    VERSION,
    auth_proof,
    check_bridge_key,
    parse_tcp_url,
)

log = logging.getLogger(__name__)

SEND_TIMEOUT_S = 1.0
"""A client that stops reading its answers is dropped after this long, not allowed to stall the rest."""


def parse_bridge_url(url: str) -> tuple[str, int]:
    """(host, port) for the SITL's `--devices tcp:HOST:PORT` option; port 0 picks a free port.

    Raises:
        ValueError: a one-line message naming the URL and the expected form.
    """
    return parse_tcp_url(url, allow_port_zero=True)


class _BadRequest(Exception):
    """A request the server understood well enough to refuse."""


def _one_line(exc: BaseException) -> str:
    text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    return " ".join(text.split()) or type(exc).__name__


class _Client:
    def __init__(self, sock: socket.socket, peer: Any, authenticated: bool) -> None:
        self.sock, self.peer = sock, peer
        self.buf = bytearray()
        self.authenticated = authenticated
        self.nonce: bytes | None = None  # the challenge sent, until it is answered
        self.connected_at = time.monotonic()


class DeviceBridgeServer:
    """Serves `bus` (anything with the I2CBus methods, e.g. a SimI2CBus) and `pwm_outputs` over TCP.

    Binds at construction, so `.address` is known before `start()`.

    Args:
        bus: the simulated I2C bus; its `.devices` (if any) are listed in the HELLO answer.
        pwm_outputs: PWM channel number (0-255) -> output, e.g. {0: EmulatedServo(...)}.
        host, port: where to listen (port 0: any free port).
        lock: held around every device call (the SITL's world lock); None = no locking.
        key: the 32-byte key clients must authenticate with (module docstring); None: anyone who can
            reach the port drives the devices, as before.
    """

    def __init__(self, bus: Any, pwm_outputs: Mapping[int, PwmOutput] | None = None, host: str = "127.0.0.1",
                 port: int = 0, lock: Any = None, *, key: bytes | None = None) -> None:
        self._key = check_bridge_key(key)
        self.bus = bus
        self.pwm_outputs = dict(pwm_outputs or {})
        for ch in self.pwm_outputs:
            if isinstance(ch, bool) or not isinstance(ch, int) or not 0 <= ch <= 255:
                raise ValueError(f"device bridge PWM channel must be an integer 0-255, got {ch!r}")
        self._lock = lock if lock is not None else contextlib.nullcontext()
        self.counters: dict[str, int] = dict.fromkeys(
            ("requests", "nacks", "bad_requests", "errors", "clients", "dropped", "authenticated",
             "unauthenticated", "auth_failed"), 0)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.create_server((host, port), family=family)
        self._listener.setblocking(False)
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listener, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._clients: dict[socket.socket, _Client] = {}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False
        self._handlers: dict[int, Callable[[bytes], bytes]] = {
            OP_HELLO: self._hello, OP_I2C_WRITE: self._i2c_write, OP_I2C_READ: self._i2c_read,
            OP_I2C_WRITE_READ: self._i2c_write_read, OP_PWM_SET: self._pwm_set, OP_PWM_DISABLE: self._pwm_disable}

    @property
    def address(self) -> tuple[str, int]:
        """The bound (host, port)."""
        host, port = self._listener.getsockname()[:2]
        return host, port

    @property
    def url(self) -> str:
        """What a payload passes to open_i2c."""
        host, port = self.address
        return f"tcp:[{host}]:{port}" if ":" in host else f"tcp:{host}:{port}"

    @property
    def client_count(self) -> int:
        """Clients connected now."""
        return len(self._clients)

    @property
    def authenticates(self) -> bool:
        """Whether clients must pass the authentication handshake (the server has a key)."""
        return self._key is not None

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> DeviceBridgeServer:
        if self._closed or self._thread is not None:
            raise RuntimeError("a DeviceBridgeServer starts once, before close()")
        self._thread = threading.Thread(target=self._run, name=f"device-bridge {self.url}", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread and close every socket (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
            if self._thread.is_alive():
                log.warning("device bridge thread did not stop within 5 s (a device call hung?)")
        for client in list(self._clients.values()):
            client.sock.close()
        self._clients.clear()
        for s in (self._listener, self._wake_r, self._wake_w):
            s.close()
        self._sel.close()

    def __enter__(self) -> DeviceBridgeServer:
        if self._thread is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the socket loop ---------------------------------------------------------------------------

    def _run(self) -> None:
        sweep_s = AUTH_TIMEOUT_S / 5 if self._key is not None else None
        while not self._stop.is_set():
            try:
                events = self._sel.select(sweep_s)
            except (OSError, ValueError):  # closed under us
                return
            if self._key is not None:
                self._expire_unauthenticated()
            for key, _ in events:
                if self._stop.is_set():
                    return
                try:
                    if key.data == "listen":
                        self._accept()
                    elif key.data == "wake":
                        self._wake_r.recv(64)
                    else:
                        self._service(key.data)
                except Exception:  # never let one client (or a bug) kill the server
                    log.exception("device bridge: unexpected failure, dropping that client")
                    if isinstance(key.data, _Client):
                        self._drop(key.data)

    def _accept(self) -> None:
        try:
            sock, peer = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(SEND_TIMEOUT_S)  # recv only runs when readable; this bounds sendall
        client = _Client(sock, peer, authenticated=self._key is None)
        self._clients[sock] = client
        self._sel.register(sock, selectors.EVENT_READ, client)
        self.counters["clients"] += 1
        log.debug("device bridge: client %s connected", peer)

    def _drop(self, client: _Client, why: str | None = None) -> None:
        if self._clients.pop(client.sock, None) is None:
            return
        if why is not None:
            self.counters["dropped"] += 1
            log.warning("device bridge: dropping client %s: %s", client.peer, why)
        with contextlib.suppress(KeyError, ValueError):
            self._sel.unregister(client.sock)
        client.sock.close()

    def _service(self, client: _Client) -> None:
        try:
            chunk = client.sock.recv(4096)
        except OSError:
            chunk = b""
        if not chunk:
            self._drop(client)
            return
        buf = client.buf
        buf += chunk
        while len(buf) >= HEADER.size:
            length, op = HEADER.unpack_from(buf)
            if length > MAX_PAYLOAD:
                self.counters["bad_requests"] += 1
                self._send(client, STATUS_BAD_REQUEST, f"frame length {length} exceeds {MAX_PAYLOAD}".encode())
                self._drop(client, f"frame length {length} > {MAX_PAYLOAD}")
                return
            end = HEADER.size + length
            if len(buf) < end:
                return
            payload = bytes(buf[HEADER.size:end])
            del buf[:end]
            if op in (OP_AUTH_CHALLENGE, OP_AUTH_PROVE):
                answer = self._auth(client, op, payload)
            elif not client.authenticated:
                self.counters["unauthenticated"] += 1
                self._send(client, STATUS_AUTH, b"this device bridge requires authentication "
                                                b"(it was started with a key)")
                self._drop(client, f"op 0x{op:02x} before authenticating")
                return
            else:
                answer = self.handle_request(op, payload)
            if not self._send(client, *answer):
                return
            if answer[0] == STATUS_AUTH:
                self._drop(client, "failed authentication")
                return

    # -- authentication ------------------------------------------------------------------------------

    def _auth(self, client: _Client, op: int, payload: bytes) -> tuple[int, bytes]:
        """One step of the handshake: (status, answer); STATUS_AUTH means drop the client after sending it."""
        if self._key is None:
            self.counters["bad_requests"] += 1
            return STATUS_BAD_REQUEST, b"this device bridge does not authenticate (it was started without a key)"
        if client.authenticated:
            self.counters["bad_requests"] += 1
            return STATUS_BAD_REQUEST, b"already authenticated"
        if op == OP_AUTH_CHALLENGE:
            if len(payload) != 2 or struct.unpack("<H", payload)[0] != AUTH_VERSION:
                self.counters["bad_requests"] += 1
                return STATUS_BAD_REQUEST, f"AUTH_CHALLENGE needs u16 auth version {AUTH_VERSION}".encode()
            client.nonce = secrets.token_bytes(NONCE_SIZE)
            return STATUS_OK, client.nonce
        server_nonce, client.nonce = client.nonce, None  # one proof per challenge
        if server_nonce is None or len(payload) != NONCE_SIZE + PROOF_SIZE:
            self.counters["auth_failed"] += 1
            return STATUS_AUTH, b"authentication failed: AUTH_PROVE without a challenge, or malformed"
        client_nonce, proof = payload[:NONCE_SIZE], payload[NONCE_SIZE:]
        if not hmac.compare_digest(proof, auth_proof(self._key, "client", server_nonce, client_nonce)):
            self.counters["auth_failed"] += 1
            return STATUS_AUTH, b"authentication failed: wrong key"
        client.authenticated = True
        self.counters["authenticated"] += 1
        log.debug("device bridge: client %s authenticated", client.peer)
        return STATUS_OK, auth_proof(self._key, "server", server_nonce, client_nonce)

    def _expire_unauthenticated(self) -> None:
        """Drop clients that connected but have not authenticated in time (they hold a socket each)."""
        cutoff = time.monotonic() - AUTH_TIMEOUT_S
        for client in [c for c in self._clients.values() if not c.authenticated and c.connected_at < cutoff]:
            self.counters["unauthenticated"] += 1
            self._drop(client, f"not authenticated within {AUTH_TIMEOUT_S:g} s")

    def _send(self, client: _Client, status: int, body: bytes) -> bool:
        try:
            client.sock.sendall(HEADER.pack(len(body), status) + body)
        except OSError as exc:
            self._drop(client, f"cannot answer: {exc}")
            return False
        return True

    # -- requests ------------------------------------------------------------------------------------

    def handle_request(self, op: int, payload: bytes) -> tuple[int, bytes]:
        """(status, response payload) for one request; never raises."""
        self.counters["requests"] += 1
        try:
            handler = self._handlers.get(op)
            if handler is None:
                raise _BadRequest(f"unknown op 0x{op:02x}")
            return STATUS_OK, handler(payload)
        except _BadRequest as exc:
            self.counters["bad_requests"] += 1
            return STATUS_BAD_REQUEST, self._message(exc)
        except I2CError as exc:
            self.counters["nacks"] += 1
            return STATUS_NACK, self._message(exc)
        except Exception as exc:
            self.counters["errors"] += 1
            log.exception("device bridge: op 0x%02x raised", op)
            return STATUS_ERROR, self._message(exc, f"{type(exc).__name__}: ")

    @staticmethod
    def _message(exc: BaseException, prefix: str = "") -> bytes:
        return (prefix + _one_line(exc)).encode("utf-8", "replace")[:MAX_PAYLOAD]

    @staticmethod
    def _expect(payload: bytes, n: int, what: str, at_least: bool = False) -> None:
        if len(payload) < n or (not at_least and len(payload) != n):
            raise _BadRequest(f"{what} needs {'at least ' if at_least else ''}{n} payload bytes, got {len(payload)}")

    @staticmethod
    def _addr_len(payload: bytes) -> tuple[int, int]:
        addr, n = struct.unpack_from("<BH", payload)
        if addr > 0x7F:
            raise _BadRequest(f"I2C address 0x{addr:02x} is not 7-bit")
        if not 1 <= n <= MAX_PAYLOAD:
            raise _BadRequest(f"I2C read length {n} is not 1-{MAX_PAYLOAD}")
        return addr, n

    @staticmethod
    def _sized(data: Any, n: int) -> bytes:
        data = bytes(data)
        if len(data) != n:
            raise RuntimeError(f"the bus returned {len(data)} bytes for a read of {n}")
        return data

    def _hello(self, payload: bytes) -> bytes:
        self._expect(payload, 2, "HELLO")
        (version,) = struct.unpack("<H", payload)
        if version != VERSION:
            raise _BadRequest(f"protocol version {version} not supported (this server speaks {VERSION})")
        devices = getattr(self.bus, "devices", None) or getattr(getattr(self.bus, "bus", None), "devices", None)
        addrs = sorted(a for a in (devices or {}) if isinstance(a, int) and 0 <= a <= 0x7F)
        channels = sorted(self.pwm_outputs)
        return struct.pack("<HB", VERSION, len(addrs)) + bytes(addrs) + bytes((len(channels),)) + bytes(channels)

    def _i2c_write(self, payload: bytes) -> bytes:
        self._expect(payload, 1, "I2C_WRITE", at_least=True)
        if payload[0] > 0x7F:
            raise _BadRequest(f"I2C address 0x{payload[0]:02x} is not 7-bit")
        with self._lock:
            self.bus.write(payload[0], payload[1:])
        return b""

    def _i2c_read(self, payload: bytes) -> bytes:
        self._expect(payload, 3, "I2C_READ")
        addr, n = self._addr_len(payload)
        with self._lock:
            return self._sized(self.bus.read(addr, n), n)

    def _i2c_write_read(self, payload: bytes) -> bytes:
        self._expect(payload, 3, "I2C_WRITE_READ", at_least=True)
        addr, n = self._addr_len(payload)
        with self._lock:
            return self._sized(self.bus.write_read(addr, payload[3:], n), n)

    def _pwm(self, channel: int) -> PwmOutput:
        try:
            return self.pwm_outputs[channel]
        except KeyError:
            have = ", ".join(map(str, sorted(self.pwm_outputs))) or "none"
            raise _BadRequest(f"no PWM channel {channel} (have: {have})") from None

    def _pwm_set(self, payload: bytes) -> bytes:
        self._expect(payload, 9, "PWM_SET")
        channel, pulse_us = struct.unpack("<Bd", payload)
        pwm = self._pwm(channel)
        if not (math.isfinite(pulse_us) and 500.0 <= pulse_us <= 2500.0):
            raise _BadRequest(f"servo pulse must be 500-2500 us, got {pulse_us}")
        with self._lock:
            pwm.set_pulse_us(pulse_us)
        return b""

    def _pwm_disable(self, payload: bytes) -> bytes:
        self._expect(payload, 1, "PWM_DISABLE")
        pwm = self._pwm(payload[0])
        with self._lock:
            pwm.disable()
        return b""
