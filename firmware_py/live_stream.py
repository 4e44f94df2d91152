"""Live sample stream to the ground station over UDP: fire and forget, never in the payload's way.

The sample log on the drone is the record; this stream is a preview (live coverage on the ground), so
the sender never blocks and never raises once open: a missing or slow ground station, a full socket
buffer or an unreachable network only increment counters.

Datagram (little-endian)::

    offset  size  field
    0       4     MAGIC = b"PSLV"
    4       1     version (1)
    5       1     flags (0; reserved)
    6       2     record count N, uint16
    8       4     sequence number, uint32 (one per datagram, wrapping)
    12      4     CRC32 of bytes 0-11 and the records (zlib.crc32)
    16      59*N  N raw SAMPLE_DTYPE records, as in the sample log

20 records per datagram (1196 bytes, under a 1400-byte path MTU with room for tunnels), i.e. 25
datagrams/s at 500 Hz. `LiveStreamReceiver` checks magic, version, length and CRC (a bad datagram is
counted and dropped, never raised), counts lost datagrams from sequence gaps, late/duplicate ones
that arrive behind the sequence, and sender restarts (back to 0, or a jump far backwards).
"""

from __future__ import annotations

import re
import socket
import struct
import zlib
from collections.abc import Iterable
from typing import Any

import numpy as np

from firmware_py.samplelog import SAMPLE_DTYPE, RecordBatcher, new_records

MAGIC = b"PSLV"
VERSION = 1
_HEAD = struct.Struct("<4sBBHI")  # magic, version, flags, count, seq
_CRC = struct.Struct("<I")
HEADER_SIZE = _HEAD.size + _CRC.size  # 16
MAX_DATAGRAM = 1400
MAX_RECORDS = (MAX_DATAGRAM - HEADER_SIZE) // SAMPLE_DTYPE.itemsize  # 23
DEFAULT_RECORDS = 20
RESTART_GAP = 1 << 16
"""A sequence number this far behind the expected one is a restarted sender, not a late datagram."""

_URL_RE = re.compile(r"udp:(?P<host>[^\s:]+|\[[0-9a-fA-F:.]+\]):(?P<port>\d{1,5})")
STREAM_URL_FORM = "udp:HOST:PORT"


def parse_stream_url(url: str, *, allow_port_zero: bool = False) -> tuple[str, int]:
    """(host, port) of `udp:HOST:PORT` (an IPv6 host in brackets); ValueError naming the URL otherwise."""
    m = _URL_RE.fullmatch(url.strip()) if isinstance(url, str) else None
    if m is None:
        raise ValueError(f"live stream URL must look like {STREAM_URL_FORM} (e.g. udp:192.168.1.10:14600), "
                         f"got {url!r}")
    port = int(m.group("port"))
    if not (0 if allow_port_zero else 1) <= port <= 65535:
        raise ValueError(f"live stream port {port} out of range in {url!r}")
    return m.group("host").strip("[]"), port


def encode_datagram(seq: int, records: np.ndarray) -> bytes:
    """One datagram carrying records (SAMPLE_DTYPE, at most MAX_RECORDS)."""
    recs = np.asarray(records)
    if recs.dtype != SAMPLE_DTYPE:
        raise TypeError(f"records must have dtype SAMPLE_DTYPE, got {recs.dtype}")
    recs = recs.reshape(-1)
    if len(recs) > MAX_RECORDS:
        raise ValueError(f"at most {MAX_RECORDS} records fit in one datagram, got {len(recs)}")
    head = _HEAD.pack(MAGIC, VERSION, 0, len(recs), seq & 0xFFFFFFFF)
    body = recs.tobytes()
    return head + _CRC.pack(zlib.crc32(body, zlib.crc32(head))) + body


def decode_datagram(data: bytes) -> tuple[int, np.ndarray]:
    """(sequence number, records) of a datagram; ValueError saying what is wrong with a malformed one."""
    data = bytes(data)
    if len(data) < HEADER_SIZE:
        raise ValueError(f"datagram of {len(data)} bytes is shorter than the {HEADER_SIZE}-byte header")
    magic, version, _flags, count, seq = _HEAD.unpack_from(data)
    if magic != MAGIC:
        raise ValueError(f"bad magic {magic!r}")
    if version != VERSION:
        raise ValueError(f"unsupported stream version {version}")
    if len(data) != HEADER_SIZE + count * SAMPLE_DTYPE.itemsize:
        raise ValueError(f"datagram of {len(data)} bytes does not hold the {count} records it declares")
    (crc,) = _CRC.unpack_from(data, _HEAD.size)
    if zlib.crc32(data[HEADER_SIZE:], zlib.crc32(data[:_HEAD.size])) != crc:
        raise ValueError("CRC mismatch")
    return seq, np.frombuffer(data, dtype=SAMPLE_DTYPE, offset=HEADER_SIZE, count=count).copy()


class LiveStreamSender:
    """Batches records into datagrams and sends them without blocking; failures are counted, not raised.

    Args:
        url: udp:HOST:PORT of the ground station's receiver.
        records_per_datagram: batch size, 1..MAX_RECORDS.
        sock: a socket to use instead of a new non-blocking UDP one (tests).

    Raises (only here, at start-up, where a bad --stream is the user's to fix):
        ValueError: a malformed URL, a bad batch size, or a host that does not resolve.
    """

    def __init__(self, url: str, records_per_datagram: int = DEFAULT_RECORDS, *, sock: Any = None) -> None:
        host, port = parse_stream_url(url)
        if isinstance(records_per_datagram, bool) or not isinstance(records_per_datagram, int) \
                or not 1 <= records_per_datagram <= MAX_RECORDS:
            raise ValueError(f"records per datagram must be 1-{MAX_RECORDS}, got {records_per_datagram!r}")
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except (OSError, UnicodeError) as exc:
            raise ValueError(f"live stream host {host!r} in {url!r} does not resolve: {exc}") from None
        family, _, _, _, addr = infos[0]
        self.url = url
        self.address = addr
        if sock is None:
            sock = socket.socket(family, socket.SOCK_DGRAM)
            sock.setblocking(False)
        self._sock = sock
        self._batch = RecordBatcher(records_per_datagram, self._send)
        self.seq = 0
        self.stats: dict[str, int] = {"datagrams": 0, "records": 0, "send_errors": 0, "records_dropped": 0}
        self.last_error: str | None = None
        self.closed = False

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

    def _send(self, batch: np.ndarray) -> None:
        n = len(batch)
        if self.closed:
            return
        data = encode_datagram(self.seq, batch)
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


class LiveStreamReceiver:
    """The ground end: parses datagrams into records, counts gaps and malformed datagrams.

    Args:
        url: udp:HOST:PORT to listen on (port 0 picks a free one; see `local_address`); None for a
            receiver that is only fed with `feed` (tests, a capture file).
    """

    def __init__(self, url: str | None = None) -> None:
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
                                      "restarts": 0}
        self.last_error: str | None = None

    @property
    def local_address(self) -> tuple[str, int]:
        if self._sock is None:
            raise ValueError("this receiver has no socket")
        return self._sock.getsockname()[:2]

    def feed(self, data: bytes) -> np.ndarray:
        """Records of one datagram (empty if it is malformed: counted in stats, never raised)."""
        try:
            seq, recs = decode_datagram(data)
        except ValueError as exc:
            self.stats["malformed"] += 1
            self.last_error = str(exc)
            return new_records(0)
        self._track(seq)
        self.stats["datagrams"] += 1
        self.stats["records"] += len(recs)
        return recs

    def feed_all(self, datagrams: Iterable[bytes]) -> np.ndarray:
        parts = [self.feed(d) for d in datagrams]
        return np.concatenate(parts) if parts else new_records(0)

    def poll(self, max_datagrams: int = 10_000) -> np.ndarray:
        """Every record received since the last poll (never blocks)."""
        if self._sock is None:
            raise ValueError("this receiver has no socket")
        got = []
        for _ in range(max_datagrams):
            try:
                data = self._sock.recv(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                self.last_error = f"{type(exc).__name__}: {exc}"
                break
            got.append(data)
        return self.feed_all(got)

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
