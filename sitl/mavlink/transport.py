"""Byte links for the MAVLink server: an in-process pipe (lockstep) and UDP as ArduPilot SITL serves it.

The server only needs send / recv / close that never block, so lockstep runs and networked runs
share every line above the transport.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol

from firmware_py.core.cli import UserError
from sitl.mavlink.datagrams import DatagramParser


class Transport(Protocol):
    """A byte link: send whole packets, receive whatever has arrived (b"" when nothing; never blocks)."""

    def send(self, data: bytes) -> None: ...

    def recv(self) -> bytes: ...

    def close(self) -> None: ...


class PipeTransport:
    """One end of an in-process byte pipe; thread-safe so a server thread and a client can share it."""

    def __init__(self) -> None:
        self._inbox: deque[bytes] = deque()
        self._lock = threading.Lock()
        self._peer: PipeTransport | None = None

    @classmethod
    def pair(cls) -> tuple[PipeTransport, PipeTransport]:
        a, b = cls(), cls()
        a._peer, b._peer = b, a
        return a, b

    def send(self, data: bytes) -> None:
        peer = self._peer
        if peer is None or not data:
            return
        with peer._lock:
            peer._inbox.append(bytes(data))

    def recv(self) -> bytes:
        with self._lock:
            data = b"".join(self._inbox)
            self._inbox.clear()
        return data

    def close(self) -> None:
        self._peer = None


def parse_udp_url(url: str) -> tuple[str, str, int]:
    kind, sep, rest = url.partition(":")
    host, sep2, port_s = rest.rpartition(":")
    if not sep or not sep2 or kind not in ("udp", "udpin", "udpout") or not host:
        raise ValueError(f"expected udp:HOST:PORT, udpin:HOST:PORT or udpout:HOST:PORT, got {url!r}")
    try:
        port = int(port_s)
    except ValueError:
        raise ValueError(f"bad UDP port in {url!r}") from None
    if not 0 <= port <= 65535 or (kind == "udpout" and port == 0):
        raise ValueError(f"bad UDP port in {url!r}")
    return ("udpout" if kind == "udpout" else "udpin"), host, port


class UdpTransport:
    """UDP like ArduPilot SITL: "udp:HOST:PORT" listens there and replies to its clients;
    "udpout:HOST:PORT" sends to that fixed address. Port 0 listens on a free port (see local_address).

    A listening transport sends telemetry (`send`) to every client (at most `max_peers`) and replies
    (`send_to`) to one, like a MAVLink router: a ground station and the companion's payload can share
    one port (ArduPilot would give each its own SERIALn port; one port is simpler to run by hand).

    A sender becomes a client only through `add_peer`, which the server calls for a datagram that
    held a valid frame (an authenticated one when signing), never for random bytes. The table is
    bounded and never evicts a client that is still talking: when it is full a newcomer is refused
    (counted in `peers_refused`) until a client has been silent for `peer_timeout_s`, so senders,
    junk or not, cannot push a live ground station out.
    """

    MAX_DATAGRAMS_PER_RECV = 1000

    def __init__(self, address: str, peer_timeout_s: float = 10.0, max_peers: int = 8,
                 clock: Callable[[], float] = time.monotonic) -> None:
        kind, host, port = parse_udp_url(address)
        if not (math.isfinite(peer_timeout_s) and peer_timeout_s > 0):
            raise ValueError(f"peer timeout must be > 0 s, got {peer_timeout_s!r}")
        if isinstance(max_peers, bool) or not isinstance(max_peers, int) or max_peers < 1:
            raise ValueError(f"max_peers must be an integer >= 1, got {max_peers!r}")
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._fixed_peer = kind == "udpout"
        self._peers: dict[tuple[str, int], float] = {}  # address -> last heard (clock seconds)
        self._peer_timeout_s, self._max_peers, self._clock = peer_timeout_s, max_peers, clock
        if self._fixed_peer:
            self._peers[(host, port)] = math.inf
        else:
            self._sock.bind((host, port))
        self.dropped_packets = 0
        self.peers_refused = 0
        self._parser = DatagramParser()  # only for recv(): the byte-stream view of the datagrams

    @property
    def local_address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    @property
    def peer_address(self) -> tuple[str, int] | None:
        """The most recently heard client (or the fixed peer)."""
        return max(self._peers, key=self._peers.__getitem__) if self._peers else None

    @property
    def peers(self) -> list[tuple[str, int]]:
        return list(self._peers)

    @property
    def datagram_drops(self) -> dict[str, int]:
        """Datagrams recv() dropped (not whole MAVLink frames), by reason."""
        return {reason.value: n for reason, n in self._parser.drops.items()}

    def _expire(self) -> None:
        if self._fixed_peer:
            return
        oldest = self._clock() - self._peer_timeout_s
        for addr in [a for a, t in self._peers.items() if t < oldest]:
            del self._peers[addr]  # a client gone quiet: stop sending to it

    def send(self, data: bytes) -> None:
        """To every client (telemetry, the vehicle's own announcements)."""
        self._expire()
        if not self._peers:
            self.dropped_packets += 1  # nobody has talked to us yet
            return
        for addr in self._peers:
            self._sendto(data, addr)

    def send_to(self, data: bytes, addr: tuple[str, int] | None) -> None:
        """To one sender (a reply), client or not; None (a fixed peer's link) is the usual destination."""
        if addr is None or self._fixed_peer:
            self.send(data)
        else:
            self._sendto(data, addr)

    def _sendto(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            self._sock.sendto(data, addr)
        except OSError:
            self.dropped_packets += 1

    def recv(self) -> bytes:
        """The datagrams that are whole MAVLink frames, joined; each of their senders becomes a client.

        For byte-stream users; the server reads `recv_datagrams` and checks each itself.
        """
        out = []
        for data, addr in self.recv_datagrams():
            if self._parser.parse(data):
                self.add_peer(addr)
                out.append(data)
        return b"".join(out)

    def recv_datagrams(self) -> list[tuple[bytes, tuple[str, int]]]:
        """Every datagram received, with its sender, WITHOUT learning the senders (see add_peer)."""
        got = []
        for _ in range(self.MAX_DATAGRAMS_PER_RECV):
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break  # e.g. ICMP port unreachable reported on some platforms
            got.append((data, addr))
        return got

    def add_peer(self, addr: tuple[str, int]) -> bool:
        """Send telemetry to addr from now on; refreshes a known client. False when the table is full."""
        if self._fixed_peer:
            return True
        if addr not in self._peers and len(self._peers) >= self._max_peers:
            self._expire()
            if len(self._peers) >= self._max_peers:
                self.peers_refused += 1
                return False
        self._peers[addr] = self._clock()
        return True

    def close(self) -> None:
        self._sock.close()


def make_transport(url: str) -> Transport:
    """Transport from a URL-like string: udp:HOST:PORT / udpin:HOST:PORT (listen), udpout:HOST:PORT."""
    if url.split(":", 1)[0] in ("udp", "udpin", "udpout"):
        try:
            return UdpTransport(url)
        except OSError as exc:  # a port in use, a host no resolver knows: say which link
            raise UserError(f"cannot open the MAVLink link {url}: {exc.strerror or exc}") from exc
    raise ValueError(f"unsupported transport {url!r} (use udp:HOST:PORT or udpout:HOST:PORT)")
