"""An in-memory byte pipe for MAVLink links in tests: the payload's own tests need no simulator for it."""

from __future__ import annotations

import threading
from collections import deque


class BytePipe:
    """One end of an in-process byte pipe (send/recv/close, as a ByteStreamLink wants); thread-safe."""

    def __init__(self) -> None:
        self._inbox: deque[bytes] = deque()
        self._lock = threading.Lock()
        self._peer: BytePipe | None = None

    @classmethod
    def pair(cls) -> tuple[BytePipe, BytePipe]:
        a, b = cls(), cls()
        a._peer, b._peer = b, a
        return a, b

    def send(self, data: bytes) -> None:
        peer = self._peer
        if peer is not None and data:
            with peer._lock:
                peer._inbox.append(bytes(data))

    def recv(self) -> bytes:
        with self._lock:
            data = b"".join(self._inbox)
            self._inbox.clear()
        return data

    def close(self) -> None:
        self._peer = None
