"""The payload's view of the vehicle pose: streams requested over MAVLink, clocks synced, poses interpolated.

`PoseTracker` owns no thread. The payload loop calls `pump()` often (every loop iteration); each call
reads everything the link has, feeds TIMESYNC replies to a `TimesyncEstimator` and ATTITUDE /
LOCAL_POSITION_NED to a `PoseBuffer` (stamps mapped to companion time), and sends what is due:
TIMESYNC requests, the companion HEARTBEAT (1 Hz), and the stream requests of `start()`
(MAV_CMD_SET_MESSAGE_INTERVAL, retried until COMMAND_ACK or a limit). It works the same over a
serial/UDP `PymavlinkLink` and over a `ByteStreamLink` in the SITL lockstep.

Choices:
- Pose messages are buffered only once the time sync has converged, and the buffer is cleared on
  every time-sync reset: a sample is never placed with an offset that is not trusted. After a reset
  the stream requests are sent again, since a rebooted autopilot has forgotten them.
- TIMESYNC requests go at `timesync_fast_hz` (10 Hz) until converged, then at `timesync_hz`: a reset
  costs about a second of pose, not converge_samples seconds.
- A reply's receive time is the time `pump()` read it, so a payload that pumps rarely adds half its
  polling delay to the offset error: pump at least as often as LiDAR samples are taken.
- Only messages from the target autopilot (system and component) count: a ground station on the same
  network answering our TIMESYNC would otherwise put its own clock into the estimate.
- TIMESYNC requests from the autopilot (tc1 = 0) are answered with our clock, as MAVROS does.
- While nothing at all has come from the autopilot, the status says that first, with the link and how long:
  waiting for TIMESYNC replies is then only the consequence.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal import Clock, MavlinkLink
from firmware_py.hal.mavlink_link import heartbeat_msg
from firmware_py.pose import PoseBuffer, PoseSample
from firmware_py.timesync import TimesyncConfig, TimesyncEstimator

POSE_STREAMS: dict[int, str] = {
    mavlink.MAVLINK_MSG_ID_ATTITUDE: "ATTITUDE",
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: "LOCAL_POSITION_NED",
}


@dataclass(frozen=True)
class PoseTrackerConfig:
    """What the tracker asks of the autopilot, and how patiently."""

    target_system: int = 1
    target_component: int = 1
    """The autopilot (MAV_COMP_ID_AUTOPILOT1); 0 accepts pose from any component of target_system."""
    stream_hz: float = 50.0
    """ATTITUDE and LOCAL_POSITION_NED rate asked for (DESIGN: 50-100 Hz)."""
    timesync_hz: float = 10.0
    """TIMESYNC rate once converged: 10 Hz as MAVROS; at 1 Hz a 5-30 ms jittery link gives 0.6-1.6 ms."""
    timesync_fast_hz: float = 10.0
    """TIMESYNC rate until converged (at least timesync_hz)."""
    heartbeat_hz: float = 1.0
    command_timeout_ns: int = 500_000_000
    command_attempts: int = 5
    buffer_capacity: int = 256
    max_pose_age_ns: int = 100_000_000
    extrapolate_ns: int = 0
    """0: a pose is only ever interpolated between two real samples (the payload waits for them).
    Extrapolating the newest two amplifies the estimate's message-to-message noise: white noise of
    sigma comes out at 1.6 sigma on average and 2.2 sigma one period ahead, beyond what the log
    header states, and the ground station's wall tolerance is sized from the header (measured over
    20 start positions: Appendix A's pile 1 at P_traj 5 % read Ve 0.36 % with extrapolation, 0.10 %
    interpolated; docs/design-notes.md)."""
    rate_window_ns: int = 1_000_000_000

    def __post_init__(self) -> None:
        if not (isinstance(self.target_system, int) and 1 <= self.target_system <= 255):
            raise ValueError(f"target_system must be an integer 1-255, got {self.target_system!r}")
        if not (isinstance(self.target_component, int) and 0 <= self.target_component <= 255):
            raise ValueError(f"target_component must be an integer 0-255, got {self.target_component!r}")
        for name in ("stream_hz", "timesync_hz", "timesync_fast_hz", "heartbeat_hz"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and 0.0 < value <= 1000.0):
                raise ValueError(f"{name} must be a rate in (0, 1000] Hz, got {value!r}")
        for name in ("command_timeout_ns", "command_attempts", "buffer_capacity", "max_pose_age_ns",
                     "rate_window_ns"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not (isinstance(self.extrapolate_ns, int) and 0 <= self.extrapolate_ns <= self.max_pose_age_ns):
            raise ValueError(f"extrapolate_ns must be an integer in 0..max_pose_age_ns, got {self.extrapolate_ns!r}")


@dataclass(frozen=True, slots=True)
class TimesyncStatus:
    """The clock mapping's health (`TimesyncEstimator`), in operator units."""

    converged: bool
    offset_ns: int | None
    rtt_ms: float | None
    rtt_min_ms: float | None
    jitter_ms: float | None
    samples: int
    rejected: int
    resets: int
    last_reset_reason: str | None


@dataclass(frozen=True, slots=True)
class PoseTrackerStatus:
    """The tracker's health at one instant (`PoseTracker.status()`): a snapshot; `as_dict()` for logs/JSON.

    Attributes:
        pose_ok: time sync converged and the newest pose no older than max_pose_age_ns.
        pose_age_s: age of the newest pose, None before any.
        pose_status: one line for the operator (what is missing and why).
        timesync: the clock mapping.
        streams: each pose stream's request state ("accepted at 50 Hz", "refused: ...").
        rates_hz: messages received per second, by type, over the last rate window.
        autopilot_heartbeat_age_s: since the autopilot's last HEARTBEAT, None before one.
        link: the link's counters (empty if it keeps none); link_last_error its last error.
        tracker: what the tracker sent and dropped.
    """

    pose_ok: bool
    pose_age_s: float | None
    pose_status: str
    timesync: TimesyncStatus
    streams: Mapping[str, str]
    rates_hz: Mapping[str, float]
    autopilot_heartbeat_age_s: float | None
    link: Mapping[str, int]
    link_last_error: str | None
    tracker: Mapping[str, int]

    def as_dict(self) -> dict[str, Any]:
        """Plain dicts all the way down (JSON, the SITL's run record)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["timesync"] = {f.name: getattr(self.timesync, f.name) for f in fields(self.timesync)}
        for name in ("streams", "rates_hz", "link", "tracker"):
            out[name] = dict(out[name])
        return out


@dataclass
class _Command:
    msg_id: int
    attempts: int
    sent_ns: int


class _Every:
    """A periodic action on a clock that may jump: due after one period, or at once if time went back."""

    def __init__(self, period_ns: int) -> None:
        self.period_ns = period_ns
        self.last_ns: int | None = None

    def due(self, now_ns: int, period_ns: int | None = None) -> bool:
        last = self.last_ns
        period = self.period_ns if period_ns is None else period_ns
        return last is None or now_ns - last >= period or now_ns < last

    def mark(self, now_ns: int) -> None:
        self.last_ns = now_ns


class PoseTracker:
    """Pose of the vehicle at any companion time, from the autopilot's MAVLink streams (module docstring)."""

    def __init__(self, link: MavlinkLink, clock: Clock, target_system: int = 1, stream_hz: float = 50.0,
                 timesync_hz: float = 10.0, *, target_component: int = 1, timesync_fast_hz: float = 10.0,
                 max_pose_age_ns: int = 100_000_000, buffer_capacity: int = 256,
                 timesync_config: TimesyncConfig | None = None, link_name: str | None = None) -> None:
        self.config = PoseTrackerConfig(
            target_system=target_system, target_component=target_component, stream_hz=stream_hz,
            timesync_hz=timesync_hz, timesync_fast_hz=max(timesync_fast_hz, timesync_hz),
            max_pose_age_ns=max_pose_age_ns, buffer_capacity=buffer_capacity)
        self.link, self.clock = link, clock
        self.link_name = link_name if link_name is not None else getattr(link, "url", None)
        """How the operator's lines name the link (its URL); None: they do not name it."""
        self._listening_since_ns = clock.now_ns()
        self.timesync = TimesyncEstimator(timesync_config)
        self.buffer = PoseBuffer(self.config.buffer_capacity, self.config.max_pose_age_ns, self.config.extrapolate_ns)
        cfg = self.config
        self._timesync = _Every(round(1e9 / cfg.timesync_hz))
        self._timesync_fast_ns = round(1e9 / cfg.timesync_fast_hz)
        self._heartbeat = _Every(round(1e9 / cfg.heartbeat_hz))
        self._started = False
        self._stream_queue: deque[int] = deque()
        self._stream_state: dict[str, str] = dict.fromkeys(POSE_STREAMS.values(), "not requested")
        self._cmd: _Command | None = None
        self._rx_counts: Counter[str] = Counter()
        self._rate_t0_ns: int | None = None
        self._rates_hz: dict[str, float] = {}
        self._last_heartbeat_rx_ns: int | None = None
        self._autopilot_base_mode: int | None = None
        self.autopilot_origin_e7: tuple[int, int, int] | None = None
        """The EKF origin the autopilot last reported (GPS_GLOBAL_ORIGIN: 1e-7 deg, 1e-7 deg, mm); None before."""
        self._replies_seen = 0
        self._autopilot_heard = False
        self.params: dict[str, float] = {}
        """Autopilot parameters asked for with `request_params` and answered (name -> value)."""
        self._params_wanted: tuple[str, ...] = ()
        self._params_missing: set[str] = set()  # asked for, not yet answered: empty, the pump's check is one test
        self._params_round = _Command(0, 0, 0)  # attempts and time of the last round of reads
        self.stats: Counter[str] = Counter()

    # ----- the payload loop's calls ---------------------------------------------------------------

    def start(self) -> None:
        """Ask for the pose streams at stream_hz and start syncing clocks (sends at once)."""
        self._started = True
        self._request_streams()
        self._service(self.clock.now_ns())

    def request_params(self, names: tuple[str, ...]) -> None:
        """Read these autopilot parameters (PARAM_REQUEST_READ by name; the unanswered asked again every
        command timeout, up to the command attempts): `params` fills as PARAM_VALUEs arrive."""
        self._params_wanted = tuple(names)
        self._params_missing = {n for n in self._params_wanted if n not in self.params}
        self._params_round = _Command(0, 0, 0)
        self._service_params(self.clock.now_ns())

    @property
    def autopilot_heard(self) -> bool:
        """Whether any message from the target autopilot has arrived."""
        return self._autopilot_heard

    @property
    def params_settled(self) -> bool:
        """Every parameter asked for answered, or its reads all sent and timed out."""
        r = self._params_round
        return not self._params_missing or (r.attempts >= self.config.command_attempts
                                and self.clock.now_ns() - r.sent_ns >= self.config.command_timeout_ns)

    def pump(self) -> None:
        """Handle everything received, send what is due (never blocks)."""
        msgs = self.link.recv()
        now = self.clock.now_ns()  # after the read: no reply is stamped before it arrived
        for msg in msgs:
            self._handle(msg, now)
        self._service(now)

    def pose_at(self, t_ns: int) -> PoseSample:
        """The vehicle pose at companion time t_ns (stale / missing flags say when it cannot be used)."""
        return self.buffer.pose_at(t_ns)

    def status(self) -> PoseTrackerStatus:
        """Health for logs and the operator: pose age, time sync, stream requests, rates, link errors."""
        now = self.clock.now_ns()
        ts = self.timesync
        newest = self.buffer.newest_ns
        pose_age_s = (now - newest) / 1e9 if newest is not None else None
        link_stats = getattr(self.link, "stats", None)  # not every MavlinkLink keeps counters
        last_error = getattr(self.link, "last_error", None)
        hb = self._last_heartbeat_rx_ns
        return PoseTrackerStatus(
            pose_ok=bool(ts.converged and pose_age_s is not None and pose_age_s * 1e9 <= self.config.max_pose_age_ns),
            pose_age_s=pose_age_s,
            pose_status=self._pose_status(),
            timesync=TimesyncStatus(
                converged=ts.converged, offset_ns=ts.offset_ns,
                rtt_ms=ts.last_rtt_ns / 1e6 if ts.last_rtt_ns is not None else None,
                rtt_min_ms=ts.rtt_min_ns / 1e6 if ts.rtt_min_ns is not None else None,
                jitter_ms=ts.jitter_ns / 1e6 if ts.jitter_ns is not None else None,
                samples=ts.stats["samples"], rejected=ts.stats["rejected"], resets=ts.stats["resets"],
                last_reset_reason=ts.last_reset_reason),
            streams=MappingProxyType(dict(self._stream_state)),
            rates_hz=MappingProxyType(dict(self._rates_hz)),
            autopilot_heartbeat_age_s=(now - hb) / 1e9 if hb is not None else None,
            link=MappingProxyType(dict(link_stats) if isinstance(link_stats, dict) else {}),
            link_last_error=None if last_error is None else str(last_error),
            tracker=MappingProxyType(dict(self.stats)))

    @property
    def autopilot_base_mode(self) -> int | None:
        """base_mode (MAV_MODE_FLAG bits) of the autopilot's last HEARTBEAT; None before one arrived."""
        return self._autopilot_base_mode

    @property
    def autopilot_armed(self) -> bool | None:
        """Whether the autopilot's last HEARTBEAT said armed (MAV_MODE_FLAG_SAFETY_ARMED); None before one."""
        mode = self._autopilot_base_mode
        return None if mode is None else bool(mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    # ----- receive ----------------------------------------------------------------------------------

    def _from_autopilot(self, msg: Any) -> bool:
        cfg = self.config
        return msg.get_srcSystem() == cfg.target_system and (
            cfg.target_component == 0 or msg.get_srcComponent() == cfg.target_component)

    def _handle(self, msg: Any, now: int) -> None:
        kind = msg.get_type()
        self._rx_counts[kind] += 1
        if not self._from_autopilot(msg):
            self.stats["rx_not_autopilot"] += 1
            return
        self._autopilot_heard = True
        if kind == "ATTITUDE":
            if self._pose_mappable(msg.time_boot_ms, now):
                self.buffer.add_attitude(self._to_companion(msg.time_boot_ms), msg.roll, msg.pitch, msg.yaw)
        elif kind == "LOCAL_POSITION_NED":
            if self._pose_mappable(msg.time_boot_ms, now):
                self.buffer.add_position(self._to_companion(msg.time_boot_ms), (msg.x, msg.y, msg.z))
        elif kind == "TIMESYNC":
            self._on_timesync(msg, now)
        elif kind == "COMMAND_ACK":
            self._on_command_ack(msg)
        elif kind == "HEARTBEAT":
            self._last_heartbeat_rx_ns = now
            self._autopilot_base_mode = int(msg.base_mode)
        elif kind == "GPS_GLOBAL_ORIGIN":
            self.autopilot_origin_e7 = (int(msg.latitude), int(msg.longitude), int(msg.altitude))
        elif kind == "PARAM_VALUE":
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else ""
            if name in self._params_wanted and math.isfinite(msg.param_value):
                self.params[name] = float(msg.param_value)
                self._params_missing.discard(name)
        elif hasattr(msg, "time_boot_ms"):
            self._check_boot(msg.time_boot_ms, now)

    def _check_boot(self, t_boot_ms: int, now: int) -> None:
        """Reboot / clock-jump check on every autopilot stamp (see TimesyncEstimator.on_boot_time)."""
        if self.timesync.on_boot_time(t_boot_ms, now):
            self._after_reset()

    def _pose_mappable(self, t_boot_ms: int, now: int) -> bool:
        self._check_boot(t_boot_ms, now)
        if not self.timesync.converged:
            self.stats["pose_dropped_unsynced"] += 1
            return False
        return True

    def _to_companion(self, t_boot_ms: int) -> int:
        return self.timesync.to_companion_ns(int(t_boot_ms) * 1_000_000)

    def _on_timesync(self, msg: Any, now: int) -> None:
        if msg.tc1 == 0:  # the autopilot measuring us: answer with our clock
            self.link.send(mavlink.MAVLink_timesync_message(now, msg.ts1))
            self.stats["timesync_answered"] += 1
            return
        self._replies_seen += 1
        resets = self.timesync.stats["resets"]
        self.timesync.on_reply(msg.tc1, msg.ts1, now)
        if self.timesync.stats["resets"] != resets:
            self._after_reset()

    def _on_command_ack(self, msg: Any) -> None:
        cmd = self._cmd
        if cmd is None or msg.command != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL or not self._ack_is_ours(msg):
            return
        name = POSE_STREAMS[cmd.msg_id]
        if msg.result == mavlink.MAV_RESULT_ACCEPTED:
            self._stream_state[name] = f"accepted at {self.config.stream_hz:g} Hz"
        elif msg.result in (mavlink.MAV_RESULT_IN_PROGRESS, mavlink.MAV_RESULT_TEMPORARILY_REJECTED):
            return  # keep waiting; the timeout resends
        else:
            entry = mavlink.enums["MAV_RESULT"].get(msg.result)
            self._stream_state[name] = f"refused: {entry.name if entry is not None else msg.result}"
        self._cmd = None

    def _ack_is_ours(self, msg: Any) -> bool:
        mav = getattr(self.link, "mav", None)
        target = (getattr(msg, "target_system", 0), getattr(msg, "target_component", 0))
        if mav is None or target == (0, 0):
            return True
        return target == (mav.srcSystem, mav.srcComponent)

    def _after_reset(self) -> None:
        """A time-sync reset: buffered times are untrustworthy; a rebooted autopilot forgot our streams."""
        self.buffer.clear()
        self._timesync.last_ns = None  # request at once
        self.stats["timesync_resets"] += 1
        if self._started:
            self._request_streams()

    # ----- send -------------------------------------------------------------------------------------

    def _request_streams(self) -> None:
        self._stream_queue = deque(POSE_STREAMS)
        self._cmd = None
        for name in POSE_STREAMS.values():
            self._stream_state[name] = "pending"

    def _service(self, now: int) -> None:
        if self._timesync.due(now, None if self.timesync.converged else self._timesync_fast_ns):
            tc1, ts1 = self.timesync.request(now)
            self.link.send(mavlink.MAVLink_timesync_message(tc1, ts1))
            self._timesync.mark(now)
            self.stats["tx_timesync"] += 1
        if self._heartbeat.due(now):
            self.link.send(heartbeat_msg())
            self._heartbeat.mark(now)
            self.stats["tx_heartbeat"] += 1
        if self._started:
            self._service_commands(now)
        self._service_params(now)
        self._update_rates(now)

    def _service_commands(self, now: int) -> None:
        cmd, cfg = self._cmd, self.config
        if cmd is None:
            if self._stream_queue:
                self._send_interval(_Command(self._stream_queue.popleft(), 0, now), now)
            return
        if now - cmd.sent_ns < cfg.command_timeout_ns and now >= cmd.sent_ns:
            return
        if cmd.attempts >= cfg.command_attempts:
            self._stream_state[POSE_STREAMS[cmd.msg_id]] = f"no COMMAND_ACK after {cmd.attempts} attempts"
            self._cmd = None
            return
        self._send_interval(cmd, now)

    def _service_params(self, now: int) -> None:
        r, cfg = self._params_round, self.config
        if not self._params_missing or r.attempts >= cfg.command_attempts or (
                r.attempts and 0 <= now - r.sent_ns < cfg.command_timeout_ns):
            return
        missing = [n for n in self._params_wanted if n in self._params_missing]  # in the order asked
        for name in missing:
            self.link.send(mavlink.MAVLink_param_request_read_message(
                cfg.target_system, cfg.target_component or 1, name.encode("ascii"), -1))
        r.attempts += 1
        r.sent_ns = now
        self.stats["tx_param_reads"] += len(missing)

    def _send_interval(self, cmd: _Command, now: int) -> None:
        cfg = self.config
        interval_us = 1e6 / cfg.stream_hz
        self.link.send(mavlink.MAVLink_command_long_message(
            cfg.target_system, cfg.target_component or 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
            min(cmd.attempts, 255), float(cmd.msg_id), interval_us, 0.0, 0.0, 0.0, 0.0, 0.0))
        cmd.attempts += 1
        cmd.sent_ns = now
        self._cmd = cmd
        self.stats["tx_commands"] += 1

    def _update_rates(self, now: int) -> None:
        t0 = self._rate_t0_ns
        if t0 is None or now < t0:
            self._rate_t0_ns = now
            self._rx_counts.clear()
            return
        elapsed = now - t0
        if elapsed >= self.config.rate_window_ns:
            self._rates_hz = {k: v * 1e9 / elapsed for k, v in sorted(self._rx_counts.items())}
            self._rx_counts.clear()
            self._rate_t0_ns = now

    def _pose_status(self) -> str:
        ts = self.timesync
        if not self._autopilot_heard:  # the actionable fact: nothing at all, not even its 1 Hz HEARTBEAT
            return self._silence_status()
        if not ts.converged:
            if self._replies_seen == 0:
                return (f"waiting for TIMESYNC replies from the autopilot (system {self.config.target_system}); "
                        "no pose can be time-tagged until they arrive")
            return (f"time sync converging ({ts.samples}/{ts.config.converge_samples} TIMESYNC samples"
                    + (f", last reset: {ts.last_reset_reason}" if ts.last_reset_reason else "") + ")")
        return self.buffer.status()

    def _silence_status(self) -> str:
        """Nothing heard from the autopilot since the tracker started listening: say so, where, and for how long."""
        silent_s = max(0.0, (self.clock.now_ns() - self._listening_since_ns) / 1e9)
        where = f" on {self.link_name}" if self.link_name else ""
        return (f"no HEARTBEAT from the autopilot (system {self.config.target_system}){where} for {silent_s:.0f} s: "
                "is it connected, is the link's URL right?")
