"""The payload loop: range, servo, pose, log — at 500 Hz, on hardware or, unchanged, in the SITL.
(A streaming rangefinder, the TFMini, sets the pace instead: `LoopConfig.paced_by_sensor`.)

Each tick: take one LiDAR reading (its time is when the acquisition was triggered), advance the
servo (a new pulse every PWM frame), pump the MAVLink link. A reading waits in a short queue until
the autopilot's poses on both sides of its time have arrived (they come over a link with latency),
then it is tagged with the servo's modelled angle and the pose interpolated at its time and
appended to the sample log (which writes, flushes and fsyncs a block every `records_per_block`
records). A reading whose pose has not arrived after `max_pose_wait_s` is logged flagged stale.
The loop sleeps on the HAL clock until the next tick; in the SITL that sleep advances the world.

Flags say what cannot be vouched for (no echo, bus error, stale or missing pose, servo unsure);
the ground station drops flagged samples, so a sample is never tagged with a pose it should not
have.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from firmware_py.core.samplelog import SAMPLE_DTYPE, SampleFlags, SampleLogWriter
from firmware_py.drivers.reading import ReadStatus
from firmware_py.drivers.servo import SweepServo
from firmware_py.hal import Clock
from firmware_py.pose import PoseSample

# Plain ints and the enum members themselves on the 500 Hz path: IntFlag arithmetic is slow, and an
# identity test against a member (`status is _OK`) is the cheapest comparison Python has.
_NO_RETURN, _SENSOR_ERROR = int(SampleFlags.NO_RETURN), int(SampleFlags.SENSOR_ERROR)
_NO_POSE, _STALE_POSE = int(SampleFlags.NO_POSE), int(SampleFlags.STALE_POSE)
_OK, _NO_ECHO = ReadStatus.OK, ReadStatus.NO_RETURN
_NO_POSE_VALUES = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


class RangeReading(Protocol):
    """One range measurement as the loop reads it (`firmware_py.drivers.reading.Reading`)."""

    @property
    def range_m(self) -> float | None: ...

    @property
    def status(self) -> ReadStatus: ...

    @property
    def t_ns(self) -> int: ...


class SensorCounters(Protocol):
    """What a rangefinder driver has counted (`LidarLiteCounters`, `TfminiCounters`)."""

    @property
    def sensor_errors(self) -> int:
        """Readings that failed (the part did not answer, or its bytes were not a reading)."""

    def as_dict(self) -> dict[str, int]: ...


class RangeSensor(Protocol):
    """A rangefinder driver as the loop and the program around it use it: the LIDAR-Lite on I2C, the
    TFMini on a UART. `read()` returns one reading, never raises for a sensor fault, and waits at most
    its driver's deadline."""

    def read(self) -> RangeReading: ...

    def counters(self) -> SensorCounters: ...


class PoseSource(Protocol):
    """What the loop needs of the vehicle pose (the `PoseTracker`; a test's canned poses)."""

    def pump(self) -> None:
        """Read the link and send what is due; never blocks."""

    def pose_at(self, t_ns: int) -> PoseSample:
        """The pose at companion time t_ns; never None (its stale / missing flags say why not usable)."""


@dataclass(frozen=True)
class LoopConfig:
    """The loop's pace and pose limits.

    Attributes:
        rate_hz: ticks per second; with `paced_by_sensor`, the sensor's own rate (for the servo's
            timing and the counters), not a schedule.
        paced_by_sensor: the sensor streams at its own rate and `read()` waits for its next reading
            (the TFMini): the loop does not sleep to a tick grid of its own, so no reading waits in a
            buffer (where its time stamp would be lost) and a sensor clock a little faster or slower
            than ours never makes a backlog or a gap. A silent sensor still ends each wait at the
            driver's deadline, with a failed reading, so the loop keeps going.
        max_pose_age_s, max_pose_wait_s: a sample's pose limits (module docstring).
    """

    rate_hz: float = 500.0
    max_pose_age_s: float = 0.1
    max_pose_wait_s: float = 0.25
    paced_by_sensor: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and 1.0 <= self.rate_hz <= 2000.0):
            raise ValueError(f"payload rate must be 1-2000 Hz, got {self.rate_hz}")
        if not (math.isfinite(self.max_pose_age_s) and self.max_pose_age_s > 0):
            raise ValueError(f"max pose age must be > 0 s, got {self.max_pose_age_s}")


COUNTED_FLAGS = tuple(f for f in SampleFlags if f)
"""The sample flags `LoopStats` counts, in the order of its `flag_counts`."""
_COUNTED_BITS = tuple(int(f) for f in COUNTED_FLAGS)


@dataclass(frozen=True, slots=True)
class LoopStats:
    """What the loop has counted since it started: a snapshot (`PayloadLoop.stats`), not a live record.

    Attributes:
        ticks: readings taken.
        overruns: tick slots missed whole (a stall of a period or more). The loop keeps its grid, so
            ticks + overruns counts the slots that passed and the samples after a stall stay in phase.
        busy_ns_total: the loop's own CPU time, when it was given a CPU clock (benchmarks), else 0.
        flag_counts: samples logged with each of `COUNTED_FLAGS`, in that order.
    """

    ticks: int = 0
    overruns: int = 0
    busy_ns_total: int = 0
    flag_counts: tuple[int, ...] = (0,) * len(COUNTED_FLAGS)

    @property
    def busy_us_per_tick(self) -> float:
        return self.busy_ns_total / max(1, self.ticks) / 1e3

    def flagged(self, flags: SampleFlags) -> int:
        """Samples logged with each flag in `flags`, summed over those flags."""
        return sum(n for f, n in zip(COUNTED_FLAGS, self.flag_counts, strict=True) if f & flags)

    def as_dict(self) -> dict[str, Any]:
        """For logs and JSON: the counts, and the flagged samples by flag name."""
        return {"ticks": self.ticks, "overruns": self.overruns, "busy_ns_total": self.busy_ns_total,
                "flagged": {f.name: n for f, n in zip(COUNTED_FLAGS, self.flag_counts, strict=True)}}


class PayloadLoop:
    """One payload: sensor, servo and pose source in, sample log out."""

    def __init__(self, sensor: RangeSensor, servo: SweepServo, pose: PoseSource, clock: Clock,
                 log: SampleLogWriter, cfg: LoopConfig | None = None, t0_ns: int | None = None,
                 cpu_clock: Callable[[], int] | None = None) -> None:
        self.sensor, self.servo, self.pose, self.clock, self.log = sensor, servo, pose, clock, log
        self.cfg = cfg or LoopConfig()
        self.period_ns = round(1e9 / self.cfg.rate_hz)
        self.t0_ns = clock.now_ns() if t0_ns is None else t0_ns
        self._ticks = self._overruns = self._busy_ns = 0  # plain ints in the loop; `stats` hands out a snapshot
        self._flag_counts = [0] * len(COUNTED_FLAGS)
        self._cpu = cpu_clock  # a real CPU-time clock to measure the loop's own cost (benchmarks)
        self._next_ns = self.t0_ns
        self._pending: collections.deque = collections.deque()

    @property
    def stats(self) -> LoopStats:
        """What the loop has counted so far (a frozen snapshot)."""
        return LoopStats(self._ticks, self._overruns, self._busy_ns, tuple(self._flag_counts))

    @property
    def pending(self) -> int:
        """Readings taken and still waiting for their pose (not yet handed to the log)."""
        return len(self._pending)

    def tick(self) -> None:
        """One sample: read, move the servo, pump the link, log what can now be tagged."""
        cpu0 = self._cpu() if self._cpu else 0
        self.servo.update((self.clock.now_ns() - self.t0_ns) * 1e-9)  # first: pulses on the tick grid
        reading = self.sensor.read()
        t_s = (reading.t_ns - self.t0_ns) * 1e-9
        self._pending.append((reading, self.servo.angle_at(t_s), self.servo.waveform.sweep_direction_at(t_s)))
        self.pose.pump()
        self._tag_ready(self.clock.now_ns())
        self._ticks += 1
        if self._cpu:
            self._busy_ns += self._cpu() - cpu0

    def _tag_ready(self, now_ns: int, flush: bool = False) -> None:
        wait_ns = round(self.cfg.max_pose_wait_s * 1e9)
        while self._pending:
            reading, servo_rad, sweep = self._pending[0]
            p = self.pose.pose_at(reading.t_ns)
            usable = not (p.stale or p.missing)
            if not (usable or flush or now_ns - reading.t_ns >= wait_ns):
                break  # its pose is still on the way; later readings are newer still
            self._pending.popleft()
            self.log.append(self._record(reading, servo_rad, sweep, p))

    def _record(self, reading: RangeReading, servo_rad: float, sweep: int, p: PoseSample) -> np.ndarray:
        """One SAMPLE_DTYPE record (0-d array), built from a tuple in field order: ~5x cheaper than
        setting fields one by one, and this runs 500 times a second."""
        status, rng_m = reading.status, reading.range_m
        if status is _OK and rng_m is not None:
            flags = 0
        else:
            flags = _NO_RETURN if status is _NO_ECHO else _SENSOR_ERROR
            rng_m = 0.0
        if p.missing:
            flags |= _NO_POSE
            pose = _NO_POSE_VALUES
        else:
            if p.stale or p.age_s > self.cfg.max_pose_age_s:
                flags |= _STALE_POSE
            x, y, z = p.pos_ned_m
            pose = (x, y, z, p.roll_rad, p.pitch_rad, p.yaw_rad, p.age_s)
        if flags:
            counts = self._flag_counts
            for i, bit in enumerate(_COUNTED_BITS):
                if bit & flags:
                    counts[i] += 1
        # Field order of SAMPLE_DTYPE: t_s, range_m, servo_rad, sweep_dir, flags, x, y, z, r, p, y, age.
        return np.array((reading.t_ns * 1e-9, rng_m, servo_rad, sweep, flags, *pose), dtype=SAMPLE_DTYPE)

    def run(self, duration_s: float | None = None, should_stop: Callable[[], bool] = lambda: False) -> LoopStats:
        """Tick at the configured rate until duration_s of sampling has passed or should_stop() says so.

        The duration counts from here, not from t0: between the two the program opened its log and greeted the
        autopilot, which on a loaded computer (an fsync on a busy card) took longer than a short run's whole
        duration, and the run logged nothing. For the same reason the grid's ticks before here are skipped, not
        counted as overruns: no loop ran then to miss them."""
        start_ns = self.clock.now_ns()
        end_ns = None if duration_s is None else start_ns + round(duration_s * 1e9)
        if start_ns > self._next_ns + self.period_ns:  # on the grid from t0 still (the sweep's pulses are)
            self._next_ns += (start_ns - self._next_ns) // self.period_ns * self.period_ns
        if self.cfg.paced_by_sensor:
            while not should_stop():
                if end_ns is not None and self.clock.now_ns() >= end_ns:
                    break
                self.tick()  # the sensor's read waits for its next reading
            self._drain()
            return self.stats
        while not should_stop():
            now = self.clock.now_ns()
            if end_ns is not None and now >= end_ns:
                break
            if now > self._next_ns + self.period_ns:  # whole ticks missed: count them, keep the grid
                missed = (now - self._next_ns) // self.period_ns
                self._overruns += missed
                self._next_ns += missed * self.period_ns
            self.clock.sleep_until_ns(self._next_ns)
            self.tick()
            self._next_ns += self.period_ns
        self._drain()
        return self.stats

    def _drain(self) -> None:
        """At the end: no more readings, but the link pumped on a tick grid until the poses after the last
        ones have come (one stream period and the link's latency; at most `max_pose_wait_s`), so a stop
        loses no sample to a missing pose. What still has none is logged flagged, and the log flushed."""
        now = self.clock.now_ns()
        deadline, t = now + round(self.cfg.max_pose_wait_s * 1e9), now
        while self._pending and t < deadline:
            t += self.period_ns
            self.clock.sleep_until_ns(t)
            self.pose.pump()
            self._tag_ready(self.clock.now_ns())
        self._tag_ready(self.clock.now_ns(), flush=True)
        self.log.flush()
