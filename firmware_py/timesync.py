"""Autopilot-to-companion clock offset from MAVLink TIMESYNC, MAVROS-style (pure logic, no I/O, no clock).

Protocol: the companion sends TIMESYNC(tc1=0, ts1=t0) with t0 its own clock (ns); the autopilot answers
TIMESYNC(tc1=T, ts1=t0) with T its clock (ns since boot) when it handled the request; the reply arrives
at companion time t3. With equal delays each way the autopilot's T happened at companion time
(t0 + t3) / 2, so

    offset_ns = autopilot_ns - companion_ns = (2 tc1 - (ts1 + t3)) / 2        (MAVROS's sign)
    rtt_ns    = t3 - ts1

and companion_ns = autopilot_ns - offset_ns. (Some write (ts1 + now - 2 tc1) / 2, the same
quantity with the opposite sign, i.e. companion minus autopilot.) A sample's error is half the
asymmetry of the two delays, so it is bounded by rtt / 2: the filter and its jump test use that.

Filter (each rule says why):
- Gain: the k-th accepted sample moves the estimate by max(1/k, 1 - exp(-dt / time_constant_s)) of
  its deviation, dt the time since the previous accepted sample. 1/k is the running mean, the fastest
  unbiased start (the fast gain of the first samples); once it falls below the time-constant gain the
  filter is an EMA (the slow gain). The slow gain is set by a time, not per sample, because both
  things it trades are times: crystal drift between the clocks (20-50 ppm) lags the estimate by
  drift x time_constant_s (0.5 ms at 50 ppm and 10 s), and link jitter averages over
  ~2 x rate x time_constant_s samples, so a faster TIMESYNC rate buys accuracy without adding lag.
  `converged` after `converge_samples` accepted samples.
- Latency outliers: a reply whose RTT exceeds rtt_reject_factor x (minimum RTT of the last
  rtt_window replies) + rtt_reject_slack_ns is dropped: a late reply can be late on one leg only, and
  its error can reach rtt / 2. The slack must exceed the link's ordinary jitter; the factor keeps a
  slow link (a radio) from rejecting everything. A windowed minimum follows a link that got slower.
- Jumps: a sample that deviates from the estimate by more than jump_ns + rtt / 2 cannot be jitter (the
  true offset lies within rtt / 2 of every sample), so the filter hard-resets at once and restarts
  from that sample; once converged, a deviation above jump_ns that jitter could explain is left out
  of the average and resets only when jump_confirm_samples such samples in a row agree in sign.
- Reboots: `on_boot_time` resets when an autopilot `time_boot_ms` goes back by more than
  reboot_tolerance_ms (less is UDP reordering; the 49.7-day wrap of the u32 counter also lands here,
  harmlessly), and when, converged, a message's time maps into the companion's future (the offset no
  longer holds: the companion's clock jumped back).
After any reset, replies to requests sent before it are ignored, and `converged` is False again.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class TimesyncConfig:
    """Filter settings (see the module docstring for why each exists)."""

    converge_samples: int = 10
    """Accepted samples before the estimate is trusted."""
    time_constant_s: float = 10.0
    """Time constant of the slow EMA that follows the running mean."""
    rtt_window: int = 32
    """Replies over which the running minimum RTT is taken."""
    rtt_reject_factor: float = 2.0
    rtt_reject_slack_ns: int = 30_000_000
    """A reply is a latency outlier above rtt_reject_factor x min RTT + rtt_reject_slack_ns."""
    jump_ns: int = 10_000_000
    """A deviation above this is a clock jump (immediately, or once confirmed; see above)."""
    jump_confirm_samples: int = 6
    """Consecutive same-sign deviations above jump_ns (each explainable by jitter) that confirm a jump.
    6, as MAVROS: at 10 Hz on a 5-30 ms link, 3 gave a false reset every hour or so."""
    reboot_tolerance_ms: int = 1000
    """time_boot_ms going back by more than this is a reboot; less is reordering."""
    pending_requests: int = 16
    """Outstanding requests remembered (replies to older ones are ignored)."""

    def __post_init__(self) -> None:
        for name in ("converge_samples", "rtt_window", "jump_confirm_samples", "pending_requests"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        for name in ("rtt_reject_slack_ns", "jump_ns", "reboot_tolerance_ms"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 0):
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
        if not (isinstance(self.time_constant_s, int | float) and math.isfinite(self.time_constant_s)
                and self.time_constant_s > 0.0):
            raise ValueError(f"time_constant_s must be a finite number > 0, got {self.time_constant_s!r}")
        if not (isinstance(self.rtt_reject_factor, int | float) and math.isfinite(self.rtt_reject_factor)
                and self.rtt_reject_factor >= 1.0):
            raise ValueError(f"rtt_reject_factor must be a finite number >= 1, got {self.rtt_reject_factor!r}")


class TimesyncEstimator:
    """Filtered autopilot-minus-companion clock offset (ns) from TIMESYNC round trips."""

    def __init__(self, config: TimesyncConfig | None = None) -> None:
        self.config = config if config is not None else TimesyncConfig()
        self._pending: deque[int] = deque(maxlen=self.config.pending_requests)
        self._rtts: deque[int] = deque(maxlen=self.config.rtt_window)
        self._base_ns = 0          # the first sample after a reset; the estimate is base + residual
        self._resid_ns = 0.0       # kept apart so large clock values keep ns precision in a float
        self._k = 0                # accepted samples since the last reset
        self._last_accept_ns = 0   # companion time of the last accepted sample
        self._jitter_var = 0.0     # EMA of squared deviations, for health reporting
        self._high_dev: list[int] = []  # signs of consecutive high-deviation samples
        self._max_boot_ms: int | None = None
        self.last_rtt_ns: int | None = None
        self.last_reset_reason: str | None = None
        self.stats: dict[str, int] = {
            "samples": 0, "rejected": 0, "resets": 0, "rejected_rtt": 0, "rejected_deviation": 0,
            "invalid": 0, "unmatched": 0, "requests": 0,
        }

    # ----- the exchange -------------------------------------------------------------------------

    def request(self, now_ns: int) -> tuple[int, int]:
        """(tc1, ts1) for an outgoing TIMESYNC request at companion time now_ns; remembers ts1."""
        now_ns = int(now_ns)
        self._pending.append(now_ns)
        self.stats["requests"] += 1
        return 0, now_ns

    def on_reply(self, tc1: int, ts1: int, now_ns: int) -> bool:
        """Feed a TIMESYNC reply received at companion time now_ns; True if the sample was used."""
        tc1, ts1, now_ns = int(tc1), int(ts1), int(now_ns)
        if tc1 == 0 or ts1 not in self._pending:
            self.stats["unmatched"] += 1  # a request, or a reply to someone else (or a duplicate)
            return False
        self._pending.remove(ts1)
        rtt = now_ns - ts1
        if rtt < 0:
            self.stats["invalid"] += 1  # the companion clock went backwards during the round trip
            self.stats["rejected"] += 1
            return False
        self._rtts.append(rtt)
        cfg = self.config
        if rtt > cfg.rtt_reject_factor * min(self._rtts) + cfg.rtt_reject_slack_ns:
            self.stats["rejected_rtt"] += 1
            self.stats["rejected"] += 1
            return False
        self.last_rtt_ns = rtt
        twice = 2 * tc1 - ts1 - now_ns  # 2 x offset, exact integer
        if self._k == 0:
            self._seed(twice, now_ns)
            return True
        dev = (twice - 2 * self._base_ns) / 2.0 - self._resid_ns
        if abs(dev) > cfg.jump_ns + rtt / 2.0:
            self._reset(f"clock jump of {dev / 1e6:+.1f} ms seen by TIMESYNC (rtt {rtt / 1e6:.1f} ms)")
            self._seed(twice, now_ns)
            return True
        if abs(dev) > cfg.jump_ns and self.converged:
            sign = 1 if dev > 0 else -1
            if self._high_dev and self._high_dev[-1] != sign:
                self._high_dev.clear()
            self._high_dev.append(sign)
            if len(self._high_dev) >= cfg.jump_confirm_samples:
                self._reset(f"clock jump of {dev / 1e6:+.1f} ms confirmed by {len(self._high_dev)} samples")
                self._seed(twice, now_ns)
                return True
            self.stats["rejected_deviation"] += 1
            self.stats["rejected"] += 1
            return False
        self._high_dev.clear()
        self._k += 1
        dt_s = max(now_ns - self._last_accept_ns, 0) / 1e9
        self._last_accept_ns = now_ns
        gain = max(1.0 / self._k, -math.expm1(-dt_s / cfg.time_constant_s))
        self._resid_ns += gain * dev
        self._jitter_var += gain * (dev * dev - self._jitter_var)
        self.stats["samples"] += 1
        return True

    def on_boot_time(self, t_boot_ms: int, now_ns: int) -> bool:
        """Check an autopilot `time_boot_ms` received at companion time now_ns; True if it forced a reset.

        Resets on a reboot (time_boot_ms back by more than reboot_tolerance_ms) and, once converged, on
        a message whose time maps more than jump_ns into the companion's future.
        """
        t_boot_ms = int(t_boot_ms)
        last = self._max_boot_ms
        if last is not None and t_boot_ms + self.config.reboot_tolerance_ms < last:
            self._reset(f"autopilot reboot: time_boot_ms went back from {last} to {t_boot_ms}")
            self._max_boot_ms = t_boot_ms
            return True
        self._max_boot_ms = t_boot_ms if last is None else max(last, t_boot_ms)
        if self.converged:
            ahead_ns = self.to_companion_ns(t_boot_ms * 1_000_000) - int(now_ns)
            if ahead_ns > self.config.jump_ns:
                self._reset(f"clock jump: autopilot time maps {ahead_ns / 1e6:.1f} ms into the future")
                self._max_boot_ms = t_boot_ms
                return True
        return False

    def reset(self, reason: str = "requested") -> None:
        """Forget the estimate and outstanding requests (e.g. the link was replaced)."""
        self._reset(reason)

    # ----- the estimate -------------------------------------------------------------------------

    @property
    def has_estimate(self) -> bool:
        return self._k > 0

    @property
    def converged(self) -> bool:
        return self._k >= self.config.converge_samples

    @property
    def samples(self) -> int:
        """Accepted samples since the last reset."""
        return self._k

    @property
    def offset_ns(self) -> int | None:
        """Autopilot clock minus companion clock, ns (None before the first sample)."""
        return self._base_ns + round(self._resid_ns) if self._k else None

    @property
    def jitter_ns(self) -> float | None:
        """RMS deviation of accepted samples from the estimate (about half the link's delay asymmetry)."""
        return math.sqrt(self._jitter_var) if self._k > 1 else None

    @property
    def rtt_min_ns(self) -> int | None:
        return min(self._rtts) if self._rtts else None

    def to_companion_ns(self, autopilot_ns: int) -> int:
        """Companion time of an autopilot time (ns); RuntimeError before the first sample."""
        if not self._k:
            raise RuntimeError("no TIMESYNC estimate yet")
        return int(autopilot_ns) - self._base_ns - round(self._resid_ns)

    def to_autopilot_ns(self, companion_ns: int) -> int:
        """Autopilot time of a companion time (ns); RuntimeError before the first sample."""
        if not self._k:
            raise RuntimeError("no TIMESYNC estimate yet")
        return int(companion_ns) + self._base_ns + round(self._resid_ns)

    # ----- internals ----------------------------------------------------------------------------

    def _seed(self, twice_offset_ns: int, now_ns: int) -> None:
        self._base_ns = twice_offset_ns // 2
        self._resid_ns = (twice_offset_ns - 2 * self._base_ns) / 2.0
        self._k = 1
        self._last_accept_ns = now_ns
        self._jitter_var = 0.0
        self._high_dev.clear()
        self.stats["samples"] += 1

    def _reset(self, reason: str) -> None:
        self._k = 0
        self._base_ns, self._resid_ns, self._jitter_var = 0, 0.0, 0.0
        self._pending.clear()
        self._high_dev.clear()
        self._max_boot_ms = None
        self.stats["resets"] += 1
        self.last_reset_reason = reason
