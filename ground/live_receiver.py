"""The ground end of the payload's live sample stream: datagrams in, records out, every loss counted.

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

Loss is counted PER SENDER (source address and, for version 2, sender id), and only as far as it is
plausible: a sender cannot have sent more datagrams than `max_rate_hz` (default: the payload's
highest loop rate, 2000 Hz, one record per datagram: no payload sends faster) allows over its
lifetime here, plus `LOSS_GRACE_S` of them for datagrams read in a burst. A forward sequence jump
beyond that budget is not a loss but a resync (`resyncs`; forged numbers, or a sender we missed
restarting): the tracking restarts at the new number. So forged sequence numbers cannot drive
`lost` to absurd values (one sender's jumps used to add up to 80,989,069,990,385 "lost" datagrams),
and another sender's numbers never make the payload's own stream look lossy. At most `MAX_SENDERS`
senders are tracked (the least recently heard is forgotten, `senders_evicted`).
"""

from __future__ import annotations

import ipaddress
import math
import socket
import time
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from firmware_py.core.keys import TIMESTAMP_UNITS_PER_S, signing_timestamp
from firmware_py.core.samplelog import new_records
from firmware_py.core.stream_format import (
    VERSION_AUTH,
    StreamAuthError,
    parse_stream_url,
    parse_with_tag_key,
    tag_key_for,
)

RESTART_GAP = 1 << 16
"""A sequence number this far behind the expected one is a restarted sender, not a late datagram."""
LATE_WINDOW_S = 2.0
"""An authenticated datagram may arrive this much (by stamp) behind the newest one and still be used."""
NEW_SENDER_MAX_AGE_S = 60.0
_MAX_RECENT_STAMPS = 4096
DEFAULT_MAX_RATE_HZ = 2000.0
"""The most datagrams a second a payload can send: its highest loop rate (2000 Hz), one record each."""
LOSS_GRACE_S = 1.0
"""Datagrams read together (a socket buffer drained at once) arrive closer than they were sent; a
second's worth of the rate is allowed on top of a sender's lifetime budget."""
MAX_SENDERS = 64
"""Senders whose sequence numbers are tracked at once (bounded memory under a flood of sources)."""


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


def _peer_key(peer: object) -> object:
    """A hashable sender address (None when the datagram came without one: `feed` by hand)."""
    if peer is None:
        return None
    try:
        return (str(peer[0]), int(peer[1]))
    except (TypeError, ValueError, IndexError):
        return repr(peer)


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


class _SeqTrack:
    """One sender's sequence numbers: the next expected, and the loss budget's bookkeeping."""

    __slots__ = ("expected", "first_t", "lost", "seen")

    def __init__(self, seq: int, t: float) -> None:
        self.expected = (seq + 1) & 0xFFFFFFFF
        self.first_t = t
        self.seen = 1
        self.lost = 0


SenderKey = tuple[object, int | None]


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
        max_rate_hz: the most datagrams a second a sender can send (the loss budget, module docstring).
        monotonic: the clock datagram arrivals are timed with (seconds).

    stats: datagrams, records, malformed; per-sender sequence accounting summed over senders: lost,
    late, restarts, resyncs (implausible jumps, not counted as lost); senders (tracked now),
    senders_evicted; datagrams refused: rejected_peer, unauthenticated, bad_tag, replayed;
    unverified counts authenticated datagrams a receiver without a key used unchecked.
    """

    def __init__(self, url: str | None = None, *, key: bytes | None = None,
                 allowed_peers: Iterable[PeerSpec] | None = None,
                 new_sender_max_age_s: float | None = NEW_SENDER_MAX_AGE_S,
                 clock: Callable[[], float] = time.time, max_rate_hz: float = DEFAULT_MAX_RATE_HZ,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        if isinstance(max_rate_hz, bool) or not isinstance(max_rate_hz, int | float) \
                or not (math.isfinite(max_rate_hz) and max_rate_hz > 0):
            raise ValueError(f"max datagram rate must be > 0 Hz, got {max_rate_hz!r}")
        self._max_rate_hz = float(max_rate_hz)
        self._monotonic = monotonic
        self._tracks: dict[SenderKey, _SeqTrack] = {}
        self._last_track: _SeqTrack | None = None
        self._tag_key = tag_key_for(key)
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
        self.stats: dict[str, int] = {"datagrams": 0, "records": 0, "malformed": 0, "lost": 0, "late": 0,
                                      "restarts": 0, "resyncs": 0, "senders": 0, "senders_evicted": 0,
                                      "rejected_peer": 0, "unauthenticated": 0, "bad_tag": 0,
                                      "replayed": 0, "unverified": 0}
        self.last_error: str | None = None

    @property
    def expected_seq(self) -> int | None:
        """The sequence number expected next from the sender heard last (None before any datagram)."""
        return None if self._last_track is None else self._last_track.expected

    def sender_losses(self) -> dict[SenderKey, tuple[int, int]]:
        """(datagrams taken, datagrams lost) per tracked sender (address, sender id or None)."""
        return {k: (t.seen, t.lost) for k, t in self._tracks.items()}

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
            d = parse_with_tag_key(data, self._tag_key)
        except StreamAuthError as exc:
            return self._refuse(exc.reason, str(exc))
        except ValueError as exc:
            return self._refuse("malformed", str(exc))
        if d.authenticated:
            if not self._fresh(d.sender_id, d.stamp):
                return self._refuse("replayed", f"replayed or stale datagram (sender {d.sender_id}, seq {d.seq})")
        elif d.version == VERSION_AUTH:
            self.stats["unverified"] += 1
        self._track((_peer_key(peer), d.sender_id), d.seq)
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

    def _track(self, sender: SenderKey, seq: int) -> None:
        """Sequence accounting for one sender (module docstring)."""
        now = self._monotonic()
        tracks = self._tracks
        track = tracks.pop(sender, None)
        if track is None:
            if len(tracks) >= MAX_SENDERS:
                del tracks[next(iter(tracks))]  # the least recently heard
                self.stats["senders_evicted"] += 1
            track = _SeqTrack(seq, now)
        else:
            self._advance(track, seq, now)
        tracks[sender] = track  # (re)inserted last: the dict's order is least to most recently heard
        self._last_track = track
        self.stats["senders"] = len(tracks)

    def _advance(self, track: _SeqTrack, seq: int, now: float) -> None:
        exp = track.expected
        track.seen += 1
        if seq == 0 and exp != 0:
            self.stats["restarts"] += 1  # a sender starts at 0 (a wrap takes years at 25 datagrams/s)
        else:
            ahead = (seq - exp) & 0xFFFFFFFF
            if ahead >= 1 << 31:  # behind the expected number
                behind = (1 << 32) - ahead
                if behind < RESTART_GAP:
                    self.stats["late"] += 1  # reordered or duplicated: its records are still used
                    return
                self.stats["restarts"] += 1
            elif ahead:
                budget = self._max_rate_hz * (now - track.first_t + LOSS_GRACE_S)
                if track.seen + track.lost + ahead <= budget:
                    track.lost += ahead
                    self.stats["lost"] += ahead
                else:
                    self.stats["resyncs"] += 1  # more than the sender could have sent: not a loss
        track.expected = (seq + 1) & 0xFFFFFFFF

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> LiveStreamReceiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
