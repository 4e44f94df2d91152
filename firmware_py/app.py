"""The payload program on the companion computer, assembled: what `pilescan-payload` runs.

`PayloadApp` is the one composition root: it opens the hardware named by URLs (MAVLink link, I2C bus,
PWM output, or the TFMini's serial port: DESIGN section 7), or takes already-open parts, and builds the
pose tracker, the rangefinder's driver (LIDAR-Lite, or TFMini: `--rangefinder`), sweeping servo, sample
log and the `PayloadLoop` (500 Hz, or paced by the TFMini's frames) on the real monotonic clock, or on
an injected one; then runs the loop until told to stop. The SITL's lockstep runner
(`sitl.runners.lockstep_payload.fly_firmware`) runs this same app with its simulated clock, link,
bus and servo injected, plus its `on_tick` hook and log opener (faults, power cut).

Around the loop, through its `should_stop` hook (called every tick, so each check is cheap):

- stop conditions: `request_stop` (the CLI's SIGINT/SIGTERM handlers call it), `duration_s`, and
  with `stop_on_disarm` the autopilot's HEARTBEAT showing disarmed after it had shown armed;
- health to the ground station at 1 Hz (`firmware_py.health`), sent on the pose tracker's link;
- a progress line on stderr every few seconds unless quiet;
- SET_GPS_GLOBAL_ORIGIN (indoor EKF origin) re-sent every few seconds until LOCAL_POSITION_NED arrives.

The optional live UDP stream (`firmware_py.live_stream`) is hooked in by handing the loop a sink that
forwards every record to the log and to the stream, so the loop itself is unchanged.

Link security (`signing`, `--signing-key FILE`): the MAVLink link signs everything it sends and drops
unsigned, forged and replayed frames (`firmware_py.hal.signing`); the live stream's datagrams carry an
authentication tag made with the same key, stamped on the link's signing clock. The start-up line and
STATUSTEXT say the link is signed; the progress line counts refused frames. `device_key` (the CLI sets it to
the same key when the I2C bus or PWM output is the networked SITL's device bridge) authenticates that
bridge connection: a wrong key, or a key on one side only, fails at start-up in one line.

Shutdown, whatever stopped the loop (and also after an error): the loop has already tagged and logged
its pending readings (flagged if their pose never came); a STATUSTEXT says why we stop; the log is
closed (its last partial block and its end record written and fsync'd: the ground station tells it from a log
cut short); the servo PWM is disabled; the stream, the link
and the bus are closed. Each step runs even if an earlier one failed, and a failure is reported, not
hidden.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, BinaryIO, TextIO

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.cli import RunFailure, UserError
from firmware_py.core.flag_tally import describe_flag_counts
from firmware_py.core.pose_source import EKF_SOURCE_PARAMS, PoseSource
from firmware_py.core.samplelog import UNPOSED, SampleFlags, SampleLogWriter
from firmware_py.core.sensor import Rangefinder
from firmware_py.drivers.lidarlite import (
    LidarLite,
    LidarLiteConfig,
    preset_by_name,
)
from firmware_py.drivers.servo import SweepServo
from firmware_py.drivers.tfmini import StreamCheck, Tfmini
from firmware_py.hal import Clock, I2CBus, MavlinkLink, PwmOutput
from firmware_py.hal.backends import open_i2c
from firmware_py.hal.clock import MonotonicClock
from firmware_py.hal.mavlink_link import open_mavlink
from firmware_py.hal.pwm import open_pwm
from firmware_py.hal.uart import DEFAULT_BAUD, SerialPort, open_uart
from firmware_py.health import TEXT_PREFIX, HealthMonitor, HealthSnapshot, HealthStatus, SensorState, statustext_msgs
from firmware_py.live_stream import LiveStreamSender
from firmware_py.log_room import check_destination, describe_room, room_s, room_warning
from firmware_py.payload import COUNTED_FLAGS, LoopStats, PayloadLoop, RangeSensor
from firmware_py.payload_config import PayloadConfig, is_finite_number
from firmware_py.pose import set_gps_global_origin_msg
from firmware_py.pose_tracker import PoseTracker
from firmware_py.preflight import (
    MIN_PREFLIGHT_S,
    PREFLIGHT_SWEEPS,
    RANGE_FAILURE,
    Check,
    MemorySink,
    NoPose,
    PreflightResult,
    Verdict,
    autopilot_check,
    ekf_source_check,
    log_check,
    loop_check,
    opening_check,
    origin_check,
    pose_check,
    rangefinder_check,
    sweep_check,
)

PROG = "pilescan-payload"
ORIGIN_RESEND_S = 5.0
ARM_POLL_HZ = 50.0
"""How often the payload reads the link while it waits for the autopilot to arm (--start-on-arm): the HEARTBEAT comes
at 1 Hz, so the start is within a heartbeat of the arming, and the streams are drained as they come."""
ORIGIN_ATTEMPTS = 5
PREFLIGHT_POSE_WAIT_S = 10.0
"""How long the preflight waits for a trusted pose before it samples: the time sync needs a few TIMESYNC round trips
and the autopilot's streams a second or two after they are asked for; a pose not there by then is a finding."""
PREFLIGHT_SILENT_S = 2.0
"""... cut short when nothing at all has come from the autopilot by then (its HEARTBEAT comes at 1 Hz)."""


@dataclass(frozen=True)
class LinkCounters:
    """The MAVLink link's counters at the end of a run (`MavlinkLink.stats`, by name)."""

    rx_bytes: int = 0
    rx_messages: int = 0
    rx_bad_bytes: int = 0
    rx_bad_frames: int = 0
    rx_seq_lost: int = 0
    tx_messages: int = 0
    tx_errors: int = 0
    io_errors: int = 0
    rx_signed: int = 0
    rx_unsigned: int = 0
    rx_bad_signature: int = 0
    rx_replayed: int = 0
    rx_unsigned_accepted: int = 0

    @classmethod
    def of(cls, stats: Mapping[str, int]) -> LinkCounters:
        """From a link's stats; a counter the link does not keep reads 0."""
        return cls(**{f.name: int(stats.get(f.name, 0)) for f in fields(cls)})

    @property
    def refused(self) -> int:
        """Frames refused for want of a valid signature: unsigned, forged or replayed."""
        return self.rx_unsigned + self.rx_bad_signature + self.rx_replayed


@dataclass(frozen=True)
class StreamCounters:
    """What the live stream sent (`LiveStreamSender.stats`)."""

    datagrams: int = 0
    records: int = 0
    send_errors: int = 0
    records_dropped: int = 0

    @classmethod
    def of(cls, stats: Mapping[str, int]) -> StreamCounters:
        return cls(**{f.name: int(stats.get(f.name, 0)) for f in fields(cls)})


@dataclass(frozen=True)
class PayloadResult:
    """How a run ended and what it produced."""

    stop_reason: str
    out_path: Path
    elapsed_s: float
    readings: int
    records_logged: int
    records_flagged: int
    loop: LoopStats | None
    lidar_counters: dict[str, int]
    stream: StreamCounters | None
    health: HealthStatus | None
    link: LinkCounters
    pose_status: str
    close_errors: tuple[str, ...] = ()
    signing_active: bool = False


class _RecordSink:
    """What the loop logs into: the sample log, plus the live stream when there is one; counts records."""

    def __init__(self, log: SampleLogWriter, stream: LiveStreamSender | None) -> None:
        self.log, self.stream = log, stream
        self.records = 0
        self.flagged = 0

    def append(self, records: Any) -> None:
        self.log.append(records)  # first: the log is the record, the stream only a preview
        if records.ndim == 0:  # the loop hands one record at a time, 500 a second
            self.records += 1
            self.flagged += 1 if records["flags"] else 0
        else:
            self.records += int(records.size)
            self.flagged += int(np.count_nonzero(records["flags"]))
        if self.stream is not None:
            self.stream.append(records)

    def flush(self) -> None:
        self.log.flush()
        if self.stream is not None:
            self.stream.flush()

    def close(self) -> None:
        self.log.close()


class PayloadApp:
    """The payload program (module docstring). `run()` once; `request_stop()` from anywhere.

    Args:
        cfg: the configuration.
        clock: the payload clock (default: the real monotonic clock).
        link, bus, pwm, uart: already-open hardware to use instead of opening the configured URLs (the
            I2C bus for a LIDAR-Lite, the serial port for a TFMini); the app takes ownership and closes
            them at the end.
        err: where progress, warnings and the summary go (None: nowhere).
        prog: the name prefixed to those lines.
        open_log: opens the sample log file, `open(path, mode)` by default (the SITL's disk faults and
            power cut give their own file).
        on_tick: the host's hook, called with the clock's time at every tick before the stop checks
            (the SITL's fault schedule and mission); what it raises ends the run like any error.
    """

    def __init__(self, cfg: PayloadConfig, *, clock: Clock | None = None, link: MavlinkLink | None = None,
                 bus: I2CBus | None = None, pwm: PwmOutput | None = None, uart: SerialPort | None = None,
                 err: TextIO | None = sys.stderr,
                 prog: str = PROG, open_log: Callable[[Path, str], BinaryIO] = open,
                 on_tick: Callable[[int], None] | None = None) -> None:
        self.cfg = cfg
        self.clock = clock or MonotonicClock()
        self.link, self.bus, self.pwm, self.uart = link, bus, pwm, uart
        self._link_url: str | None = None  # the URL of the link the app opened (a link given names itself, or not)
        self._open_log, self._on_tick = open_log, on_tick
        self.err, self.prog = err, prog
        self.lidar: RangeSensor | None = None  # the rangefinder's driver: LidarLite or Tfmini
        self.tracker: PoseTracker | None = None
        self.stream: LiveStreamSender | None = None
        self.log: SampleLogWriter | None = None
        self.sink: _RecordSink | None = None
        self.loop: PayloadLoop | None = None
        self.health: HealthMonitor | None = None
        self._stop_reason: str | None = None
        self._ran = False
        self._was_armed = False
        self._next_status_ns = 0
        self._status_prev: tuple[int, int] | None = None
        self._origin_sent = 0
        self.origin_disagreement: str | None = None  # set when the autopilot's EKF origin is not the one sent
        self._origin_checked: tuple[int, int, int] | None = None  # the autopilot's origin last compared with ours
        self._next_origin_ns = 0
        self._close_errors: list[str] = []
        self._log_room_low = False  # the log's file system holds less than the flight (`log_room`)
        self.health_errors = 0
        self._failed_since_ns: int | None = None

    # ----- control --------------------------------------------------------------------------------

    def request_stop(self, reason: str = "stop requested") -> None:
        """Ask the loop to stop at its next tick (safe from a signal handler or another thread).

        No lock: a signal handler runs in the main thread and would deadlock on one the loop holds;
        the first reason wins, and a race between two only decides which reason is reported.
        """
        if self._stop_reason is None:
            self._stop_reason = reason

    @property
    def stop_reason(self) -> str | None:
        return self._stop_reason

    def run(self) -> PayloadResult:
        """Open everything, run the loop until a stop condition, shut down cleanly (module docstring).

        Raises:
            UserError: the log exists (without force), or hardware cannot be opened (names the URL).
            OSError: the log cannot be written.
        """
        if self._ran:
            raise RuntimeError("a PayloadApp runs once")
        self._ran = True
        t_start = self.clock.now_ns()
        try:
            self._open()
            if self._stop_reason is None:
                self._say(f"logging to {self.cfg.out_path} at {self.cfg.rate_hz:g} Hz ({self._sensor_note()}); "
                          f"MAVLink {self.cfg.mavlink_url}, {self._sensor_port_note()}, PWM {self.cfg.pwm_url}"
                          + (f", stream {self.cfg.stream_url}" if self.cfg.stream_url else "")
                          + self._signing_note()
                          + ("; device bridge authenticated" if self.bridge_authenticated else ""))
                self._send_health([*self.health.event(
                    mavlink.MAV_SEVERITY_INFO,
                    f"started, {self.cfg.rate_hz:g} Hz" + (", link signed" if self.signing_active else "")),
                    *(self.health.event(mavlink.MAV_SEVERITY_WARNING, "log storage nearly full")
                      if self._log_room_low else []),
                    *self._pose_source_events()])
                self.loop.run(duration_s=self.cfg.duration_s, should_stop=self._should_stop)
            self.request_stop("duration reached")
        except BaseException as exc:
            self.request_stop(f"error: {_failure_detail(exc)}")
            raise
        finally:
            self._shutdown()
        return self._result((self.clock.now_ns() - t_start) / 1e9)

    def preflight(self, duration_s: float | None = None) -> PreflightResult:
        """Open the hardware as a flight does, run the loop for a few sweep periods into memory (no log is written),
        and judge what it saw (`firmware_py.preflight`). A part that cannot be opened is a failed check, not an
        error: the other parts are still checked. The ground station is sent the verdict as a STATUSTEXT. The flight's
        own start and stop conditions (--start-on-arm, --stop-on-disarm) and the live stream do not apply; --duration
        is the flight's, which the log card's room is checked against.

        duration_s: how long to sample, at least one sweep period; None: PREFLIGHT_SWEEPS sweep periods, at least
            MIN_PREFLIGHT_S.
        """
        if self._ran:
            raise RuntimeError("a PayloadApp runs once")
        self._ran = True
        cfg = self.cfg
        period_s = 1.0 / cfg.servo_waveform().frequency_hz
        if duration_s is None:
            duration_s = max(MIN_PREFLIGHT_S, PREFLIGHT_SWEEPS * period_s)
        if not (is_finite_number(duration_s) and duration_s > 0):
            raise ValueError(f"preflight duration must be > 0 s, got {duration_s!r}")
        # Less than a sweep period sees only part of the sweep, from wherever the shaft was: the sweep check would
        # judge a few sectors near one end. The checklist's first line says the time sampled.
        duration_s = max(duration_s, period_s)
        checks: list[Check] = [self._log_check()]
        sink, result = MemorySink(), None
        pose_ok_ticks: list[bool] = []
        try:
            for name, opener in (("autopilot link", self._open_link), ("rangefinder", self._open_sensor),
                                 ("servo PWM", self._open_pwm)):
                try:
                    opener()
                except (UserError, ValueError) as exc:
                    checks.append(opening_check(name, str(exc).splitlines()[0]))
                    if name == "rangefinder":
                        self.lidar = None  # a TFMini whose port opened but sends no frames: not sampled
            if self.link is not None:
                self._start_tracker()
                self._say(f"preflight: waiting up to {PREFLIGHT_POSE_WAIT_S:g} s for the pose, then sampling "
                          f"{duration_s:g} s (no log is written)")
                start = self.clock.now_ns()
                end_ns, silent_ns = start + round(PREFLIGHT_POSE_WAIT_S * 1e9), start + round(PREFLIGHT_SILENT_S * 1e9)
                self._pump_until(lambda: self.tracker.status().pose_ok, round(1e9 / cfg.rate_hz),
                                 lambda now: now >= end_ns or (now >= silent_ns and not self.tracker.autopilot_heard))
                if self.tracker.autopilot_heard:  # a silent autopilot has no parameters to give
                    self._wait_for_params()
            if self.lidar is not None and self.pwm is not None:
                if isinstance(self.lidar, Tfmini):
                    self.lidar.discard_input()
                self.loop = self._build_loop(sink, self.tracker or NoPose(), self.clock.now_ns())
                self.loop.run(duration_s=duration_s, should_stop=self._preflight_tick)
            elif self.link is not None:  # no samples to pose: the share of the window's pumps the pose was usable at
                end_ns = self.clock.now_ns() + round(duration_s * 1e9)

                def tally_pose() -> bool:
                    pose_ok_ticks.append(self.tracker.status().pose_ok)
                    return False
                self._pump_until(tally_pose, round(1e9 / cfg.rate_hz), lambda now: now >= end_ns)
            if self._stop_reason is not None:
                raise RunFailure(f"the preflight was stopped before it finished ({self._stop_reason})")
            checks += self._preflight_checks(sink.samples(), duration_s, pose_ok_ticks)
            result = PreflightResult(tuple(checks), duration_s, self.loop.stats.ticks if self.loop else 0)
            self.request_stop(result.statustext())
            if self.link is not None:  # as ArduPilot's pre-arm messages: CRITICAL when the flight should not go
                self._send_health(statustext_msgs(
                    mavlink.MAV_SEVERITY_INFO if result.passed else mavlink.MAV_SEVERITY_CRITICAL,
                    TEXT_PREFIX + result.statustext()))
        except BaseException as exc:
            self.request_stop(f"preflight error: {_failure_detail(exc)}")
            raise
        finally:
            self._shutdown()
        return result

    def _preflight_tick(self) -> bool:
        """The preflight loop's stop check: a stop asked for; the EKF origin sent again until it takes."""
        if self._stop_reason is not None:
            return True
        self._tend_origin(self.clock.now_ns())
        return False

    def _log_check(self) -> Check:
        """Whether the flight's log could be written where the configuration puts it, and the card's room."""
        out = Path(self.cfg.out_path)
        try:
            check_destination(out, self.cfg.force)
        except UserError as exc:
            return log_check(str(exc), None, None)
        room = room_s(out, self.cfg.rate_hz, self.cfg.records_per_block)
        room_line = None if room is None else f"{out}: room for {describe_room(room)} of samples"
        return log_check(None, room_line, room_warning(room, self.cfg.duration_s, self.cfg.rate_hz))

    def _preflight_checks(self, samples: np.ndarray, duration_s: float, pose_ok_ticks: Sequence[bool]) -> list[Check]:
        """The checks of what the preflight saw. pose_ok_ticks: without samples (no rangefinder opened), whether the
        pose was usable at each pump of the sampling window: its share stands for the samples' posed share. (The pose
        at the window's end alone failed a preflight whose autopilot's stream came a little late at that instant, on
        a machine kept busy: a snapshot, not a share.)"""
        cfg = self.cfg
        checks: list[Check] = []
        if self.tracker is not None:
            st = self.tracker.status()
            checks.append(autopilot_check(self.tracker.autopilot_heard, self.tracker.autopilot_armed,
                                          cfg.target_system, cfg.mavlink_url))
            if samples.size:
                posed_share = float(np.mean((samples["flags"] & int(UNPOSED)) == 0))
            else:
                posed_share = float(np.mean(pose_ok_ticks)) if len(pose_ok_ticks) else float(st.pose_ok)
            checks.append(pose_check(posed_share, st.pose_status, st.rates_hz, cfg.pose_stream_hz,
                                     st.timesync.rtt_ms, cfg.send_origin is not None))
            source = PoseSource.from_params(self.tracker.params) if self.tracker.params else None
            known = source is not None and source.known
            checks.append(ekf_source_check(known, source.describe() if known else None,
                                           known and source.height_from_rangefinder, self.tracker.autopilot_heard))
            origin = origin_check(self.origin_disagreement)
            if origin is not None:
                checks.append(origin)
        if self.loop is not None:
            stats = self.loop.stats
            ranged = samples[(samples["flags"] & int(RANGE_FAILURE)) == 0]
            spec = cfg.sensor()
            checks.append(rangefinder_check(
                stats.ticks, stats.flagged(SampleFlags.NO_RETURN), stats.flagged(SampleFlags.SENSOR_ERROR),
                ranged["range_m"], duration_s, cfg.rate_hz, self._sensor_port_note()))
            if not cfg.loop_config().paced_by_sensor:
                checks.append(loop_check(stats.ticks, stats.overruns, cfg.rate_hz))
            checks.append(sweep_check(ranged["servo_rad"], ranged["range_m"], cfg.servo_waveform().amplitude_rad,
                                      spec["range_sigma_m"], spec["range_sigma_rel"], cfg.pwm_url))
        elif self.lidar is not None or self.pwm is not None:  # one of the two opened: say what could not be judged
            missing = "the rangefinder" if self.lidar is None else "the servo's output"
            checks.append(Check("servo sweep", Verdict.WARN, f"not checked: {missing} could not be opened"))
        return checks

    # ----- start-up -------------------------------------------------------------------------------

    def _open(self) -> None:
        cfg = self.cfg
        out = Path(cfg.out_path)
        check_destination(out, cfg.force)  # before the hardware and the pose wait: a bad path fails at once
        low = room_warning(room_s(out, cfg.rate_hz, cfg.records_per_block), cfg.duration_s, cfg.rate_hz)
        if low:
            self._warn(low)
        self._log_room_low = low is not None  # said on the ground station too, with "started"
        self._open_link()
        self._open_sensor()
        self._open_pwm()
        if cfg.stream_url is not None:
            signer = self.link.signer
            self.stream = LiveStreamSender(
                cfg.stream_url, cfg.stream_records_per_datagram, key=cfg.signing.key if cfg.signing else None,
                stamp_source=signer.now if signer is not None else None)
        self._start_tracker()
        if cfg.start_on_arm:
            self._wait_for_arm()
            if self._stop_reason is not None:
                return  # stopped on the ground: no log
            self.tracker.request_params(EKF_SOURCE_PARAMS)  # those the autopilot, maybe still booting, missed
        self._wait_for_pose()
        self._wait_for_params()
        if isinstance(self.lidar, Tfmini):
            self.lidar.discard_input()  # frames that waited through the pose wait have lost their times
        t0_ns = self.clock.now_ns()  # the sweep's time origin, written in the header before the first sample
        self.log = SampleLogWriter(out, cfg.log_header(sweep_t0_s=t0_ns * 1e-9, autopilot_params=self.tracker.params),
                                   records_per_block=cfg.records_per_block, fsync=cfg.fsync, overwrite=cfg.force,
                                   opener=self._open_log)
        self.sink = _RecordSink(self.log, self.stream)
        self.loop = self._build_loop(self.sink, self.tracker, t0_ns)
        self.health = HealthMonitor(self.loop.t0_ns, cfg.health_period_s)
        self._next_status_ns = self.loop.t0_ns + round(cfg.status_period_s * 1e9)
        self._status_prev = (self.loop.t0_ns, 0)

    def _open_link(self) -> None:
        cfg = self.cfg
        if self.link is None:
            self.link = _opening("MAVLink link", cfg.mavlink_url,
                                 lambda: open_mavlink(cfg.mavlink_url, signing=cfg.signing))
            self._link_url = cfg.mavlink_url
        elif cfg.signing is not None and not self.signing_active:
            self._warn("the MAVLink link given to the payload does not sign; signing applies to links it opens")

    def _open_sensor(self) -> None:
        cfg = self.cfg
        if cfg.rangefinder is Rangefinder.TFMINI:
            self._open_tfmini()
            return
        if self.bus is None:
            self.bus = _opening("I2C bus", cfg.i2c_url, lambda: open_i2c(cfg.i2c_url, key=cfg.device_key))
        lidar_cfg = LidarLiteConfig(address=cfg.i2c_address, preset=preset_by_name(cfg.preset),
                                    busy_timeout_ns=cfg.busy_deadline_ns())
        self.lidar = _opening(f"LIDAR-Lite at 0x{cfg.i2c_address:02x} on", cfg.i2c_url,
                              lambda: LidarLite(self.bus, self.clock, lidar_cfg))

    def _open_pwm(self) -> None:
        cfg = self.cfg
        if self.pwm is None:
            self.pwm = _opening("PWM output", cfg.pwm_url, lambda: open_pwm(
                cfg.pwm_url, i2c_opener=open_i2c, link=self.link, mav=getattr(self.link, "mav", None),
                key=cfg.device_key))

    def _start_tracker(self) -> None:
        """The pose tracker on the open link: streams asked for, the EKF origin sent, the EKF sources read."""
        cfg = self.cfg
        self.tracker = PoseTracker(self.link, self.clock, cfg.target_system, cfg.pose_stream_hz,
                                   target_component=cfg.target_component,
                                   max_pose_age_ns=round(cfg.max_pose_age_s * 1e9), link_name=self._link_url)
        self._send_origin(self.clock.now_ns())
        self.tracker.start()
        self.tracker.request_params(EKF_SOURCE_PARAMS)

    def _build_loop(self, sink: Any, pose: Any, t0_ns: int) -> PayloadLoop:
        cfg = self.cfg
        loop_cfg = cfg.loop_config()
        # A loop paced by its sensor ticks a little before or after a PWM frame boundary: half a tick early
        # still sends that frame's pulse (`SweepServo.early_s`); a loop on its own grid ticks on the boundary.
        servo = (SweepServo(self.pwm, cfg.servo_waveform(), cfg.servo, early_s=0.5 / cfg.rate_hz)
                 if loop_cfg.paced_by_sensor else SweepServo(self.pwm, cfg.servo_waveform(), cfg.servo))
        return PayloadLoop(self.lidar, servo, pose, self.clock, sink, loop_cfg, t0_ns=t0_ns)

    def _open_tfmini(self) -> None:
        """Open the TFMini's serial port and check that it streams frames (one line saying what is wrong
        if it does not: nothing arrives, or bytes that never form a frame)."""
        cfg = self.cfg
        if self.uart is None:
            self.uart = _opening("TFMini serial port", cfg.uart_url, lambda: open_uart(cfg.uart_url))
        tfmini = Tfmini(self.uart, self.clock, cfg.tfmini_config())
        self.lidar = tfmini
        wait_s = cfg.sensor_start_timeout_s
        seen = _opening("TFMini serial port", cfg.uart_url,
                        lambda: tfmini.check_streaming(round(wait_s * 1e9)))
        if seen is StreamCheck.SILENT:
            raise RunFailure(f"no data from the TFMini on {cfg.uart_url} within {wait_s:g} s: check the port, "
                            "its wiring (the TFMini's TX to the Pi's RX, 5 V, ground) and its power")
        if seen is StreamCheck.NO_FRAMES:
            raise RunFailure(f"bytes arrive on {cfg.uart_url} but no valid TFMini frame within {wait_s:g} s: "
                            f"is the part set to {cfg.uart_baud()} baud (the factory rate is {DEFAULT_BAUD})?")

    def _sensor_note(self) -> str:
        if self.cfg.rangefinder is Rangefinder.TFMINI:
            return "TFMini, paced by its frames"
        return f"preset {self.cfg.preset}"

    def _sensor_port_note(self) -> str:
        if self.cfg.rangefinder is Rangefinder.TFMINI:
            return f"TFMini {self.cfg.uart_url}"
        return f"I2C {self.cfg.i2c_url}"

    def _wait_for_arm(self) -> None:
        """Pump the link (the servo idle, no log open) until the autopilot's HEARTBEAT shows armed or a stop is asked
        for: a payload started with the companion computer waits through the time on the ground."""
        self._say("waiting for the autopilot to arm (--start-on-arm): the servo is idle and nothing is logged")
        self._send_health(statustext_msgs(mavlink.MAV_SEVERITY_INFO, TEXT_PREFIX + "waiting for arm"))
        if self._pump_until(lambda: bool(self.tracker.autopilot_armed), round(1e9 / ARM_POLL_HZ)):
            self._say("the autopilot armed: starting")

    def _wait_for_pose(self) -> None:
        """Pump the link until the pose is trusted, the wait runs out or a stop is asked for."""
        if self.cfg.wait_for_pose_s <= 0:
            return
        end_ns = self.clock.now_ns() + round(self.cfg.wait_for_pose_s * 1e9)
        if not self._pump_until(lambda: self.tracker.status().pose_ok, round(1e9 / self.cfg.rate_hz),
                                lambda now: now >= end_ns) and self._stop_reason is None:
            self._warn(f"no trusted pose after {self.cfg.wait_for_pose_s:g} s; sampling anyway")

    def _pump_until(self, done: Callable[[], bool], period_ns: int,
                    expired: Callable[[int], bool] = lambda _now: False) -> bool:
        """Pump the link every period_ns, sending the EKF origin again when it is due, until done(); False when a stop
        is asked for or expired(now) first (the pose and arm waits)."""
        while self._stop_reason is None and not done():
            now = self.clock.now_ns()
            if expired(now):
                return False
            if self._origin_sent and now >= self._next_origin_ns:
                self._send_origin(now)
            self.clock.sleep_until_ns(now + period_ns)
            self.tracker.pump()
        return self._stop_reason is None

    def _pose_source_events(self) -> list[Any]:
        """Say what the autopilot's pose comes from (its EKF sources, as read at start), and warn the operator, on the
        console and as a STATUSTEXT the ground station shows, before the survey is flown, when its height comes
        from the downward rangefinder: over a stockpile that is the height above the pile, and every point of a
        sweep is placed low by a share of the pile's height. The ground station measures and takes out that share
        when the flight crosses the pile at different heights below it, but a barometer height needs no repair."""
        source = PoseSource.from_params(self.tracker.params) if self.tracker.params else None
        if source is None or not source.known:
            return []
        self._say(f"pose from the autopilot: {source.describe()}")
        if not source.height_from_rangefinder:
            return []
        self._warn(f"the autopilot takes its height from the downward rangefinder "
                   f"({source.rangefinder_height_setting}): over a stockpile that is "
                   "the height above the pile, so the logged height follows the pile and places every point low by "
                   "a share of the pile's height. The ground station measures and takes out that share when the "
                   "flight crosses the pile, but for a survey a barometer height is surer (EK3_SRC1_POSZ = 1, "
                   "EK3_RNG_USE_HGT = -1)")
        return self.health.event(mavlink.MAV_SEVERITY_WARNING, "EKF height from rangefinder")

    def _wait_for_params(self) -> None:
        """Pump the link until the autopilot has answered the EKF source reads (or they timed out), for at most
        param_wait_s, and at most 1 s while nothing at all comes from the autopilot."""
        if self.cfg.param_wait_s <= 0:
            return
        start = self.clock.now_ns()
        end_ns = start + round(self.cfg.param_wait_s * 1e9)
        silent_end_ns = start + min(round(self.cfg.param_wait_s * 1e9), 1_000_000_000)
        period_ns = round(1e9 / self.cfg.rate_hz)
        while self._stop_reason is None and not self.tracker.params_settled:
            now = self.clock.now_ns()
            if now >= end_ns or (now >= silent_end_ns and not self.tracker.autopilot_heard):
                break
            self.clock.sleep_until_ns(now + period_ns)
            self.tracker.pump()
        if not self.tracker.params and self.tracker.autopilot_heard:
            self._warn("the autopilot did not answer its EKF source parameters (EK3_SRC1_*): the log will not say "
                       "what the pose came from")

    @property
    def bridge_authenticated(self) -> bool:
        """Whether the I2C bus or the PWM output is a device bridge connection that authenticated."""
        return any(getattr(getattr(h, "conn", None), "authenticated", False) for h in (self.bus, self.pwm))

    @property
    def signing_active(self) -> bool:
        """Whether the MAVLink link signs and checks (it was opened with a key)."""
        return self.link is not None and self.link.signing_active

    def _signing_note(self) -> str:
        if not self.signing_active:
            return ""
        signer = self.link.signer
        cfg = signer.config if signer is not None else self.cfg.signing
        if cfg is None:
            return "; MAVLink signing on"
        note = f"; MAVLink signing on (link id {cfg.link_id}"
        note += ", unsigned frames accepted)" if cfg.allow_unsigned else ", unsigned frames refused)"
        if self.stream is not None and self.stream.authenticated:
            note += ", stream authenticated"
        return note

    def auth_rejects(self) -> int:
        """Frames the link refused: unsigned, forged or replayed (0 without signing)."""
        return LinkCounters.of(self.link.stats).refused

    # ----- every tick (PayloadLoop's should_stop) -------------------------------------------------

    def _should_stop(self) -> bool:
        if self._stop_reason is not None:
            return True
        now = self.clock.now_ns()
        if self._on_tick is not None:
            self._on_tick(now)
        if self.health.due(now):
            before = self.health.sensor_state
            self._send_health(self.health.update(self.snapshot(now)))
            self._sensor_state_line(before, self.health.sensor_state, now)
            if self.stream is not None:
                self.stream.flush()
        if not self.cfg.quiet and now >= self._next_status_ns:
            self._status_line(now)
        self._tend_origin(now)
        if self.cfg.stop_on_disarm:
            armed = self.tracker.autopilot_armed
            if armed:
                self._was_armed = True
            elif armed is False and self._was_armed:
                self.request_stop("autopilot disarmed")
        return self._stop_reason is not None

    def snapshot(self, now_ns: int) -> HealthSnapshot:
        """The health counters now (for `HealthMonitor`)."""
        st = self.tracker.status()
        c = self.lidar.counters()
        stats = self.loop.stats
        return HealthSnapshot(
            t_ns=now_ns, readings=stats.ticks, logged=self.sink.records,
            sensor_errors=c.sensor_errors, pose_ok=st.pose_ok, pose_age_s=st.pose_age_s,
            pose_status=st.pose_status, timesync_converged=st.timesync.converged,
            autopilot_heard=self.tracker.autopilot_heard,
            stale=stats.flagged(UNPOSED), overruns=stats.overruns,
            sensor_error_samples=stats.flagged(SampleFlags.SENSOR_ERROR))

    def _sensor_state_line(self, before: SensorState, after: SensorState, now: int) -> None:
        """Tell the operator once when the rangefinder stops giving readings (unplugged, dead) and once
        when it gives them again; the STATUSTEXTs say the same to the ground station."""
        if after is SensorState.FAILED and before is not SensorState.FAILED:
            self._failed_since_ns = now
            self._warn(f"the rangefinder fails every reading ({self._sensor_port_note()}): samples are logged "
                       "flagged until it answers again")
        elif before is SensorState.FAILED and after is not SensorState.FAILED and self._failed_since_ns is not None:
            self._say(f"the rangefinder answers again after {(now - self._failed_since_ns) / 1e9:.1f} s")
            self._failed_since_ns = None

    def _send_health(self, msgs: list[Any]) -> None:
        for msg in msgs:
            try:
                self.link.send(msg)
            except (OSError, ValueError) as exc:  # health must never stop the payload
                self.health_errors += 1
                if self.health_errors == 1:
                    self._warn(f"health message not sent: {exc}")

    def _tend_origin(self, now: int) -> None:
        """Every tick (the flight's and the preflight's): the EKF origin sent again until it takes, and the autopilot's
        origin compared with it once it says one."""
        if self._origin_sent and now >= self._next_origin_ns:
            self._send_origin(now)
        if self.origin_disagreement is None and self.tracker is not None:
            theirs = self.tracker.autopilot_origin_e7
            if theirs is not None and theirs != self._origin_checked:  # once per origin said, not every tick
                self._origin_checked = theirs
                self._check_origin(theirs)

    def _send_origin(self, now: int) -> None:
        """SET_GPS_GLOBAL_ORIGIN, again every few seconds until LOCAL_POSITION_NED arrives (a few tries)."""
        origin = self.cfg.send_origin
        if origin is None:
            return
        if self._origin_sent and (self.tracker.buffer.ever_position or self._origin_sent >= ORIGIN_ATTEMPTS):
            self._origin_sent = 0  # done: stop checking
            return
        self.link.send(set_gps_global_origin_msg(*origin, target_system=self.cfg.target_system))
        self._origin_sent += 1
        self._next_origin_ns = now + round(ORIGIN_RESEND_S * 1e9)

    def _check_origin(self, theirs: tuple[int, int, int]) -> None:
        """The autopilot's EKF origin (GPS_GLOBAL_ORIGIN) against the one we sent: positions about another
        point put the header's storage frame (the site about the origin sent) in the wrong place."""
        sent = self.cfg.send_origin
        if sent is None:
            return
        msg = set_gps_global_origin_msg(*sent)
        if theirs == (msg.latitude, msg.longitude, msg.altitude):
            return
        self.origin_disagreement = (f"the autopilot's EKF origin is {theirs[0] / 1e7:.7f}, {theirs[1] / 1e7:.7f}, "
                                    f"{theirs[2] / 1e3:g} m, not the {sent[0]:.7f}, {sent[1]:.7f}, {sent[2]:g} m sent: "
                                    "the log header's storage frame does not match its positions")
        self._warn(self.origin_disagreement)

    def _status_line(self, now: int) -> None:
        t_prev, n_prev = self._status_prev
        n = self.loop.stats.ticks
        rate = (n - n_prev) * 1e9 / (now - t_prev) if now > t_prev else 0.0
        self._status_prev = (now, n)
        self._next_status_ns = now + round(self.cfg.status_period_s * 1e9)
        st = self.tracker.status()
        age = st.pose_age_s
        pose = f"pose age {age:.3f} s" if age is not None else "no pose yet"
        if not st.pose_ok:  # whole: a cut status ended "until they arrive" as "unt)"
            pose += f" ({st.pose_status})"
        auth = f"  refused frames {self.auth_rejects()}" if self.signing_active else ""
        self._say(f"{(now - self.loop.t0_ns) / 1e9:7.1f} s  {rate:5.0f} Hz  samples {self.sink.records} "
                  f"{self._samples_detail()}  "
                  f"overruns {self.loop.stats.overruns}{auth}  {pose}")

    def _samples_detail(self) -> str:
        """What the log holds, counted from the samples' own flags (`firmware_py.core.flag_tally`):
        "(usable 5712; flagged: no return 120, sensor error 168)"."""
        n, flagged = self.sink.records, self.sink.flagged
        counts = dict(zip(COUNTED_FLAGS, self.loop.stats.flag_counts, strict=True))
        detail = f"; flagged: {describe_flag_counts(counts)}" if flagged else ""
        return f"(usable {n - flagged}{detail})"

    # ----- shutdown -------------------------------------------------------------------------------

    def _shutdown(self) -> None:
        reason = self._stop_reason or "stopped"
        if self.health is not None and self.link is not None:
            self._step("stop message", lambda: self._send_health(
                self.health.event(mavlink.MAV_SEVERITY_CRITICAL if reason.startswith("error")
                                  else mavlink.MAV_SEVERITY_NOTICE, f"stopping: {reason}")))
        if self.log is not None:
            self._step("closing the sample log", self.log.close)
        if self.pwm is not None:
            self._step("disabling the servo PWM", self.pwm.disable)
            self._step("closing the servo PWM", self.pwm.close)
        if self.stream is not None:
            self._step("closing the live stream", self.stream.close)
        if self.link is not None:
            self._step("closing the MAVLink link", self.link.close)
        if self.bus is not None:
            self._step("closing the I2C bus", self.bus.close)
        if self.uart is not None:
            self._step("closing the TFMini serial port", self.uart.close)

    def _step(self, what: str, action: Callable[[], Any]) -> None:
        try:
            action()
        except Exception as exc:  # every step runs; a failure is reported, not hidden
            msg = f"{what} failed: {type(exc).__name__}: {exc}"
            self._close_errors.append(msg)
            self._warn(msg)

    def _result(self, elapsed_s: float) -> PayloadResult:
        loop = self.loop
        st = self.tracker.status() if self.tracker is not None else None
        res = PayloadResult(
            stop_reason=self._stop_reason or "stopped", out_path=Path(self.cfg.out_path), elapsed_s=elapsed_s,
            readings=loop.stats.ticks if loop else 0, records_logged=self.sink.records if self.sink else 0,
            records_flagged=self.sink.flagged if self.sink else 0, loop=loop.stats if loop else None,
            lidar_counters=self.lidar.counters().as_dict() if self.lidar else {},
            stream=StreamCounters.of(self.stream.stats) if self.stream else None,
            health=self.health.status() if self.health else None,
            link=LinkCounters.of(self.link.stats) if self.link is not None else LinkCounters(),
            pose_status=st.pose_status if st else "", close_errors=tuple(self._close_errors),
            signing_active=self.signing_active)
        detail = f" {self._samples_detail()}" if self.sink is not None and loop is not None else ""
        if self.log is None and self.cfg.start_on_arm:
            self._say(f"stopped ({res.stop_reason}) after {elapsed_s:.1f} s before the autopilot armed: no log "
                      "written")
        else:
            self._say(f"stopped ({res.stop_reason}) after {elapsed_s:.1f} s: {res.records_logged} samples{detail} "
                      f"in {res.out_path}")
        return res

    # ----- output ---------------------------------------------------------------------------------

    def _say(self, text: str) -> None:
        if not self.cfg.quiet:
            self._print(text)

    def _warn(self, text: str) -> None:
        self._print(f"warning: {text}")

    def _print(self, text: str) -> None:
        if self.err is not None:
            try:
                print(f"{self.prog}: {text}", file=self.err, flush=True)
            except (OSError, ValueError):
                pass  # a closed stderr must not stop the payload


def _failure_detail(exc: BaseException) -> str:
    """What the operator's ground station is told failed (e.g. "No space left on device"): the system's words, else the
    message's first line, else the exception's type."""
    detail = (getattr(exc, "strerror", None) or str(exc).splitlines()[0]) if str(exc) else ""
    return detail or type(exc).__name__


def _opening(what: str, url: str, opener: Callable[[], Any]) -> Any:
    """Open hardware; a failure becomes one line naming what and the URL (UserError, exit 2)."""
    try:
        return opener()
    except ValueError:
        raise  # already names the URL (malformed, unknown scheme)
    except (OSError, RuntimeError) as exc:  # I2CError is an OSError; RuntimeError: smbus2 missing
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise UserError(f"cannot open {what} {url}: {detail}") from exc


def run_payload(cfg: PayloadConfig, **kwargs: Any) -> PayloadResult:
    """Run the payload once (`PayloadApp(cfg, **kwargs).run()`)."""
    return PayloadApp(cfg, **kwargs).run()
