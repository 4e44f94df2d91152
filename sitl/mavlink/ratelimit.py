"""Token buckets: a steady rate with a burst allowance, per sender, on whatever clock the caller passes.

Used for what one sender can make the server do that costs everyone: STATUSTEXT answers to its bad
requests, and the telemetry log space its frames take. The clock is the caller's (simulated time
in lockstep, so runs stay deterministic), and the table of senders is bounded.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass


@dataclass(frozen=True)
class Rate:
    """At most `per_s` on average, and `burst` at once (a full bucket)."""

    per_s: float
    burst: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.per_s) and self.per_s > 0):
            raise ValueError(f"rate must be > 0 per second, got {self.per_s!r}")
        if not (math.isfinite(self.burst) and self.burst >= 1):
            raise ValueError(f"burst must be >= 1, got {self.burst!r}")


class TokenBucket:
    """One sender's bucket: take() spends a token if there is one."""

    __slots__ = ("rate", "t_s", "tokens")

    def __init__(self, rate: Rate, now_s: float) -> None:
        self.rate, self.tokens, self.t_s = rate, float(rate.burst), now_s

    def take(self, now_s: float, cost: float = 1.0) -> bool:
        if now_s > self.t_s:
            self.tokens = min(self.rate.burst, self.tokens + (now_s - self.t_s) * self.rate.per_s)
            self.t_s = now_s
        elif now_s < self.t_s:
            self.t_s = now_s  # the clock was changed (time_link_by): refill from here on
        if self.tokens >= cost:
            self.tokens -= cost
            return True
        return False


class KeyedBuckets:
    """A bucket per key (sender), at most `max_keys` of them (the least recently used goes first;
    a sender that comes back starts with a full bucket, so the bound costs at most one burst)."""

    def __init__(self, rate: Rate, max_keys: int = 1024) -> None:
        self.rate, self._max_keys = rate, max_keys
        self._buckets: OrderedDict[Hashable, TokenBucket] = OrderedDict()
        self.refused = 0

    def take(self, key: Hashable, now_s: float, cost: float = 1.0) -> bool:
        bucket = self._buckets.get(key)
        if bucket is None:
            bucket = self._buckets[key] = TokenBucket(self.rate, now_s)
            if len(self._buckets) > self._max_keys:
                self._buckets.popitem(last=False)
        else:
            self._buckets.move_to_end(key)
        if bucket.take(now_s, cost):
            return True
        self.refused += 1
        return False

    def __len__(self) -> int:
        return len(self._buckets)
