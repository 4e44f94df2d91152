"""Where the micro-services' messages go: to every client, or back to the one that asked.

ArduPilot broadcasts its telemetry and its own announcements, and answers a request on the link
it came in on. The server's services do the same through an `Outbox`: `reply` / `say` go to the
sender of the message being handled (`asker()`), `send_to` / `say_to` to one remembered earlier
(the mission upload's partner), `broadcast` / `announce` to every client. A peer is whatever the
transport names a sender by (a UDP address; None on the lockstep pipe, which has one client).
"""

from __future__ import annotations

from typing import Any, Protocol

Peer = Any
"""A sender as the transport names it (a UDP (host, port); None on a single-client link)."""


class Outbox(Protocol):
    def broadcast(self, msg: Any) -> None:
        """To every client: telemetry, and what the vehicle does whoever asked for it."""

    def reply(self, msg: Any) -> None:
        """To the sender of the message being handled."""

    def asker(self) -> Peer:
        """The sender of the message being handled (for a reply sent later)."""

    def send_to(self, msg: Any, peer: Peer) -> None: ...

    def say(self, severity: int, text: str) -> None:
        """STATUSTEXT to the sender of the message being handled (rate-limited per sender)."""

    def say_to(self, peer: Peer, severity: int, text: str) -> None: ...

    def announce(self, severity: int, text: str) -> None:
        """STATUSTEXT to every client (the vehicle's own news)."""
