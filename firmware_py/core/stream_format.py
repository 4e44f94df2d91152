"""The live sample stream's wire format: what the payload sends and the ground station parses.

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
(a bad datagram is counted and dropped, never raised) and, per sender, counts lost datagrams from
sequence gaps (only as many as the sender could have sent: a larger jump is a resync, so forged
numbers cannot inflate the loss), late/duplicate ones that arrive behind the sequence, and sender
restarts (back to 0, or a jump far backwards). A sender numbers its datagrams from 0 when it starts,
so a receiver whose first datagram from it is number N knows N were sent before it listened
(`ground.listen`'s "joined at datagram N"); the records carry no index of their own.

`encode_datagram` / `parse_datagram` are the whole contract; the sender (`firmware_py.live_stream`)
and the receiver (`ground.live_receiver`) add batching, counters, replay and peer checks.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from firmware_py.core.keys import KEY_SIZE, TIMESTAMP_MAX
from firmware_py.core.samplelog import SAMPLE_DTYPE

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
_TAG_KEY_LABEL = b"pilescan live stream v2"

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


def tag_key_for(key: bytes | None) -> bytes | None:
    """The HMAC key of the tags, derived from the 32-byte link key (kept apart from MAVLink signing)."""
    if key is None:
        return None
    if not isinstance(key, bytes | bytearray) or len(key) != KEY_SIZE:
        raise ValueError(f"live stream key must be {KEY_SIZE} bytes (firmware_py.core.keys.load_key)")
    return hmac.new(bytes(key), _TAG_KEY_LABEL, hashlib.sha256).digest()


def _tag(tag_key: bytes, data: bytes) -> bytes:
    return hmac.new(tag_key, data, hashlib.sha256).digest()[:TAG_SIZE]


def checked_records(records: np.ndarray) -> np.ndarray:
    recs = np.asarray(records)
    if recs.dtype != SAMPLE_DTYPE:
        raise TypeError(f"records must have dtype SAMPLE_DTYPE, got {recs.dtype}")
    recs = recs.reshape(-1)
    if len(recs) > MAX_RECORDS:
        raise ValueError(f"at most {MAX_RECORDS} records fit in one datagram, got {len(recs)}")
    return recs


def encode_with_tag_key(seq: int, recs: np.ndarray, tag_key: bytes | None, stamp: int, sender_id: int) -> bytes:
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
    return encode_with_tag_key(seq, checked_records(records), tag_key_for(key), stamp, sender_id)


def parse_with_tag_key(data: bytes, tag_key: bytes | None) -> Datagram:
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
    return parse_with_tag_key(data, tag_key_for(key))


def decode_datagram(data: bytes, *, key: bytes | None = None) -> tuple[int, np.ndarray]:
    """(sequence number, records) of a datagram; ValueError as `parse_datagram` (no replay check)."""
    d = parse_datagram(data, key=key)
    return d.seq, d.records
