"""Payload health for the ground station: NAMED_VALUE_FLOAT values at 1 Hz, STATUSTEXT on state changes.

`HealthMonitor` is pure apart from building pymavlink message objects: it is fed `HealthSnapshot`s
(cumulative counters read from the loop, the LiDAR driver and the pose tracker, stamped with the
payload clock) and returns the messages due; the caller sends them on the link the pose tracker uses.
No clock, no I/O, so tests feed it snapshots and read its messages.

Values (names at most 10 characters, MAVLink's char[10]; MAVProxy graphs them, QGC shows them in its
MAVLink inspector):

    PS_RATE     LiDAR readings per second over the last period, Hz
    PS_LOGGED   records in the sample log (written or buffered)
    PS_I2CERR   cumulative sensor failures: bus errors + busy timeouts + failed configuration transfers
                (a TFMini: frames lost to their checksum + waits that ended without a frame)
    PS_SENSERR  cumulative samples logged SENSOR_ERROR (what the log holds: failed readings AND the
                readings taken while the part reloads after an automatic reset, which are no failed
                transfer and so not in PS_I2CERR)
    PS_POSEAGE  age of the newest pose, s (-1: no pose received yet)
    PS_STALE    cumulative samples flagged STALE_POSE or NO_POSE
    PS_OVERRUN  cumulative loop ticks missed (the loop fell a whole period behind)

STATUSTEXT (prefixed "pilescan: "; a text longer than the message's 50 characters goes in MAVLink 2 chunks,
`statustext_msgs`): started and stopping (the caller's `event`; a stop's reason can be long), pose acquired /
lost / regained, a pose still missing 10 s after start (with the reason: no HEARTBEAT from the autopilot, no
time sync, no local position (EKF origin?)), LiDAR errors appearing, the LiDAR failing every
reading, and its recovery (judged on the larger of the two error counts over the period, so a part
stuck resetting is not reported "ok"). Severities follow ArduPilot's use: INFO for routine, NOTICE for
recoveries and stopping, WARNING for degraded data, ERROR when nothing usable is coming.
"""

from __future__ import annotations

import enum
import itertools
import math
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

NAME_MAX = 10
"""NAMED_VALUE_FLOAT.name is char[10]."""
TEXT_MAX = 50
"""STATUSTEXT.text is char[50]: a longer text goes in chunks (`statustext_msgs`)."""
TEXT_CHUNKS_MAX = 4
"""The most chunks one text is sent in (up to 199 characters); a longer text is cut at a word, ending '~'."""
TEXT_PREFIX = "pilescan: "

RATE, LOGGED, I2C_ERRORS, SENSOR_ERROR_SAMPLES, POSE_AGE, STALE, OVERRUNS = (
    "PS_RATE", "PS_LOGGED", "PS_I2CERR", "PS_SENSERR", "PS_POSEAGE", "PS_STALE", "PS_OVERRUN")
VALUE_NAMES = (RATE, LOGGED, I2C_ERRORS, SENSOR_ERROR_SAMPLES, POSE_AGE, STALE, OVERRUNS)

NO_POSE_WARNING_S = 10.0
"""A pose still missing this long after the start is reported once, with the reason."""


def named_value_msg(name: str, value: float, time_boot_ms: int) -> Any:
    """NAMED_VALUE_FLOAT; ValueError for a name MAVLink would silently truncate or a non-ASCII one."""
    if not isinstance(name, str) or not 1 <= len(name) <= NAME_MAX or not name.isascii():
        raise ValueError(f"NAMED_VALUE_FLOAT name must be 1-{NAME_MAX} ASCII characters, got {name!r}")
    return mavlink.MAVLink_named_value_float_message(int(time_boot_ms) & 0xFFFFFFFF, name.encode("ascii"),
                                                     float(value))


_chunk_ids = itertools.cycle(range(1, 65536))
"""The id a chunked text's STATUSTEXTs share (uint16, 0 meaning "not chunked"), one after another."""


def _cut_at_word(raw: bytes, limit: int) -> bytes:
    """raw itself when it fits in limit bytes, else cut after its last whole word that fits, ending '~' (mid-word
    only when a single word fills more than half the room)."""
    if len(raw) <= limit:
        return raw
    room = raw[:limit - 1]
    space = room.rfind(b" ")
    return (room[:space].rstrip() if space > limit // 2 else room) + b"~"


def statustext_msgs(severity: int, text: str) -> list[Any]:
    """The STATUSTEXTs that say text: one message (id 0) when it fits in 50 characters; else MAVLink 2 chunks of 50
    sharing a non-zero id, chunk_seq 0, 1, ..., the last shorter than 50 (its NUL ends the text: one empty chunk more
    when the text fills the last), as PX4 sends them. QGroundControl joins them into one message; a ground station
    that does not shows each chunk. At most TEXT_CHUNKS_MAX chunks: a text longer than those hold is cut at a word,
    ending '~'. Non-ASCII becomes '?'.
    """
    if not (isinstance(severity, int) and mavlink.MAV_SEVERITY_EMERGENCY <= severity <= mavlink.MAV_SEVERITY_DEBUG):
        raise ValueError(f"STATUSTEXT severity must be a MAV_SEVERITY 0-7, got {severity!r}")
    raw = str(text).encode("ascii", "replace")
    if len(raw) <= TEXT_MAX:
        return [mavlink.MAVLink_statustext_message(severity, raw)]
    raw = _cut_at_word(raw, TEXT_MAX * TEXT_CHUNKS_MAX - 1)
    chunks = [raw[k:k + TEXT_MAX] for k in range(0, len(raw), TEXT_MAX)]
    if len(chunks[-1]) == TEXT_MAX:
        chunks.append(b"")
    text_id = next(_chunk_ids)
    return [mavlink.MAVLink_statustext_message(severity, chunk, text_id, seq) for seq, chunk in enumerate(chunks)]


class PoseState(enum.Enum):
    """Whether the payload has a pose to tag samples with: waiting -> ok -> lost -> ok ..."""

    WAITING = "waiting"
    OK = "ok"
    LOST = "lost"


class SensorState(enum.Enum):
    """The LiDAR over the last period: every reading good, some errors, or nothing but errors."""

    OK = "ok"
    ERRORS = "errors"
    FAILED = "failed"


@dataclass(frozen=True, slots=True)
class HealthStatus:
    """What the monitor has concluded and sent so far (`HealthMonitor.status()`): a snapshot."""

    pose_state: PoseState
    sensor_state: SensorState
    rate_hz: float
    values_sent: int
    texts_sent: int

    def as_dict(self) -> dict[str, Any]:
        """For logs and JSON (the states by their value)."""
        return {"pose_state": self.pose_state.value, "sensor_state": self.sensor_state.value,
                "rate_hz": self.rate_hz, "values_sent": self.values_sent, "texts_sent": self.texts_sent}


@dataclass(frozen=True, slots=True)
class HealthSnapshot:
    """Cumulative payload counters at one instant (all counts since the start).

    Attributes:
        t_ns: payload clock time of the snapshot.
        readings: LiDAR readings taken (loop ticks).
        logged: records in the sample log, written or buffered.
        sensor_errors: bus errors + busy timeouts + failed configuration transfers.
        pose_ok: the pose tracker vouches for its pose now (time sync converged, pose fresh).
        pose_age_s: age of the newest pose, s; None before any.
        pose_status: the tracker's one-line pose status (used to say why a pose is missing).
        timesync_converged: the tracker's clock mapping is trusted.
        autopilot_heard: anything at all has come from the autopilot (its HEARTBEAT, at least, once a second).
        stale: samples flagged STALE_POSE or NO_POSE.
        overruns: loop ticks missed.
        sensor_error_samples: samples logged SENSOR_ERROR (includes readings during a reset).
    """

    t_ns: int
    readings: int
    logged: int
    sensor_errors: int
    pose_ok: bool
    pose_age_s: float | None
    pose_status: str = ""
    timesync_converged: bool = False
    autopilot_heard: bool = True
    stale: int = 0
    overruns: int = 0
    sensor_error_samples: int = 0


class HealthMonitor:
    """Turns snapshots into NAMED_VALUE_FLOAT (every period) and STATUSTEXT (on state changes).

    Args:
        t0_ns: payload start time (time_boot_ms counts from it).
        period_s: how often values are sent (and state changes looked for).
    """

    def __init__(self, t0_ns: int, period_s: float = 1.0) -> None:
        if not (isinstance(period_s, int | float) and math.isfinite(period_s) and 0.05 <= period_s <= 60.0):
            raise ValueError(f"health period must be 0.05-60 s, got {period_s!r}")
        self.t0_ns = int(t0_ns)
        self.period_ns = round(period_s * 1e9)
        self._next_ns = self.t0_ns
        self._prev: HealthSnapshot | None = None
        self.pose_state = PoseState.WAITING
        self.sensor_state = SensorState.OK
        self._no_pose_warned = False
        self.rate_hz = 0.0
        self._values_sent = self._texts_sent = 0

    def status(self) -> HealthStatus:
        """The states, the last reading rate and what was sent so far (a frozen snapshot)."""
        return HealthStatus(self.pose_state, self.sensor_state, self.rate_hz, self._values_sent, self._texts_sent)

    def _boot_ms(self, t_ns: int) -> int:
        return max(0, (t_ns - self.t0_ns) // 1_000_000)

    def event(self, severity: int, text: str) -> list[Any]:
        """The STATUSTEXT (or its chunks, when long: a stop's reason) for something the caller knows (started,
        stopping)."""
        self._texts_sent += 1
        return statustext_msgs(severity, TEXT_PREFIX + text)

    def due(self, now_ns: int) -> bool:
        """Whether `update` would send values now (cheap: the payload asks every tick)."""
        return now_ns >= self._next_ns or now_ns < self._next_ns - self.period_ns

    def update(self, snap: HealthSnapshot) -> list[Any]:
        """The messages due at snap.t_ns: nothing between periods; values and any state changes at one."""
        if not self.due(snap.t_ns):
            return []
        self._next_ns = max(self._next_ns + self.period_ns, snap.t_ns)
        prev = self._prev
        self._prev = snap
        out = self._pose_events(snap)
        if prev is not None and snap.t_ns > prev.t_ns:
            self.rate_hz = (snap.readings - prev.readings) * 1e9 / (snap.t_ns - prev.t_ns)
            errors = max(snap.sensor_errors - prev.sensor_errors, snap.sensor_error_samples - prev.sensor_error_samples)
            out += self._sensor_events(snap.readings - prev.readings, errors)
        ms = self._boot_ms(snap.t_ns)
        age = -1.0 if snap.pose_age_s is None or not math.isfinite(snap.pose_age_s) else snap.pose_age_s
        out += [named_value_msg(RATE, self.rate_hz, ms), named_value_msg(LOGGED, snap.logged, ms),
                named_value_msg(I2C_ERRORS, snap.sensor_errors, ms),
                named_value_msg(SENSOR_ERROR_SAMPLES, snap.sensor_error_samples, ms),
                named_value_msg(POSE_AGE, age, ms), named_value_msg(STALE, snap.stale, ms),
                named_value_msg(OVERRUNS, snap.overruns, ms)]
        self._values_sent += len(VALUE_NAMES)
        return out

    def _text(self, severity: int, text: str) -> list[Any]:
        return self.event(severity, text)

    def _pose_events(self, snap: HealthSnapshot) -> list[Any]:
        age = "" if snap.pose_age_s is None else f" (age {snap.pose_age_s:.2f} s)"
        if snap.pose_ok:
            if self.pose_state is PoseState.WAITING:
                self.pose_state = PoseState.OK
                return self._text(mavlink.MAV_SEVERITY_INFO, "pose acquired")
            if self.pose_state is PoseState.LOST:
                self.pose_state = PoseState.OK
                return self._text(mavlink.MAV_SEVERITY_NOTICE, "pose regained")
            return []
        if self.pose_state is PoseState.OK:
            self.pose_state = PoseState.LOST
            return self._text(mavlink.MAV_SEVERITY_WARNING, "pose lost" + age)
        if (self.pose_state is PoseState.WAITING and not self._no_pose_warned
                and snap.t_ns - self.t0_ns >= NO_POSE_WARNING_S * 1e9):
            self._no_pose_warned = True
            return self._text(mavlink.MAV_SEVERITY_WARNING, "no pose: " + _why_no_pose(snap))
        return []

    def _sensor_events(self, readings: int, errors: int) -> list[Any]:
        if readings <= 0:
            return []  # no readings this period (stopping, or a stalled loop): nothing to judge
        state = SensorState.OK if errors <= 0 else (SensorState.FAILED if errors >= readings else SensorState.ERRORS)
        if state is self.sensor_state:
            return []
        self.sensor_state = state
        if state is SensorState.FAILED:
            return self._text(mavlink.MAV_SEVERITY_ERROR, f"LiDAR failing: {errors} errors/{readings} reads")
        if state is SensorState.ERRORS:
            return self._text(mavlink.MAV_SEVERITY_WARNING, f"LiDAR errors: {errors} of {readings} reads")
        return self._text(mavlink.MAV_SEVERITY_NOTICE, "LiDAR ok again")


def _why_no_pose(snap: HealthSnapshot) -> str:
    if not snap.autopilot_heard:  # the cause; the time sync waits on it
        return "no HEARTBEAT from autopilot"
    if not snap.timesync_converged:
        return "time sync not converged"
    if snap.pose_status.startswith("no LOCAL_POSITION_NED"):
        return "no local position (EKF origin?)"
    if snap.pose_status.startswith("no ATTITUDE"):
        return "no ATTITUDE stream"
    return "pose too old" if snap.pose_age_s is not None else "no pose messages"
