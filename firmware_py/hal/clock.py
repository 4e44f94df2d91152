"""Clocks: the real monotonic clock, and a simulated one whose sleeping advances the simulation."""

from __future__ import annotations

import time
from collections.abc import Callable


class MonotonicClock:
    """time.monotonic_ns, sleeping with time.sleep (good to ~0.1 ms on Linux)."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until_ns(self, t_ns: int) -> None:
        delay = t_ns - time.monotonic_ns()
        if delay > 0:
            time.sleep(delay / 1e9)


class SimClock:
    """Simulated time. `sleep_until_ns` calls `advance(t_ns)`, which the SITL uses to step the world
    up to t_ns in lockstep; `advance_by_ns` lets emulated devices charge time for bus transfers.

    `advance` may return the time (ns) up to which the world is already stepped; the clock then
    skips calling it until time passes that horizon. A 500 Hz payload sleeps ~20 times per sample
    (bus transfers, busy polls) while the physics steps every few ms: most calls have nothing to do.
    Returning None means "call me every time".
    """

    def __init__(self, start_ns: int = 0, advance: Callable[[int], int | None] | None = None) -> None:
        self._t = int(start_ns)
        self._advance = advance
        self._horizon = -1

    def now_ns(self) -> int:
        return self._t

    def set_advance(self, advance: Callable[[int], int | None] | None) -> None:
        self._advance = advance
        self._horizon = -1

    def sleep_until_ns(self, t_ns: int) -> None:
        t_ns = int(t_ns)
        if t_ns <= self._t:
            return
        if self._advance is not None and t_ns > self._horizon:
            horizon = self._advance(t_ns)
            self._horizon = -1 if horizon is None else int(horizon)
        self._t = t_ns

    def advance_by_ns(self, dt_ns: int) -> None:
        """Time passing without the payload sleeping (e.g. an I2C transfer on the wire)."""
        t_ns = self._t + int(dt_ns)
        if t_ns <= self._horizon:  # the world is already stepped past it: the common case, kept cheap
            if t_ns > self._t:  # (not max(): a builtin call ~450k times a flight)
                self._t = t_ns
        else:
            self.sleep_until_ns(t_ns)

    def set_ns(self, t_ns: int) -> None:
        """Move time forward to t_ns (the world's owner uses this while stepping)."""
        self._t = max(self._t, int(t_ns))
