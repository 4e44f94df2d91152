"""MAVLink 2 links to the autopilot (ardupilotmega dialect), behind the HAL's `MavlinkLink` protocol.

Backends, chosen by URL (DESIGN section 7):

    serial:/dev/ttyAMA0:921600   UART to the autopilot (pyserial through pymavlink; baud optional, 921600)
    udp:HOST:PORT                we listen there and answer whoever talks to us (also udpin:HOST:PORT)
    udpout:HOST:PORT             we send there; a HEARTBEAT goes out at once so a listening autopilot
                                 (ArduPilot SITL, `pilescan-sitl serve`) learns our address
    tcp:HOST:PORT                TCP client (ArduPilot SITL's tcp:5760)
    SCHEME:...                   a backend another layer registered (`register_mavlink_backend`)

The schemes live in `MAVLINK_BACKENDS`, a `firmware_py.hal.registry.BackendRegistry` (the rules every
URL-selected backend follows); `signing=` is its credential, and a backend that cannot sign is refused.

`PymavlinkLink` uses `mavutil.mavlink_connection` for the transport only; `ByteStreamLink` runs over any
pair of byte callables (the SITL lockstep's in-process pipes, tests). Both parse with `MavlinkFramer`,
so both survive garbage the same way: a frame that fails its CRC costs one byte, not the length its
(possibly corrupt) header claims, so one bad length byte cannot swallow the valid frames behind it.
Nothing on the receive path raises for bad data; everything is counted in `stats`.

Signing (`signing=SigningConfig(...)`, `firmware_py.hal.signing`): every frame we send is signed
(MAVLink 2 signature: link id, 48-bit timestamp, SHA-256-based tag); a received frame is delivered
only if its signature checks out and its timestamp is newer than the last one accepted from that
sender; unsigned, forged and replayed frames are refused and counted (`rx_unsigned`,
`rx_bad_signature`, `rx_replayed`; `rx_signed` counts authenticated frames, `rx_unsigned_accepted`
unsigned ones let in by `allow_unsigned`). Authentication is checked after the CRC: a frame that
fails its CRC still costs one byte of resync; a refused frame has passed its CRC, so its length is
as trustworthy as an accepted frame's and it is skipped whole, like one (its payload, which a
sender without the key chose, is never scanned for frames, and it is not counted as line noise).
On a listening UDP link (udp:HOST:PORT) a sender is only kept as a destination if its datagram
held an authenticated frame, so unauthenticated senders cannot make us send to them. Without a
key everything is as before: signed frames from others are delivered without a check.

The companion's 1 Hz HEARTBEAT is the caller's job (`heartbeat_msg()`); the pose tracker sends it.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal import MavlinkLink
from firmware_py.hal.registry import BackendRegistry, Credential
from firmware_py.hal.signing import MavlinkSigner, SigningConfig

DEFAULT_SERIAL_BAUD = 921_600
"""The usual companion UART rate on a Pixhawk TELEM2 (SERIAL2_BAUD = 921)."""

COMPANION_SYSTEM_ID = 1
"""A companion computer shares its vehicle's system id (MAVLink microservices convention)."""

COMPANION_COMPONENT_ID = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191

_MAX_READS_PER_RECV = 256
"""Reads per recv() call; bounds the time one call can take on a flooded link."""

_READ_CHUNK = 4096


def heartbeat_msg() -> Any:
    """The companion's HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER, no autopilot); send it at 1 Hz."""
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3)


# ----- framing ------------------------------------------------------------------------------------

class MavlinkFramer:
    """Cuts a byte stream into MAVLink 1/2 frames checked by pymavlink; resynchronises one byte at a time.

    Frames of message ids outside the dialect cannot be CRC-checked (no CRC_EXTRA) and are skipped
    like bad frames. Without a signer, signed frames are accepted without checking the signature.
    With one (`MavlinkSigner`), a CRC-checked frame is delivered only if `signer.verify` accepts it;
    a refused frame is counted in the signer's stats (not in bad_bytes / bad_frames: it is not line
    noise) and skipped whole, as an accepted frame is: its CRC vouches for its length. The decoder
    `mav` must not have a pymavlink signing key: the signer does the checking.
    """

    _MAGIC_V1 = mavlink.PROTOCOL_MARKER_V1  # 0xFE
    _MAGIC_V2 = mavlink.PROTOCOL_MARKER_V2  # 0xFD

    def __init__(self, mav: mavlink.MAVLink | None = None, signer: MavlinkSigner | None = None) -> None:
        self._mav = mav if mav is not None else mavlink.MAVLink(None)
        if signer is not None and self._mav.signing.secret_key is not None:
            raise ValueError("MavlinkFramer checks signatures with its signer: give it a decoder without a key")
        self.signer = signer
        self._buf = bytearray()
        self._last_seq: dict[tuple[int, int], int] = {}
        self.bad_bytes = 0
        self.bad_frames = 0
        self.seq_lost = 0

    def feed(self, data: bytes | bytearray) -> list[Any]:
        """Append bytes; return every complete valid message now in the buffer, in order."""
        self._buf += data
        buf, out, i = self._buf, [], 0
        while i < len(buf):
            if buf[i] != self._MAGIC_V1 and buf[i] != self._MAGIC_V2:
                j = self._next_magic(i)
                self.bad_bytes += j - i
                i = j
                continue
            total = self._frame_length(i)
            if total is None:
                break  # header incomplete
            if total > 0 and len(buf) - i < total:
                break  # wait for the rest of the frame
            msg = self._decode(buf[i:i + total]) if total else None
            if msg is None:
                self.bad_frames += 1  # impossible header or failed CRC: skip one byte, look again
                self.bad_bytes += 1
                i += 1
                continue
            if self.signer is not None:
                frame = buf[i:i + total]
                if self.signer.verify(frame) is not None:  # unsigned, forged or replayed: counted there
                    i += total  # well-formed (its CRC passed): skipped whole, its payload never scanned
                    continue
                msg._signed = bool(frame[2] & mavlink.MAVLINK_IFLAG_SIGNED) and frame[0] == self._MAGIC_V2
                if msg._signed:
                    msg._link_id = frame[-13]
            out.append(msg)
            self._count_seq(msg)
            i += total
        del self._buf[:i]
        return out

    def _next_magic(self, start: int) -> int:
        hits = [j for j in (self._buf.find(self._MAGIC_V1, start), self._buf.find(self._MAGIC_V2, start)) if j >= 0]
        return min(hits) if hits else len(self._buf)

    def _frame_length(self, i: int) -> int | None:
        """Whole frame length from the header at i; None if incomplete, 0 if the header is impossible."""
        buf = self._buf
        if len(buf) - i < 3:
            return None
        if buf[i] == self._MAGIC_V1:
            return 6 + buf[i + 1] + 2
        flags = buf[i + 2]
        if flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
            return 0
        return 10 + buf[i + 1] + 2 + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if flags else 0)

    def _decode(self, frame: bytearray) -> Any | None:
        try:
            msg = self._mav.decode(bytearray(frame))
        except Exception:  # pymavlink raises MAVError, and struct/Unicode errors on hostile input
            return None
        if isinstance(msg, mavlink.MAVLink_unknown | mavlink.MAVLink_bad_data):
            return None
        return msg

    def _count_seq(self, msg: Any) -> None:
        """Sequence gaps per sender: frames lost on the wire (a jump over half the range is a reorder)."""
        key = (msg.get_srcSystem(), msg.get_srcComponent())
        seq = msg.get_seq()
        last = self._last_seq.get(key)
        if last is not None:
            gap = (seq - last - 1) % 256
            if gap < 128:
                self.seq_lost += gap
        self._last_seq[key] = seq


# ----- links --------------------------------------------------------------------------------------

_SIGNING_STATS = (("rx_signed", "signed"), ("rx_unsigned", "unsigned"), ("rx_bad_signature", "bad_signature"),
                  ("rx_replayed", "replayed"), ("rx_unsigned_accepted", "unsigned_accepted"))


def _signer(signing: SigningConfig | MavlinkSigner | None) -> MavlinkSigner | None:
    if signing is None or isinstance(signing, MavlinkSigner):
        return signing
    return MavlinkSigner(signing)  # ValueError for anything but a SigningConfig


class _FramedLink:
    """Shared send/recv bookkeeping; subclasses provide _read_chunks, _write and _close."""

    def __init__(self, source_system: int, source_component: int,
                 signing: SigningConfig | MavlinkSigner | None = None) -> None:
        for name, value in (("source_system", source_system), ("source_component", source_component)):
            if not (isinstance(value, int) and 1 <= value <= 255):
                raise ValueError(f"{name} must be an integer 1-255, got {value!r}")
        self.mav = mavlink.MAVLink(None, srcSystem=source_system, srcComponent=source_component)
        """Our encoder (source ids, sequence); `link.mav.xxx_encode(...)` builds messages to send."""
        self.signer = _signer(signing)
        """The link's signing state (`firmware_py.hal.signing.MavlinkSigner`), None when unsigned."""
        if self.signer is not None:
            self.signer.attach(self.mav)
        self._framer = MavlinkFramer(mavlink.MAVLink(None), signer=self.signer)
        self.stats: dict[str, int] = {
            "rx_bytes": 0, "rx_messages": 0, "rx_bad_bytes": 0, "rx_bad_frames": 0, "rx_seq_lost": 0,
            "tx_messages": 0, "tx_errors": 0, "io_errors": 0,
            **{name: 0 for name, _ in _SIGNING_STATS},
        }
        self.last_error: str | None = None
        self.closed = False

    @property
    def signing_active(self) -> bool:
        """Whether we sign what we send and check what we receive."""
        return self.signer is not None

    def send(self, msg: Any) -> None:
        """Pack with our ids and sequence (signed, with a key) and write; a failed write is counted."""
        if self.closed:
            raise ValueError("send on a closed MAVLink link")
        buf = self.signer.pack(msg, self.mav) if self.signer is not None else msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        try:
            ok = self._write(bytes(buf))
        except OSError as exc:
            ok = False
            self._io_error(exc)
        if ok:
            self.stats["tx_messages"] += 1
        else:
            self.stats["tx_errors"] += 1

    def recv(self) -> list[Any]:
        """All complete messages received so far; never blocks, never raises for bad bytes."""
        if self.closed:
            return []
        out: list[Any] = []
        got = False
        try:
            for chunk, new_peer in self._read_chunks():
                got = True
                self.stats["rx_bytes"] += len(chunk)
                msgs = self._framer.feed(chunk)
                out.extend(msgs)
                if new_peer is not None and self.signer is not None and not msgs:
                    self._forget_peer(new_peer)  # nothing authenticated from it: do not answer it
        except OSError as exc:
            self._io_error(exc)
        if not got:
            return out  # the usual case at 500 Hz: nothing new, no bookkeeping
        f = self._framer
        self.stats["rx_messages"] += len(out)
        self.stats["rx_bad_bytes"] = f.bad_bytes
        self.stats["rx_bad_frames"] = f.bad_frames
        self.stats["rx_seq_lost"] = f.seq_lost
        if self.signer is not None:
            for name, key in _SIGNING_STATS:
                self.stats[name] = self.signer.stats[key]
        return out

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self._close()

    def __enter__(self) -> _FramedLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _io_error(self, exc: OSError) -> None:
        self.stats["io_errors"] += 1
        self.last_error = f"{type(exc).__name__}: {exc}"

    def _read_chunks(self) -> list[tuple[bytes, Any]]:
        """Chunks read now, each with the sender it made us learn (a UDP client), or None."""
        raise NotImplementedError

    def _forget_peer(self, peer: Any) -> None:
        """Stop sending to a sender learnt from a chunk that held nothing authenticated."""

    def _write(self, data: bytes) -> bool:
        raise NotImplementedError

    def _close(self) -> None:
        raise NotImplementedError


class ByteStreamLink(_FramedLink):
    """A MavlinkLink over two byte callables: `send_bytes(frame)` and `recv_bytes() -> bytes` (b"" if none).

    For in-memory pipes, e.g. `ByteStreamLink(end.send, end.recv)` on a `sitl.mavlink.transport.PipeTransport`
    end; the SITL lockstep runner and the tests use it, so they run the same parser as the real links.
    """

    def __init__(self, send_bytes: Callable[[bytes], None], recv_bytes: Callable[[], bytes],
                 source_system: int = COMPANION_SYSTEM_ID, source_component: int = COMPANION_COMPONENT_ID,
                 close: Callable[[], None] | None = None, *,
                 signing: SigningConfig | MavlinkSigner | None = None) -> None:
        super().__init__(source_system, source_component, signing)
        self._send_bytes, self._recv_bytes, self._close_cb = send_bytes, recv_bytes, close

    def _read_chunks(self) -> list[tuple[bytes, Any]]:
        data = self._recv_bytes()
        return [(bytes(data), None)] if data else []

    def _write(self, data: bytes) -> bool:
        self._send_bytes(data)
        return True

    def _close(self) -> None:
        if self._close_cb is not None:
            self._close_cb()


_URL_RE = re.compile(r"(?P<scheme>[a-z][a-z0-9]*):(?P<rest>.*)", re.DOTALL)


def _host_port(url: str, rest: str, allow_port_zero: bool) -> tuple[str, int]:
    host, sep, port_s = rest.rpartition(":")
    if not sep or not host or any(c.isspace() for c in host) or not port_s.isdigit():
        raise ValueError(f"expected HOST:PORT in MAVLink URL {url!r}")
    port = int(port_s)
    if not (0 if allow_port_zero else 1) <= port <= 65535:
        raise ValueError(f"UDP/TCP port {port} out of range in MAVLink URL {url!r}")
    return host, port


def mavutil_device(url: str) -> tuple[str, int]:
    """Our link URL -> (mavutil device string, baud): the one place URL forms are translated.

    serial:PATH[:BAUD] -> (PATH, BAUD); udp:H:P and udpin:H:P -> "udpin:H:P" (we listen; port 0 picks
    a free one); udpout:H:P -> "udpout:H:P"; tcp:H:P -> "tcp:H:P". ValueError for anything else.
    """
    m = _URL_RE.fullmatch(url.strip()) if isinstance(url, str) else None
    if m is None:
        raise ValueError(f"MAVLink URL must look like serial:/dev/ttyAMA0:921600, udp:HOST:PORT, "
                         f"udpout:HOST:PORT or tcp:HOST:PORT, got {url!r}")
    scheme, rest = m.group("scheme"), m.group("rest")
    if scheme == "serial":
        path, baud = rest, DEFAULT_SERIAL_BAUD
        head, sep, tail = rest.rpartition(":")
        if sep and tail.isdigit():
            path, baud = head, int(tail)
        elif sep and not tail:
            raise ValueError(f"missing baud rate after ':' in MAVLink URL {url!r}")
        if not path or any(c.isspace() for c in path):
            raise ValueError(f"missing serial device path in MAVLink URL {url!r}")
        if not 50 <= baud <= 20_000_000:
            raise ValueError(f"serial baud rate {baud} out of range in MAVLink URL {url!r}")
        return path, baud
    if scheme in ("udp", "udpin"):
        host, port = _host_port(url, rest, allow_port_zero=True)
        return f"udpin:{host}:{port}", 0
    if scheme in ("udpout", "tcp"):
        host, port = _host_port(url, rest, allow_port_zero=False)
        return f"{scheme}:{host}:{port}", 0
    raise ValueError(f"unsupported MAVLink link scheme {scheme!r} in {url!r} "
                     f"(use serial:, udp:, udpout:, tcp: or a registered backend)")


class PymavlinkLink(_FramedLink):
    """A MavlinkLink on `mavutil.mavlink_connection` (serial, UDP or TCP; see the module docstring).

    mavutil provides the transport (sockets, pyserial, its serial baud-rate workaround); parsing is
    MavlinkFramer's, so stats mean the same on every link. `connect` replaces mavutil for tests.
    `signing`: sign and check (module docstring).
    """

    def __init__(self, url: str, source_system: int = COMPANION_SYSTEM_ID,
                 source_component: int = COMPANION_COMPONENT_ID, *,
                 connect: Callable[..., Any] | None = None,
                 signing: SigningConfig | MavlinkSigner | None = None) -> None:
        super().__init__(source_system, source_component, signing)
        self.url = url
        device, baud = mavutil_device(url)
        if connect is None:
            from pymavlink import mavutil  # late: a heavy import only real links need
            connect = mavutil.mavlink_connection
        kwargs: dict[str, Any] = {"source_system": source_system, "source_component": source_component}
        if baud:
            kwargs["baud"] = baud
        self._conn = connect(device, **kwargs)
        if device.startswith("udpout:"):
            self.send(heartbeat_msg())  # a udp-listening autopilot replies to whoever spoke last

    @property
    def local_address(self) -> tuple[str, int] | None:
        """Bound (host, port) of a UDP/TCP link (e.g. after udp:127.0.0.1:0), None for serial."""
        sock = getattr(self._conn, "port", None)
        getsockname = getattr(sock, "getsockname", None)
        return getsockname() if getsockname is not None else None

    def _read_chunks(self) -> list[tuple[bytes, Any]]:
        chunks = []
        # mavutil's listening UDP socket answers every address it has heard (its `clients`); with a
        # key, a datagram's sender is only kept there if the datagram held an authenticated frame
        clients = getattr(self._conn, "clients", None) if self.signer is not None else None
        known = set(clients) if isinstance(clients, set) else None
        for _ in range(_MAX_READS_PER_RECV):
            try:
                data = self._conn.recv(_READ_CHUNK)
            except OSError as exc:  # keep what was read before the error
                self._io_error(exc)
                break
            if not data:  # mavutil returns "" (a str) when a socket has nothing
                break
            new_peer = None
            if known is not None:
                added = clients - known
                if added:
                    new_peer = added.pop()
                    known.add(new_peer)
            chunks.append((bytes(data), new_peer))
        return chunks

    def _forget_peer(self, peer: Any) -> None:
        self._conn.clients.discard(peer)
        alive = getattr(self._conn, "clients_last_alive", None)
        if isinstance(alive, dict):
            alive.pop(peer, None)

    def _write(self, data: bytes) -> bool:
        result = self._conn.write(data)
        return not (isinstance(result, int) and result < 0)  # mavserial returns -1 for a dead port

    def _close(self) -> None:
        self._conn.close()


# ----- factory --------------------------------------------------------------------------------------

def _open_pymavlink(url: str, *, signing: SigningConfig | None = None, source_system: int = COMPANION_SYSTEM_ID,
                    source_component: int = COMPANION_COMPONENT_ID) -> MavlinkLink:
    return PymavlinkLink(url, source_system, source_component, signing=signing)


MAVLINK_BACKENDS: BackendRegistry[MavlinkLink] = BackendRegistry(
    "MAVLink link", credential="signing", policy=Credential.REQUIRED,
    unknown="unsupported MAVLink link scheme {scheme!r} in {url!r}")
"""Every `open_mavlink` scheme: pymavlink's transports, and what other layers (the SITL) register.
A link asked to sign that cannot is refused, never opened unsigned."""
for _scheme in ("serial", "udp", "udpin", "udpout", "tcp"):
    MAVLINK_BACKENDS.builtin(_scheme, _open_pymavlink, takes_credential=True, check=mavutil_device)


def register_mavlink_backend(scheme: str, factory: Callable[..., MavlinkLink]) -> None:
    """Let another layer (the SITL) provide `SCHEME:...` links without firmware_py importing it; a
    factory taking a `signing=` keyword can sign."""
    MAVLINK_BACKENDS.register(scheme, factory)


def unregister_mavlink_backend(scheme: str) -> None:
    """Remove a registered backend (tests); unknown schemes are ignored."""
    MAVLINK_BACKENDS.unregister(scheme)


def check_mavlink_url(url: str) -> None:
    """Refuse a malformed or unknown MAVLink URL without opening anything (ValueError naming it); a
    registered scheme's options are checked when it is opened."""
    if not isinstance(url, str):
        raise ValueError(f"MAVLink URL must be a string, got {url!r}")
    MAVLINK_BACKENDS.check(url)


def open_mavlink(url: str, source_system: int = COMPANION_SYSTEM_ID,
                 source_component: int = COMPANION_COMPONENT_ID, *,
                 signing: SigningConfig | None = None) -> MavlinkLink:
    """A MavlinkLink from its URL: a PymavlinkLink for the built-in schemes, else the registered
    backend of its scheme (ValueError naming the URL and the known schemes for an unknown one).

    With `signing`, a registered backend must take a `signing=` keyword (ValueError otherwise).
    """
    if not isinstance(url, str):
        raise ValueError(f"MAVLink URL must be a string, got {url!r}")
    return MAVLINK_BACKENDS.open(url, signing, source_system=source_system, source_component=source_component)
