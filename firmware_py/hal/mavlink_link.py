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
Without a key, signed frames from others are delivered without a check.

UDP links (udp:/udpin:/udpout:) parse each datagram on its own (`MavlinkFramer.feed_datagram`): a
datagram is whole frames or nothing, so bytes never carry over from one datagram (or one sender)
to the next. A truncated frame, a header claiming more bytes than arrived, garbage, a bad CRC: the
datagram's rest is dropped and counted (`rx_truncated`, `rx_bad_bytes`, `rx_bad_frames`), and the
next datagram is parsed from its first byte. (The old design fed every datagram from every sender
into one stream buffer: one 10-byte datagram whose header claimed 255 bytes held back every later
frame until 267 more bytes had come.) Sequence gaps are counted per (sender address, system,
component), in a table of at most `MAX_SEQ_STREAMS` entries (the least recently heard one goes).

Peers. A listening link (udp:HOST:PORT) answers only senders it has ADMITTED, and admits a sender
only when one of its datagrams held a valid frame (CRC-checked, of a known message, and with a key,
correctly signed and fresh): random bytes, truncated headers and bad CRCs never make us send to
their source (no reflector). At most `max_peers` are kept (default `DEFAULT_MAX_PEERS`); a peer
with no valid frame for `peer_timeout_s` (default 5 s: five missed 1 Hz heartbeats, MAVLink's
usual link-lost rule) may be replaced by a new one, and while every place is held by a live peer,
new senders are refused (`rx_peers_refused`): a live autopilot is never pushed out. A sending link
(udpout:HOST:PORT) takes datagrams only from HOST:PORT; others are dropped and counted
(`rx_foreign`).

The companion's 1 Hz HEARTBEAT is the caller's job (`heartbeat_msg()`); the pose tracker sends it.
"""

from __future__ import annotations

import math
import re
import socket
import time
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

_UDP_MAX_DATAGRAM = 65_535
"""The largest UDP payload: a datagram is read whole (a short read would cut its frames)."""

MAX_SEQ_STREAMS = 64
"""Sequence-gap state kept for at most this many (sender, system, component) streams."""

DEFAULT_MAX_PEERS = 4
"""Peers a listening UDP link answers: the autopilot, or a router, and a few spare places."""

DEFAULT_PEER_TIMEOUT_S = 5.0
"""A peer silent (no valid frame) this long may give its place to a new one: 5 missed 1 Hz heartbeats."""


def heartbeat_msg() -> Any:
    """The companion's HEARTBEAT (MAV_TYPE_ONBOARD_CONTROLLER, no autopilot); send it at 1 Hz."""
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3)


# ----- framing ------------------------------------------------------------------------------------

def decode_frame(mav: mavlink.MAVLink, frame: bytes | bytearray) -> Any | None:
    """One whole frame decoded and CRC-checked by pymavlink; None for anything that is not a message
    of the dialect (a failed CRC, an unknown id, hostile bytes: pymavlink raises MAVError and struct /
    Unicode errors on those, or hands back MAVLink_unknown / MAVLink_bad_data)."""
    try:
        msg = mav.decode(bytearray(frame))
    except Exception:
        return None
    if isinstance(msg, mavlink.MAVLink_unknown | mavlink.MAVLink_bad_data):
        return None
    return msg


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
        self._last_seq: dict[tuple[Any, int, int], int] = {}
        self._sender: Any = None
        self.bad_bytes = 0
        self.bad_frames = 0
        self.truncated = 0
        self.seq_lost = 0

    def feed_datagram(self, data: bytes | bytearray, sender: Any = None) -> list[Any]:
        """Every valid frame in ONE datagram, in order; nothing is kept for the next datagram.

        Bytes that do not form a whole frame (garbage, a bad CRC) are skipped as in a stream; a
        frame cut short by the datagram's end is dropped and counted in `truncated` (its bytes in
        bad_bytes). `sender` (e.g. the source address) keeps sequence gaps apart per sender."""
        if self._buf:
            raise ValueError("feed_datagram on a framer holding stream bytes: use one framer per mode")
        self._sender = sender
        try:
            out = self.feed(data)
        finally:
            if self._buf:
                self.truncated += 1
                self.bad_bytes += len(self._buf)
                self._buf.clear()
            self._sender = None
        return out

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
        """Whole frame length from the header at i; None if incomplete, 0 if the header is impossible.

        Impossible: unknown incompatibility flags, a message id outside the dialect, or a payload
        longer than that message's. Checked on the header alone, so such a header costs one byte at
        once instead of holding the bytes behind it until its claimed length has arrived."""
        buf = self._buf
        n = len(buf) - i
        if buf[i] == self._MAGIC_V1:
            if n < 6:
                return None
            length, msg_id, total = buf[i + 1], buf[i + 5], 6 + buf[i + 1] + 2
        else:
            if n < 10:
                return None
            flags = buf[i + 2]
            if flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
                return 0
            length = buf[i + 1]
            msg_id = buf[i + 7] | buf[i + 8] << 8 | buf[i + 9] << 16
            total = 10 + length + 2 + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if flags else 0)
        cls = mavlink.mavlink_map.get(msg_id)
        if cls is None or length > cls.unpacker.size:
            return 0
        return total

    def _decode(self, frame: bytearray) -> Any | None:
        return decode_frame(self._mav, frame)

    def _count_seq(self, msg: Any) -> None:
        """Sequence gaps per sender: frames lost on the wire (a jump over half the range is a reorder).

        Keyed by (sender, system, component), at most MAX_SEQ_STREAMS of them (least recently heard
        dropped), so another sender's frames cannot make one stream's numbers jump."""
        key = (self._sender, msg.get_srcSystem(), msg.get_srcComponent())
        seq = msg.get_seq()
        last = self._last_seq.pop(key, None)
        if last is not None:
            gap = (seq - last - 1) % 256
            if gap < 128:
                self.seq_lost += gap
        elif len(self._last_seq) >= MAX_SEQ_STREAMS:
            del self._last_seq[next(iter(self._last_seq))]
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
            "rx_datagrams": 0, "rx_truncated": 0, "rx_foreign": 0, "rx_peers_refused": 0,
            "tx_messages": 0, "tx_errors": 0, "io_errors": 0,
            **{name: 0 for name, _ in _SIGNING_STATS},
        }
        self._datagrams = False
        """Parse each chunk on its own (UDP: a datagram is whole frames or nothing), else as a stream."""
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
            for chunk, sender in self._read_chunks():
                got = True
                self.stats["rx_bytes"] += len(chunk)
                if self._datagrams:
                    self.stats["rx_datagrams"] += 1
                    msgs = self._framer.feed_datagram(chunk, sender)
                    self._heard(sender, msgs)
                else:
                    msgs = self._framer.feed(chunk)
                out.extend(msgs)
        except OSError as exc:
            self._io_error(exc)
        if not got:
            return out  # the usual case at 500 Hz: nothing new, no bookkeeping
        f = self._framer
        self.stats["rx_messages"] += len(out)
        self.stats["rx_bad_bytes"] = f.bad_bytes
        self.stats["rx_bad_frames"] = f.bad_frames
        self.stats["rx_truncated"] = f.truncated
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
        """Chunks read now, each with its sender (a UDP datagram's source address) or None."""
        raise NotImplementedError

    def _heard(self, sender: Any, msgs: list[Any]) -> None:
        """A datagram from sender held msgs (valid, authenticated with a key); admit peers here."""

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
    `signing`: sign and check (module docstring). On UDP, datagrams are read from the socket with
    their source address and parsed one by one; `max_peers` / `peer_timeout_s` bound whom a
    listening link answers (module docstring).
    """

    def __init__(self, url: str, source_system: int = COMPANION_SYSTEM_ID,
                 source_component: int = COMPANION_COMPONENT_ID, *,
                 connect: Callable[..., Any] | None = None,
                 signing: SigningConfig | MavlinkSigner | None = None,
                 max_peers: int = DEFAULT_MAX_PEERS, peer_timeout_s: float = DEFAULT_PEER_TIMEOUT_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(source_system, source_component, signing)
        if isinstance(max_peers, bool) or not isinstance(max_peers, int) or not 1 <= max_peers <= 256:
            raise ValueError(f"max_peers must be an integer 1-256, got {max_peers!r}")
        if not (isinstance(peer_timeout_s, int | float) and math.isfinite(peer_timeout_s) and peer_timeout_s > 0):
            raise ValueError(f"peer timeout must be > 0 s, got {peer_timeout_s!r}")
        self.url = url
        device, baud = mavutil_device(url)
        self._max_peers, self._peer_timeout_s, self._clock = max_peers, float(peer_timeout_s), clock
        self._peers: dict[Any, float] = {}  # admitted sender -> when its last valid frame came
        self._server = device.startswith("udpin:")
        self._datagrams = self._server or device.startswith("udpout:")
        self._only_from = _resolved(device[len("udpout:"):]) if device.startswith("udpout:") else None
        if connect is None:
            from pymavlink import mavutil  # late: a heavy import only real links need
            connect = mavutil.mavlink_connection
        kwargs: dict[str, Any] = {"source_system": source_system, "source_component": source_component}
        if baud:
            kwargs["baud"] = baud
        self._conn = connect(device, **kwargs)
        if self._server:
            self._conn.timeout = 0  # mavutil must not prune our peers: we do (see _heard)
            self._sync_clients()
        if device.startswith("udpout:"):
            self.send(heartbeat_msg())  # a udp-listening autopilot replies to whoever spoke last

    @property
    def local_address(self) -> tuple[str, int] | None:
        """Bound (host, port) of a UDP/TCP link (e.g. after udp:127.0.0.1:0), None for serial."""
        sock = getattr(self._conn, "port", None)
        getsockname = getattr(sock, "getsockname", None)
        return getsockname() if getsockname is not None else None

    @property
    def peers(self) -> list[Any]:
        """The senders a listening UDP link answers (admitted on a valid frame), oldest first."""
        return list(self._peers)

    def _read_chunks(self) -> list[tuple[bytes, Any]]:
        if self._datagrams:
            return self._read_datagrams()
        chunks = []
        for _ in range(_MAX_READS_PER_RECV):
            try:
                data = self._conn.recv(_READ_CHUNK)
            except OSError as exc:  # keep what was read before the error
                self._io_error(exc)
                break
            if not data:  # mavutil returns "" (a str) when a socket has nothing
                break
            chunks.append((bytes(data), None))
        return chunks

    def _read_datagrams(self) -> list[tuple[bytes, Any]]:
        """Whole datagrams with their source, straight from mavutil's socket (its recv() would add
        every source to the addresses it answers); a connection without a socket (tests) hands out
        one datagram per recv(), source unknown."""
        sock = getattr(self._conn, "port", None)
        recvfrom = getattr(sock, "recvfrom", None)
        chunks = []
        for _ in range(_MAX_READS_PER_RECV):
            try:
                if recvfrom is not None:
                    data, sender = recvfrom(_UDP_MAX_DATAGRAM)
                else:
                    data, sender = self._conn.recv(_UDP_MAX_DATAGRAM), None
            except (BlockingIOError, InterruptedError):
                break
            except ConnectionRefusedError:
                continue  # an earlier datagram found no listener (ICMP): not this read's failure
            except OSError as exc:  # keep what was read
                self._io_error(exc)
                break
            if not data:
                if recvfrom is None:
                    break
                continue  # an empty datagram
            if sender is not None and self._only_from is not None and not _same_address(sender, self._only_from):
                self.stats["rx_foreign"] += 1
                continue
            chunks.append((bytes(data), sender))
        return chunks

    def _heard(self, sender: Any, msgs: list[Any]) -> None:
        if not self._server or sender is None or not msgs:
            return  # only a valid (with a key: authenticated) frame admits a peer
        now = self._clock()
        if sender in self._peers:
            self._peers[sender] = now
            return
        if len(self._peers) >= self._max_peers:
            stalest = min(self._peers, key=self._peers.__getitem__)
            if now - self._peers[stalest] < self._peer_timeout_s:
                self.stats["rx_peers_refused"] += 1  # every place held by a live peer: it stays
                return
            del self._peers[stalest]
        self._peers[sender] = now
        self._sync_clients()

    def _sync_clients(self) -> None:
        """mavutil's listening socket writes to its `clients`: make them exactly our peers."""
        clients = getattr(self._conn, "clients", None)
        if isinstance(clients, set):
            clients.clear()
            clients.update(self._peers)
        alive = getattr(self._conn, "clients_last_alive", None)
        if isinstance(alive, dict):
            alive.clear()
            alive.update(dict.fromkeys(self._peers, time.time()))

    def _write(self, data: bytes) -> bool:
        result = self._conn.write(data)
        return not (isinstance(result, int) and result < 0)  # mavserial returns -1 for a dead port

    def _close(self) -> None:
        self._conn.close()


def _resolved(host_port: str) -> tuple[str, int] | None:
    """(IP, port) a udpout link sends to; None if the name does not resolve (then nothing is filtered:
    mavutil reports the failure when it sends)."""
    host, _, port = host_port.rpartition(":")
    try:
        infos = socket.getaddrinfo(host, int(port), socket.AF_INET, socket.SOCK_DGRAM)
    except (OSError, UnicodeError, ValueError):
        return None
    return infos[0][4][:2] if infos else None


def _same_address(a: Any, b: tuple[str, int]) -> bool:
    try:
        return a[1] == b[1] and a[0] == b[0]
    except (TypeError, IndexError):
        return False


# ----- factory --------------------------------------------------------------------------------------

def _open_pymavlink(url: str, *, signing: SigningConfig | None = None, source_system: int = COMPANION_SYSTEM_ID,
                    source_component: int = COMPANION_COMPONENT_ID) -> MavlinkLink:
    return PymavlinkLink(url, source_system, source_component, signing=signing)


MAVLINK_BACKENDS: BackendRegistry[MavlinkLink] = BackendRegistry(
    "MAVLink link", credential="signing", policy=Credential.REQUIRED,
    unknown="unsupported MAVLink link scheme {scheme!r} in {url!r}",
    expected="serial:/dev/ttyAMA0:921600, udp:HOST:PORT, udpout:HOST:PORT or tcp:HOST:PORT")
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
    if not isinstance(url, str) or not url.strip():
        raise ValueError(f"MAVLink URL must be a non-empty string like serial:/dev/ttyAMA0:921600 or "
                         f"udp:HOST:PORT, got {url!r}")
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
