"""Live sample stream to the ground station over UDP: fire and forget, never in the payload's way.

The sample log on the drone is the record; this stream is a preview (live coverage on the ground), so
the sender never blocks and never raises once open: a missing or slow ground station, a full socket
buffer or an unreachable network only increment counters.

Two datagram formats (little-endian). Version 1, unauthenticated (a sender without a key)::

    offset  size  field
    0       4     MAGIC = b"PSLV"
    4       1     version (1)
    5       1     flags (0; reserved)
    6       2     record count N, uint16
    8       4     sequence number, uint32 (one per datagram, wrapping)
    12      4     CRC32 of bytes 0-11 and the records (zlib.crc32)
    16      59*N  N raw SAMPLE_DTYPE records, as in the sample log

Version 2, authenticated (a sender with `key=`, e.g. `pilescan-payload --signing-key FILE`)::

    offset  size  field
    0       4     MAGIC = b"PSLV"
    4       1     version (2)
    5       1     flags (FLAG_AUTH = 0x01; other bits reserved, 0)
    6       2     record count N, uint16
    8       4     sequence number, uint32
    12      4     CRC32 of bytes 0-11, then bytes 16 .. 23+59*N (stamp, sender id, reserved, records)
    16      6     stamp, uint48: 10 us units since 2015-01-01 (the MAVLink signing clock), strictly
                  increasing per sender, never behind the sender's clock (`stamp_source`)
    22      1     sender id (0-255; one key may serve several senders)
    23      1     reserved (0)
    24      59*N  N raw SAMPLE_DTYPE records
    24+59*N 16    tag: HMAC-SHA256(K, bytes 0 .. 23+59*N), first 16 bytes, where
                  K = HMAC-SHA256(key, b"pilescan live stream v2") (the same 32-byte key as MAVLink
                  signing, separated from that use)

20 records per datagram (1196 bytes unkeyed, 1220 keyed; under a 1400-byte path MTU with room for
tunnels), i.e. 25 datagrams/s at 500 Hz. `LiveStreamReceiver` checks magic, version, length and CRC
(a bad datagram is counted and dropped, never raised), counts lost datagrams from sequence gaps,
late/duplicate ones that arrive behind the sequence, and sender restarts (back to 0, or a jump
far backwards).

A receiver with `key=` takes only version 2 datagrams whose tag checks out (an unauthenticated one
is counted in `unauthenticated`, a bad tag in `bad_tag`), and only fresh ones (`replayed`): per
sender id, a stamp must not have been seen before and must be within LATE_WINDOW_S of the newest
one (a datagram reordered by the network is still used); a sender's first stamp may be at most
`new_sender_max_age_s` (60 s) behind the receiver's clock, so a capture played back to a restarted
ground station is refused. The stamp, not the sequence number, guards against replay: a restarted
sender starts its sequence at 0 again but its stamps keep rising (its clock must not go back). A
receiver without a key takes both versions, without checking tags (`unverified` counts the
version 2 datagrams it could not check). `allowed_peers=[(host, port) or host, ...]` (names are
resolved once, at start) drops datagrams from any other address (`rejected_peer`), key or not.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import re
import socket
import struct
import time
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from firmware_py.hal.signing import KEY_SIZE, TIMESTAMP_MAX, TIMESTAMP_UNITS_PER_S, signing_timestamp
from firmware_py.samplelog import SAMPLE_DTYPE, RecordBatcher, new_records

MAGIC = b"PSLV"
VERSION = 1
"""Unauthenticated datagrams (a sender without a key)."""
VERSION_AUTH = 2
"""Authenticated datagrams: stamp, sender id and a 16-byte tag (module docstring)."""
FLAG_AUTH = 0x01
_HEAD = struct.Struct("<4sBBHI")  # magic, version, flags, count, seq
_CRC = struct.Struct("<I")
HEADER_SIZE = _HEAD.size + _CRC.size  # 16
_AUTH_EXT = 8  # stamp (6), sender id (1), reserved (1)
AUTH_HEADER_SIZE = HEADER_SIZE + _AUTH_EXT  # 24
TAG_SIZE = 16
MAX_DATAGRAM = 1400
MAX_RECORDS = (MAX_DATAGRAM - AUTH_HEADER_SIZE - TAG_SIZE) // SAMPLE_DTYPE.itemsize  # 23, either version
DEFAULT_RECORDS = 20
RESTART_GAP = 1 << 16
"""A sequence number this far behind the expected one is a restarted sender, not a late datagram."""
LATE_WINDOW_S = 2.0
"""An authenticated datagram may arrive this much (by stamp) behind the newest one and still be used."""
NEW_SENDER_MAX_AGE_S = 60.0
_TAG_KEY_LABEL = b"pilescan live stream v2"
_MAX_RECENT_STAMPS = 4096

_URL_RE = re.compile(r"udp:(?P<host>[^\s:]+|\[[0-9a-fA-F:.]+\]):(?P<port>\d{1,5})")
STREAM_URL_FORM = "udp:HOST:PORT"


class StreamAuthError(ValueError):
    """A well-formed datagram a keyed receiver refuses; reason is "unauthenticated" or "bad_tag"."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Datagram:
    """A parsed datagram. stamp and sender_id are None for version 1; authenticated means the tag
    was checked with a key (a keyless parse of version 2 leaves it False)."""

    seq: int
    records: np.ndarray
    version: int
    stamp: int | None = None
    sender_id: int | None = None
    authenticated: bool = False


def parse_stream_url(url: str, *, allow_port_zero: bool = False) -> tuple[str, int]:
    """(host, port) of `udp:HOST:PORT` (an IPv6 host in brackets); ValueError naming the URL otherwise."""
    m = _URL_RE.fullmatch(url.strip()) if isinstance(url, str) else None
    if m is None:
        raise ValueError(f"live stream URL must look like {STREAM_URL_FORM} (e.g. udp:192.168.1.10:14600), "
                         f"got {url!r}")
    port = int(m.group("port"))
    if not (0 if allow_port_zero else 1) <= port <= 65535:
        raise ValueError(f"live stream port {port} out of range in {url!r}")
    host = m.group("host").strip("[]")
    if not host:
        raise ValueError(f"live stream URL {url!r} has an empty host")
    return host, port


def _tag_key(key: bytes | None) -> bytes | None:
    """The HMAC key of the tags, derived from the 32-byte link key (kept apart from MAVLink signing)."""
    if key is None:
        return None
    if not isinstance(key, bytes | bytearray) or len(key) != KEY_SIZE:
        raise ValueError(f"live stream key must be {KEY_SIZE} bytes (firmware_py.hal.signing.load_key)")
    return hmac.new(bytes(key), _TAG_KEY_LABEL, hashlib.sha256).digest()


def _tag(tag_key: bytes, data: bytes) -> bytes:
    return hmac.new(tag_key, data, hashlib.sha256).digest()[:TAG_SIZE]


def _checked_records(records: np.ndarray) -> np.ndarray:
    recs = np.asarray(records)
    if recs.dtype != SAMPLE_DTYPE:
        raise TypeError(f"records must have dtype SAMPLE_DTYPE, got {recs.dtype}")
    recs = recs.reshape(-1)
    if len(recs) > MAX_RECORDS:
        raise ValueError(f"at most {MAX_RECORDS} records fit in one datagram, got {len(recs)}")
    return recs


def _encode(seq: int, recs: np.ndarray, tag_key: bytes | None, stamp: int, sender_id: int) -> bytes:
    body = recs.tobytes()
    if tag_key is None:
        head = _HEAD.pack(MAGIC, VERSION, 0, len(recs), seq & 0xFFFFFFFF)
        return head + _CRC.pack(zlib.crc32(body, zlib.crc32(head))) + body
    if isinstance(stamp, bool) or not isinstance(stamp, int) or not 0 <= stamp <= TIMESTAMP_MAX:
        raise ValueError(f"stamp must be an integer 0..2**48-1, got {stamp!r}")
    if isinstance(sender_id, bool) or not isinstance(sender_id, int) or not 0 <= sender_id <= 255:
        raise ValueError(f"sender id must be an integer 0-255, got {sender_id!r}")
    head = _HEAD.pack(MAGIC, VERSION_AUTH, FLAG_AUTH, len(recs), seq & 0xFFFFFFFF)
    ext = stamp.to_bytes(6, "little") + bytes((sender_id, 0))
    crc = zlib.crc32(body, zlib.crc32(ext, zlib.crc32(head)))
    data = head + _CRC.pack(crc) + ext + body
    return data + _tag(tag_key, data)


def encode_datagram(seq: int, records: np.ndarray, *, key: bytes | None = None, stamp: int = 0,
                    sender_id: int = 0) -> bytes:
    """One datagram carrying records (SAMPLE_DTYPE, at most MAX_RECORDS): version 1 without a key,
    version 2 (authenticated, with stamp and sender id) with one."""
    return _encode(seq, _checked_records(records), _tag_key(key), stamp, sender_id)


def _parse(data: bytes, tag_key: bytes | None) -> Datagram:
    data = bytes(data)
    if len(data) < HEADER_SIZE:
        raise ValueError(f"datagram of {len(data)} bytes is shorter than the {HEADER_SIZE}-byte header")
    magic, version, flags, count, seq = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise ValueError(f"bad magic {magic!r}")
    size = SAMPLE_DTYPE.itemsize
    (crc,) = _CRC.unpack_from(data, _HEAD.size)
    if version == VERSION:
        if len(data) != HEADER_SIZE + count * size:
            raise ValueError(f"datagram of {len(data)} bytes does not hold the {count} records it declares")
        if zlib.crc32(data[HEADER_SIZE:], zlib.crc32(data[:_HEAD.size])) != crc:
            raise ValueError("CRC mismatch")
        if tag_key is not None:
            raise StreamAuthError("unauthenticated", "unauthenticated datagram (stream version 1) refused: "
                                                     "this receiver has a key")
        return Datagram(seq, np.frombuffer(data, dtype=SAMPLE_DTYPE, offset=HEADER_SIZE, count=count).copy(), VERSION)
    if version != VERSION_AUTH:
        raise ValueError(f"unsupported stream version {version}")
    if flags != FLAG_AUTH:
        raise ValueError(f"bad flags 0x{flags:02x} in an authenticated datagram")
    end = AUTH_HEADER_SIZE + count * size
    if len(data) != end + TAG_SIZE:
        raise ValueError(f"datagram of {len(data)} bytes does not hold the {count} records it declares")
    if tag_key is not None and not hmac.compare_digest(_tag(tag_key, data[:end]), data[end:]):
        raise StreamAuthError("bad_tag", "datagram with a bad authentication tag refused (forged, corrupt, "
                                         "or sent with another key)")
    if zlib.crc32(data[HEADER_SIZE:end], zlib.crc32(data[:_HEAD.size])) != crc:
        raise ValueError("CRC mismatch")
    stamp = int.from_bytes(data[HEADER_SIZE:HEADER_SIZE + 6], "little")
    recs = np.frombuffer(data, dtype=SAMPLE_DTYPE, offset=AUTH_HEADER_SIZE, count=count).copy()
    return Datagram(seq, recs, VERSION_AUTH, stamp, data[HEADER_SIZE + 6], tag_key is not None)


def parse_datagram(data: bytes, *, key: bytes | None = None) -> Datagram:
    """A datagram's fields; ValueError saying what is wrong with a malformed one, and with a key,
    StreamAuthError (a ValueError) for one that is unauthenticated or fails its tag."""
    return _parse(data, _tag_key(key))


def decode_datagram(data: bytes, *, key: bytes | None = None) -> tuple[int, np.ndarray]:
    """(sequence number, records) of a datagram; ValueError as `parse_datagram` (no replay check)."""
    d = parse_datagram(data, key=key)
    return d.seq, d.records


class LiveStreamSender:
    """Batches records into datagrams and sends them without blocking; failures are counted, not raised.

    Args:
        url: udp:HOST:PORT of the ground station's receiver.
        records_per_datagram: batch size, 1..MAX_RECORDS.
        sock: a socket to use instead of a new non-blocking UDP one (tests).
        key: the 32-byte link key: send authenticated (version 2) datagrams; None: version 1.
        sender_id: 0-255, tells senders sharing a key apart (replay state is kept per sender id).
        stamp_source: the MAVLink signing clock (10 us units since 2015) the stamps follow, e.g. the
            MAVLink link's `signer.now` (so a companion without a real-time clock follows its
            autopilot); default: the wall clock. Stamps strictly increase whatever it returns.

    Raises (only here, at start-up, where a bad --stream is the user's to fix):
        ValueError: a malformed URL, a bad batch size or key, or a host that does not resolve.
    """

    def __init__(self, url: str, records_per_datagram: int = DEFAULT_RECORDS, *, sock: Any = None,
                 key: bytes | None = None, sender_id: int = 0,
                 stamp_source: Callable[[], int] | None = None) -> None:
        host, port = parse_stream_url(url)
        if isinstance(records_per_datagram, bool) or not isinstance(records_per_datagram, int) \
                or not 1 <= records_per_datagram <= MAX_RECORDS:
            raise ValueError(f"records per datagram must be 1-{MAX_RECORDS}, got {records_per_datagram!r}")
        self._tag_key = _tag_key(key)
        if isinstance(sender_id, bool) or not isinstance(sender_id, int) or not 0 <= sender_id <= 255:
            raise ValueError(f"sender id must be an integer 0-255, got {sender_id!r}")
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except (OSError, UnicodeError) as exc:
            raise ValueError(f"live stream host {host!r} in {url!r} does not resolve: {exc}") from None
        family, _, _, _, addr = infos[0]
        self.url = url
        self.address = addr
        self.sender_id = sender_id
        self._stamp_source = stamp_source or (lambda: signing_timestamp(time.time()))
        self._last_stamp = -1
        if sock is None:
            sock = socket.socket(family, socket.SOCK_DGRAM)
            sock.setblocking(False)
        self._sock = sock
        self._batch = RecordBatcher(records_per_datagram, self._send)
        self.seq = 0
        self.stats: dict[str, int] = {"datagrams": 0, "records": 0, "send_errors": 0, "records_dropped": 0}
        self.last_error: str | None = None
        self.closed = False

    @property
    def authenticated(self) -> bool:
        """Whether the datagrams carry an authentication tag (a key was given)."""
        return self._tag_key is not None

    def append(self, records: np.ndarray | np.void) -> None:
        """Queue records; every full batch goes out at once. Never raises for network trouble."""
        recs = np.asarray(records)
        self._batch.add(recs if recs.ndim == 0 else recs.reshape(-1))

    def flush(self) -> None:
        """Send a partial batch now (the payload does this every second, so a slow rate still streams)."""
        self._batch.flush()

    def close(self) -> None:
        if self.closed:
            return
        self.flush()
        self.closed = True
        try:
            self._sock.close()
        except OSError:
            pass

    def _next_stamp(self) -> int:
        stamp = min(max(self._last_stamp + 1, int(self._stamp_source())), TIMESTAMP_MAX)
        self._last_stamp = stamp
        return stamp

    def _send(self, batch: np.ndarray) -> None:
        n = len(batch)
        if self.closed:
            return
        recs = _checked_records(batch)
        stamp = self._next_stamp() if self._tag_key is not None else 0
        data = _encode(self.seq, recs, self._tag_key, stamp, self.sender_id)
        self.seq = (self.seq + 1) & 0xFFFFFFFF  # a lost datagram still uses its number: the receiver sees the gap
        try:
            self._sock.sendto(data, self.address)
        except OSError as exc:  # BlockingIOError (buffer full), ECONNREFUSED, ENETUNREACH, ...
            self.stats["send_errors"] += 1
            self.stats["records_dropped"] += n
            self.last_error = f"{type(exc).__name__}: {exc}"
            return
        self.stats["datagrams"] += 1
        self.stats["records"] += n


PeerSpec = str | tuple[str, int]


def _normal_ip(host: str) -> str:
    ip = ipaddress.ip_address(host.split("%", 1)[0])
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return str(ip)


def _resolve_host(host: str) -> set[str]:
    if not isinstance(host, str) or not host.strip():
        raise ValueError(f"allowed peer host must be a non-empty string, got {host!r}")
    host = host.strip().strip("[]")
    try:
        return {_normal_ip(host)}
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_DGRAM)
    except (OSError, UnicodeError) as exc:
        raise ValueError(f"allowed peer {host!r} does not resolve: {exc}") from None
    return {_normal_ip(info[4][0]) for info in infos}


def _resolve_peers(peers: Iterable[PeerSpec]) -> tuple[set[tuple[str, int]], set[str]]:
    exact: set[tuple[str, int]] = set()
    hosts: set[str] = set()
    if isinstance(peers, str | bytes) or (isinstance(peers, tuple) and len(peers) == 2 and isinstance(peers[1], int)):
        raise ValueError("allowed_peers must be a list of (host, port) pairs or host names")
    for peer in peers:
        if isinstance(peer, str):
            hosts |= _resolve_host(peer)
            continue
        if not (isinstance(peer, Sequence) and len(peer) == 2):
            raise ValueError(f"allowed peer must be (host, port) or host, got {peer!r}")
        host, port = peer
        if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
            raise ValueError(f"allowed peer port must be 1-65535, got {port!r}")
        exact |= {(ip, port) for ip in _resolve_host(host)}
    return exact, hosts


class _ReplayWindow:
    """Stamps accepted from one sender: a stamp is fresh if unseen and within the window of the newest."""

    def __init__(self, window: int) -> None:
        self.window = window
        self.newest = -1
        self.floor = -1  # stamps at or below this are refused
        self.recent: set[int] = set()

    def accept(self, stamp: int) -> bool:
        if stamp <= self.floor or stamp in self.recent:
            return False
        self.recent.add(stamp)
        self.newest = max(self.newest, stamp)
        self.floor = max(self.floor, self.newest - self.window)
        if len(self.recent) > 64:
            self.recent = {s for s in self.recent if s > self.floor}
            if len(self.recent) > _MAX_RECENT_STAMPS:  # a flood within the window: keep the newest
                keep = sorted(self.recent)[-_MAX_RECENT_STAMPS:]
                self.floor = max(self.floor, keep[0] - 1)
                self.recent = set(keep)
        return True


class LiveStreamReceiver:
    """The ground end: parses datagrams into records, counts gaps and malformed datagrams.

    Args:
        url: udp:HOST:PORT to listen on (port 0 picks a free one; see `local_address`); None for a
            receiver that is only fed with `feed` (tests, a capture file).
        key: the 32-byte link key: accept only authenticated, fresh datagrams (module docstring).
        allowed_peers: accept datagrams only from these senders, each (host, port) or a host (any
            port); names are resolved now (ValueError if they do not). None: from anyone. With it
            set, `feed` without a peer refuses the datagram.
        new_sender_max_age_s: how far a sender's first stamp may lag our clock (None: no limit).
        clock: the wall clock (Unix seconds) for that check.

    stats: datagrams, records, malformed, lost, late, restarts (sequence numbers, as before), and
    datagrams refused: rejected_peer, unauthenticated, bad_tag, replayed; unverified counts
    authenticated datagrams a receiver without a key used unchecked.
    """

    def __init__(self, url: str | None = None, *, key: bytes | None = None,
                 allowed_peers: Iterable[PeerSpec] | None = None,
                 new_sender_max_age_s: float | None = NEW_SENDER_MAX_AGE_S,
                 clock: Callable[[], float] = time.time) -> None:
        self._tag_key = _tag_key(key)
        self._allowed = _resolve_peers(allowed_peers) if allowed_peers is not None else None
        if new_sender_max_age_s is not None and not new_sender_max_age_s >= 0:
            raise ValueError(f"new sender max age must be >= 0 s, got {new_sender_max_age_s!r}")
        self._new_sender_max_age = (None if new_sender_max_age_s is None
                                    else round(new_sender_max_age_s * TIMESTAMP_UNITS_PER_S))
        self._clock = clock
        self._senders: dict[int, _ReplayWindow] = {}
        self._newest_stamp = 0
        self._sock: socket.socket | None = None
        if url is not None:
            host, port = parse_stream_url(url, allow_port_zero=True)
            family = socket.AF_INET6 if ":" in host else socket.AF_INET
            sock = socket.socket(family, socket.SOCK_DGRAM)
            try:
                sock.bind((host, port))
            except OSError:
                sock.close()
                raise
            sock.setblocking(False)
            self._sock = sock
        self.expected_seq: int | None = None
        self.stats: dict[str, int] = {"datagrams": 0, "records": 0, "malformed": 0, "lost": 0, "late": 0,
                                      "restarts": 0, "rejected_peer": 0, "unauthenticated": 0, "bad_tag": 0,
                                      "replayed": 0, "unverified": 0}
        self.last_error: str | None = None

    @property
    def authenticated(self) -> bool:
        """Whether this receiver has a key (takes only authenticated datagrams)."""
        return self._tag_key is not None

    @property
    def local_address(self) -> tuple[str, int]:
        if self._sock is None:
            raise ValueError("this receiver has no socket")
        return self._sock.getsockname()[:2]

    def fileno(self) -> int:
        """The socket's descriptor, so a caller can wait for datagrams (select) instead of spinning on poll."""
        if self._sock is None:
            raise ValueError("this receiver has no socket")
        return self._sock.fileno()

    def feed(self, data: bytes, peer: tuple[str, int] | None = None) -> np.ndarray:
        """Records of one datagram from peer (empty if refused or malformed: counted, never raised)."""
        if self._allowed is not None and not self._peer_allowed(peer):
            return self._refuse("rejected_peer", f"datagram from {peer!r}, not an allowed peer")
        try:
            d = _parse(data, self._tag_key)
        except StreamAuthError as exc:
            return self._refuse(exc.reason, str(exc))
        except ValueError as exc:
            return self._refuse("malformed", str(exc))
        if d.authenticated:
            if not self._fresh(d.sender_id, d.stamp):
                return self._refuse("replayed", f"replayed or stale datagram (sender {d.sender_id}, seq {d.seq})")
        elif d.version == VERSION_AUTH:
            self.stats["unverified"] += 1
        self._track(d.seq)
        self.stats["datagrams"] += 1
        self.stats["records"] += len(d.records)
        return d.records

    def feed_all(self, datagrams: Iterable[bytes]) -> np.ndarray:
        parts = [self.feed(d) for d in datagrams]
        return np.concatenate(parts) if parts else new_records(0)

    def poll(self, max_datagrams: int = 10_000) -> np.ndarray:
        """Every record received since the last poll (never blocks)."""
        if self._sock is None:
            raise ValueError("this receiver has no socket")
        parts = []
        for _ in range(max_datagrams):
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                self.last_error = f"{type(exc).__name__}: {exc}"
                break
            parts.append(self.feed(data, addr[:2]))
        return np.concatenate(parts) if parts else new_records(0)

    def _refuse(self, reason: str, message: str) -> np.ndarray:
        self.stats[reason] += 1
        self.last_error = message
        return new_records(0)

    def _peer_allowed(self, peer: tuple[str, int] | None) -> bool:
        if peer is None:
            return False
        try:
            ip, port = _normal_ip(str(peer[0])), int(peer[1])
        except (ValueError, TypeError, IndexError):
            return False
        exact, hosts = self._allowed
        return ip in hosts or (ip, port) in exact

    def _fresh(self, sender_id: int, stamp: int) -> bool:
        window = self._senders.get(sender_id)
        if window is None:
            now = max(self._newest_stamp, signing_timestamp(self._clock()))
            if self._new_sender_max_age is not None and stamp + self._new_sender_max_age < now:
                return False  # a new sender, but its stamp is old: a capture played back
            window = self._senders[sender_id] = _ReplayWindow(round(LATE_WINDOW_S * TIMESTAMP_UNITS_PER_S))
        if not window.accept(stamp):
            return False
        self._newest_stamp = max(self._newest_stamp, stamp)
        return True

    def _track(self, seq: int) -> None:
        exp = self.expected_seq
        if exp is not None and seq == 0 and exp != 0:
            self.stats["restarts"] += 1  # a new sender starts at 0 (a wrap takes years at 25 datagrams/s)
        elif exp is not None:
            ahead = (seq - exp) & 0xFFFFFFFF
            if ahead >= 1 << 31:  # behind the expected number
                behind = (1 << 32) - ahead
                if behind < RESTART_GAP:
                    self.stats["late"] += 1  # reordered or duplicated: its records are still used
                    return
                self.stats["restarts"] += 1
            else:
                self.stats["lost"] += ahead
        self.expected_seq = (seq + 1) & 0xFFFFFFFF

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> LiveStreamReceiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
