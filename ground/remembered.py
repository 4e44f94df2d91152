"""Values a process remembers up to a byte budget, the least recently used let go first.

Why one piece: the servo's re-simulations are remembered twice over, by the mount's fits (`ground.self_calibration`:
the angles at each scale of one drive) and by the servo's timing search (`ground.servo_timing`: the states stepped at
each speed), each under its own lock and budget. What is remembered is what would be computed, so a value let go
costs only its recomputation.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

V = TypeVar("V")


class Remembered(Generic[V]):
    """Values by key, up to max_bytes in all (`nbytes` of each), the least recently used let go first but never the
    newest; safe to use from several threads (the value is computed outside the lock: two threads may compute the same
    one, which is the same value)."""

    def __init__(self, max_bytes: int, nbytes: Callable[[V], int]) -> None:
        self.max_bytes = max_bytes
        self._nbytes = nbytes
        self._values: OrderedDict[Hashable, V] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable, usable: Callable[[V], bool] | None = None) -> V | None:
        """The value remembered by key (and now the most recently used), or None; None too when `usable` says the
        value remembered will not do."""
        with self._lock:
            got = self._values.get(key)
            if got is None or (usable is not None and not usable(got)):
                return None
            self._values.move_to_end(key)
            return got

    def put(self, key: Hashable, value: V) -> None:
        """Remember value by key, letting the least recently used go while the budget is exceeded."""
        with self._lock:
            self._values[key] = value
            self._values.move_to_end(key)
            held = sum(self._nbytes(v) for v in self._values.values())
            while held > self.max_bytes and len(self._values) > 1:
                held -= self._nbytes(self._values.popitem(last=False)[1])

    def clear(self) -> None:
        with self._lock:
            self._values.clear()
