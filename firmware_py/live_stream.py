"""Live sample stream to the ground station over UDP: fire and forget, never in the payload's way.

The sample log on the drone is the record; this stream is a preview (live coverage on the ground), so
the sender never blocks and never raises once open: a missing or slow ground station, a full socket
buffer or an unreachable network only increment counters.

The datagram format is `firmware_py.core.stream_format`; the ground end is `ground.live_receiver`.
UDP keeps no history: what is sent before the ground station listens is gone. The datagrams are
numbered from 0 from the sender's start, listened to or not, so a receiver that joins late knows how
many it never had (`ground.listen`, "joined at datagram N").
"""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from firmware_py.core.keys import TIMESTAMP_MAX, signing_timestamp
from firmware_py.core.samplelog import RecordBatcher
from firmware_py.core.stream_format import (
    DEFAULT_RECORDS,
    MAX_RECORDS,
    checked_records,
    encode_with_tag_key,
    parse_stream_url,
    tag_key_for,
)


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
        self._tag_key = tag_key_for(key)
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
        recs = checked_records(batch)
        stamp = self._next_stamp() if self._tag_key is not None else 0
        data = encode_with_tag_key(self.seq, recs, self._tag_key, stamp, self.sender_id)
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
