"""MAVLink 2 autopilot peer for any simulated `Vehicle`: what a GCS or the payload talks to in SITL.

`MavlinkVehicleServer` makes a `sitl.vehicle.api.Vehicle` look like an ArduCopter on a link:
heartbeat and telemetry streams (`streams`), commands with COMMAND_ACK (`commands`), the mission
and parameter micro-services (`missions`, `params`), TIMESYNC, STATUSTEXT, and a .tlog of
everything both ways. It has no thread and no clock of its own; in lockstep everything is timed by
the vehicle's simulated clock, so a run is deterministic and as fast as the CPU allows.

Lockstep use (tests, the in-process runner)::

    server_end, client_end = PipeTransport.pair()
    server = MavlinkVehicleServer(vehicle, server_end, tlog_path="flight.tlog")
    while flying:
        vehicle.step()
        server.update()              # every step, or every few (streams cannot beat that rate)
        client_parser.parse_buffer(client_end.recv())

Networked use (`pilescan-sitl serve`): `run_realtime(server, vehicle, speedup=1.0)` steps the
vehicle and paces it against the wall clock, with the server on `UdpTransport("udp:0.0.0.0:14550")`
so `mavproxy.py --master=udp:127.0.0.1:14550` (or QGC, or the payload) connects as to ArduPilot SITL.
While it runs, the link's own timing (stream rates, the mission-upload timeout) follows the wall
clock (`time_link_by`): a ground station reads at its own pace, whatever the speed-up.

Choices, where MAVLink or ArduPilot leave room (the micro-services' modules list theirs):

- Parsing: on a datagram link (`UdpTransport`) each datagram is parsed on its own, whole frames or
  nothing (`sitl.mavlink.datagrams`): junk, truncated headers and bad CRCs are dropped and counted
  (stats `rx_datagrams_dropped`, by reason in `rx_drops`) and can never hold back another frame.
  On a byte stream (the lockstep pipe) our own framer around pymavlink's decoder: a frame that
  fails its CRC costs one byte, not the whole frame length, so a corrupt length byte cannot swallow
  the valid frames after it.
- Peers: a UDP sender becomes a telemetry client only when a datagram of its held a valid frame
  (an authenticated one when signing); the transport's table is bounded and keeps live clients.
- Routing (`sitl.mavlink.outbox`): telemetry and the vehicle's own news go to every client; a
  reply (COMMAND_ACK, PARAM_VALUE for a read, the mission protocol, TIMESYNC, FTP refusals, a
  STATUSTEXT saying why a request was refused) goes to the sender that asked. STATUSTEXT answers
  are rate-limited per sender (`LinkLimits`), and dropped ones counted (`statustext_dropped`).
- The .tlog: what a sender makes us log (its frames, our replies to it) is rate-limited per client
  (senders the full client table refused share one budget), and the whole file is capped
  (`LinkLimits.tlog_max_bytes`); once full, one warning, no more writes. The STATUSTEXT budget is
  kept the same way.
- SYS_STATUS reports the sensors and controllers a flying ArduCopter reports, present, enabled and
  healthy, and the geofence bit healthy (no fence, no breach): MAVProxy says "fence breach" when
  that bit is clear. MAVLink FTP is refused (`sitl.mavlink.ftp`) so ground stations read the
  parameters with the classic protocol at once.
- Telemetry log timestamps are TLOG_EPOCH_US + simulated time, so two lockstep runs give identical
  logs (unless signing is on: signatures carry wall-clock timestamps).
- Signing (`signing=SigningConfig(...)`, `pilescan-sitl serve --signing-key FILE`): as the payload's
  links (`firmware_py.hal.mavlink_link`): everything sent is signed; unsigned, forged and replayed
  frames are refused (never handled, never logged) and counted in stats (`rx_unsigned`,
  `rx_bad_signature`, `rx_replayed`; `rx_signed`, `rx_unsigned_accepted`). On a listening
  `UdpTransport` a client only becomes a destination once one of its datagrams held an
  authenticated frame, so a client without the key hears nothing (and cannot aim our telemetry
  at a spoofed address).
"""

from __future__ import annotations

import logging
import math
import os
import struct
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, BinaryIO, Protocol

os.environ["MAVLINK20"] = "1"  # for mavutil users in this process; the v20 dialect below is MAVLink 2 anyway

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.geodesy import Home
from firmware_py.core.site import DEFAULT_SITE
from firmware_py.hal.mavlink_link import MavlinkFramer
from firmware_py.hal.signing import MavlinkSigner, SigningConfig
from sitl.mavlink import streams as tm
from sitl.mavlink.commands import Commands
from sitl.mavlink.datagrams import DatagramParser
from sitl.mavlink.ftp import FtpRefusal
from sitl.mavlink.missions import MissionItem, Missions
from sitl.mavlink.outbox import Peer
from sitl.mavlink.params import ParamProvider, Params
from sitl.mavlink.ratelimit import KeyedBuckets, Rate
from sitl.mavlink.streams import TLOG_EPOCH_US, StreamSchedule
from sitl.mavlink.transport import Transport
from sitl.vehicle.api import Vehicle, VehicleState

STATUSTEXT_LEN = 50
TLOG_RECORD_HEADER_LEN = 8  # the big-endian microsecond timestamp before each frame
log = logging.getLogger(__name__)


class PoseErrors(Protocol):
    """One message's pose error (`sitl.sensing.noise.PoseNoiser`): attitude rad, position NED m."""

    def attitude(self) -> tuple[float, float, float]: ...

    def position(self) -> tuple[float, float, float]: ...


STATUSTEXT_RATE = Rate(per_s=5.0, burst=20)
TLOG_RX_RATE = Rate(per_s=200.0, burst=2000)


@dataclass(frozen=True)
class LinkLimits:
    """What one sender can cost the others; every limit is far above what a ground station uses.

    statustext: answers to one sender's refused requests. A ground station's operator reads a few
    a second; MAVProxy re-sends a refused request about once a second, so 5/s with a burst of 20
    never drops a text an operator could read, and caps a flood's at 5/s.
    tlog_rx: frames a sender makes us log (its own, and our replies to it). A ground station sends
    a few tens a second (heartbeat, requests; a mission upload ~2 per item), and our telemetry
    (logged apart) is ~110/s; 200/s with a burst of 2000 logs every frame of a 1000-item upload.
    tlog_max_bytes: the whole .tlog; our telemetry alone is ~20 MB an hour, so 256 MB is half a day
    of flying, and what a flood can add stops there.
    """

    statustext: Rate = STATUSTEXT_RATE
    tlog_rx: Rate = TLOG_RX_RATE
    tlog_max_bytes: int = 256_000_000

    def __post_init__(self) -> None:
        if isinstance(self.tlog_max_bytes, bool) or not isinstance(self.tlog_max_bytes, int) \
                or self.tlog_max_bytes < 1:
            raise ValueError(f"the tlog cap must be a whole number of bytes >= 1, got {self.tlog_max_bytes!r}")


_NO_ASKER = object()
_STRANGERS = object()


class MavlinkVehicleServer:
    """Serves a Vehicle over MAVLink 2 as an ArduCopter-like autopilot; call update() after vehicle steps."""

    def __init__(self, vehicle: Vehicle, transport: Transport, tlog_path: str | os.PathLike[str] | None = None,
                 sysid: int = 1, compid: int = 1, home: Home = DEFAULT_SITE.corner,
                 signing: SigningConfig | MavlinkSigner | None = None,
                 extra_params: ParamProvider | None = None, limits: LinkLimits = LinkLimits()) -> None:
        if not isinstance(home, Home):
            raise ValueError(f"home must be a GeodeticPoint, got {home!r}")
        self.home = home  # also the EKF origin (GPS_GLOBAL_ORIGIN): indoors both are the storage's corner
        self.vehicle = vehicle
        self.transport = transport
        self.sysid, self.compid = sysid, compid
        self._mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if signing is not None and not isinstance(signing, MavlinkSigner):
            signing = MavlinkSigner(signing)
        self.signer: MavlinkSigner | None = signing
        if self.signer is not None:
            self.signer.attach(self._mav)  # the encoder signs; the framer's own decoder does not check
            self._framer = MavlinkFramer(mavlink.MAVLink(None), signer=self.signer)
        else:
            self._framer = MavlinkFramer(self._mav)  # the payload's framer: one parser for both ends
        self._datagrams = DatagramParser(self.signer)  # for a transport with recv_datagrams (UDP)
        self.limits = limits
        self._tlog: BinaryIO | None = Path(tlog_path).open("wb") if tlog_path is not None else None
        self._tlog_path = tlog_path
        self._tlog_bytes = 0
        self._tlog_budget = KeyedBuckets(limits.tlog_rx)
        self._statustext_budget = KeyedBuckets(limits.statustext)
        self._asker: Any = _NO_ASKER  # the sender of the message being handled
        self._clients: set[Any] = set()  # senders admitted as clients (for the operator's log)
        self._strangers: set[Any] = set()  # senders of this update's datagrams the full client table refused
        self._last_armed_mode: tuple[bool, int] | None = None
        self.stats: dict[str, Any] = {
            "rx_messages": 0, "rx_bad_bytes": 0, "rx_parse_errors": 0, "rx_not_for_us": 0,
            "tx_messages": 0, "handler_errors": 0, "rx_by_type": Counter(), "tx_by_type": Counter(),
            "rx_signed": 0, "rx_unsigned": 0, "rx_bad_signature": 0, "rx_replayed": 0, "rx_unsigned_accepted": 0,
            "rx_datagrams_dropped": 0, "rx_drops": {}, "statustext_dropped": 0, "tlog_frames_skipped": 0,
            "tlog_full": False, "peers_refused": 0, "ftp_refused": 0, "origin_refused": 0,
        }
        self._now_s = 0.0
        self._boot_epoch_s = 0.0  # vehicle time at which the autopilot last booted (time_boot_ms 0)
        self._silent_until_s = -math.inf  # rebooting until then: deaf and mute
        self._state: VehicleState | None = None
        # The vehicle's clock, cheaply when the vehicle offers it (JSBSim), else from its state.
        self._vehicle_time_s: Callable[[], float] = getattr(vehicle, "time_s", None) or (lambda: vehicle.state().t_s)
        self._link_clock: Callable[[], float] | None = None  # None: the link runs on simulated time
        self._statustext_id = 0
        self.streams = StreamSchedule()
        self.missions = Missions(vehicle, self.home, self._mav, self, self._link_now)
        self.params = Params(vehicle, extra_params, self._mav, self)
        self.commands = Commands(vehicle, self.streams, self._mav, self, self._build_stream_message,
                                 self._home_position, self._link_now)
        self.ftp = FtpRefusal(self._mav, self)
        self._handlers: dict[str, Callable[[Any], None]] = {
            "HEARTBEAT": self._ignore, "REQUEST_DATA_STREAM": self._ignore, "MISSION_ACK": self._ignore,
            "TIMESYNC": self._on_timesync, "SET_GPS_GLOBAL_ORIGIN": self._on_set_gps_global_origin,
            **self.commands.handlers, **self.params.handlers, **self.missions.handlers, **self.ftp.handlers,
        }
        self._builders: dict[int, Callable[[VehicleState], Any | None]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: lambda s: tm.heartbeat(self._mav, s),
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: lambda s: tm.sys_status(self._mav, s, self._rx_errors()),
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: lambda s: tm.system_time(self._mav, s, self._boot_ms),
            mavlink.MAVLINK_MSG_ID_ATTITUDE: lambda s: tm.attitude(self._mav, self._estimated(s, True), self._boot_ms),
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
                lambda s: tm.local_position(self._mav, self._estimated(s, False), self._boot_ms),
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
                lambda s: tm.global_position(self._mav, self._drifted(s), self._boot_ms, self.home),
            mavlink.MAVLINK_MSG_ID_VFR_HUD: lambda s: tm.vfr_hud(self._mav, s, self.home),
            mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: lambda _s: self.missions.mission_current(),
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: lambda _s: self._home_position(),
            mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
                lambda _s: tm.gps_global_origin(self._mav, self.home, self._now_s),
        }

    pose_noise: PoseErrors | None = None
    """The estimator's error on what ATTITUDE and LOCAL_POSITION_NED report (a SITL sensor-noise model):
    one draw per message; None: the true state, as before."""

    def _drifted(self, s: VehicleState) -> VehicleState:
        """The state the vehicle's estimator reports: the true one plus the vehicle's `pose_error` (an indoor
        EKF's drift, `sitl.sensing.pose_drift`), which its own guidance flies on too; the truth without one."""
        err = getattr(getattr(self, "vehicle", None), "pose_error", None)  # a bare seam (tests) has no vehicle
        if err is None or not any(err):
            return s
        n, e, d = s.pos_ned_m
        return replace(s, pos_ned_m=(n + err[0], e + err[1], d + err[2]),
                       yaw_rad=(s.yaw_rad + err[3] + math.pi) % (2 * math.pi) - math.pi)

    def _estimated(self, s: VehicleState, attitude: bool) -> VehicleState:
        """The state a message reports: the estimate (`_drifted`), with this message's pose noise if any."""
        s = self._drifted(s)
        noise = self.pose_noise
        if noise is None:
            return s
        if attitude:
            dr, dp, dy = noise.attitude()
            return replace(s, roll_rad=s.roll_rad + dr, pitch_rad=s.pitch_rad + dp, yaw_rad=s.yaw_rad + dy)
        dn, de, dd = noise.position()
        n, e, d = s.pos_ned_m
        return replace(s, pos_ned_m=(n + dn, e + de, d + dd))

    @property
    def extra_params(self) -> ParamProvider | None:
        """Listed, read and set with the vehicle's parameters."""
        return self.params.extra

    # ----- main loop ------------------------------------------------------------------------------

    def update(self) -> None:
        """Handle everything received, report vehicle events, send the streams now due."""
        # The state the streams are built from is taken here, before any command is handled, as
        # before; but only on a step that may need it (something received, or a stream due): most
        # physics steps (200 Hz against 50 Hz streams) need only the time.
        self._state = None
        self._now_s = self._vehicle_time_s()
        if self._now_s < self._silent_until_s:
            self.transport.recv()  # a rebooting autopilot hears nothing
            return
        if hasattr(self.transport, "recv_datagrams"):
            got = self.transport.recv_datagrams()
            if got or self.streams.may_be_due(self._link_now()):
                self._state = self.vehicle.state()
            if got:
                self._receive_datagrams(got)
        else:
            data = self.transport.recv()
            if data or self.streams.may_be_due(self._link_now()):
                self._state = self.vehicle.state()
            if data:
                self._asker = None  # the one client at the other end of the stream
                try:
                    for msg in self._framer.feed(data):
                        self._handle(msg)
                finally:
                    self._asker = _NO_ASKER
                self._update_rx_stats()
        if self._state is not None:
            self._watch_vehicle(self._state)
        self.missions.report_vehicle_events()
        for text in self.vehicle.pop_status_text():
            log.info("vehicle: %s", text)
            self.announce(mavlink.MAV_SEVERITY_INFO, text)
        self.missions.service_upload_timeout()
        for msg_id in self.streams.due(self._link_now()):
            msg = self._build_stream_message(msg_id)
            if msg is not None:
                self._send(msg)

    def time_link_by(self, clock: Callable[[], float] | None) -> None:
        """Time the link (stream rates, the mission-upload timeout) by clock; None: simulated time again.

        `run_realtime` passes the wall clock, so the rates a ground station asked for are per second
        of its own time: at a speed-up of 25, simulated-time rates would send it 25 times as much
        as it asked for, more than it can read. Every stream is due again at once on the new clock.
        """
        self._link_clock = clock
        self.streams.restart(self._link_now())
        self.missions.restart_timer()

    def _link_now(self) -> float:
        return self._now_s if self._link_clock is None else self._link_clock()

    def reboot(self, silent_s: float = 3.0) -> None:
        """The flight controller restarts (a SITL fault, like ArduPilot's reboot under SIM_*): silent for
        silent_s, then time_boot_ms counts again from 0 and the message rates set with
        SET_MESSAGE_INTERVAL are back to their defaults. The simulated vehicle keeps flying and keeps
        its mission (a real one in the air would not): this is the companion's view of a reboot.
        """
        if not (math.isfinite(silent_s) and silent_s >= 0):
            raise ValueError(f"reboot silence must be >= 0 s, got {silent_s!r}")
        self._now_s = self.vehicle.state().t_s
        self._silent_until_s = self._boot_epoch_s = self._now_s + silent_s
        self.missions.cancel_upload()
        # Streams restart when the silence ends: at boot on simulated time; on the wall clock, muted until then.
        self.streams.reset(self._boot_epoch_s if self._link_clock is None else self._link_clock())
        self.stats["reboots"] = self.stats.get("reboots", 0) + 1

    def _receive_datagrams(self, got: list[tuple[bytes, Any]]) -> None:
        """Each datagram alone; only a sender whose datagram held a valid (authenticated) frame becomes
        a client, and the replies to each message go back to its sender."""
        for data, addr in got:
            msgs = self._datagrams.parse(data)
            if not msgs:
                continue
            if self.transport.add_peer(addr) is False:
                self._strangers.add(addr)  # answered, but on the budget all strangers share
            elif addr not in self._clients:
                self._new_client(addr, msgs[0])
            self._asker = addr
            try:
                for msg in msgs:
                    self._handle(msg)
            finally:
                self._asker = _NO_ASKER
        self._strangers.clear()
        self._update_rx_stats()

    def _new_client(self, addr: Any, first: Any) -> None:
        """Tell the operator; greet it with a HEARTBEAT (it detects the vehicle at once, not within a second)."""
        peers = getattr(self.transport, "peers", None)
        if peers is not None:
            for gone in self._clients - set(peers):
                log.info("client %s gone quiet", _peer_name(gone))
            self._clients &= set(peers)
        self._clients.add(addr)
        log.info("client %s connected (system %d, component %d)", _peer_name(addr), first.get_srcSystem(),
                 first.get_srcComponent())
        self.send_to(self._build_stream_message(mavlink.MAVLINK_MSG_ID_HEARTBEAT), addr)

    def _budget_key(self, peer: Peer) -> Any:
        """Whose budget a sender's frames and our replies to it spend: a client's own; one shared by every
        sender the full client table refused (so a thousand source ports get no more than one)."""
        return _STRANGERS if peer in self._strangers else peer

    def _watch_vehicle(self, s: VehicleState) -> None:
        """Tell the operator when the vehicle arms, disarms or changes mode."""
        now = (s.armed, int(s.mode))
        last, self._last_armed_mode = self._last_armed_mode, now
        if last is None or last == now:
            return
        if now[0] != last[0]:
            log.info("vehicle %s", "armed" if s.armed else "disarmed")
        if now[1] != last[1]:
            log.info("mode %s", getattr(s.mode, "name", s.mode))

    def _rx_errors(self) -> int:
        """SYS_STATUS errors_comm: frames that failed on the stream, datagrams dropped on UDP."""
        return self._framer.bad_frames + self._datagrams.dropped

    def _update_rx_stats(self) -> None:
        self.stats["rx_bad_bytes"] = self._framer.bad_bytes
        self.stats["rx_parse_errors"] = self._framer.bad_frames
        self.stats["rx_datagrams_dropped"] = self._datagrams.dropped
        self.stats["rx_drops"] = {reason.value: n for reason, n in self._datagrams.drops.items()}
        self.stats["peers_refused"] = getattr(self.transport, "peers_refused", 0)
        self.stats["ftp_refused"] = self.ftp.refused
        if self.signer is not None:
            for key in ("signed", "unsigned", "bad_signature", "replayed", "unsigned_accepted"):
                self.stats[f"rx_{key}"] = self.signer.stats[key]

    @property
    def signing_active(self) -> bool:
        return self.signer is not None

    def close(self) -> None:
        """Close the telemetry log (the transport belongs to the caller)."""
        if self._tlog is not None:
            self._tlog.close()
            self._tlog = None
        self.stats["statustext_dropped"] = self._statustext_budget.refused
        self.stats["tlog_frames_skipped"] = self._tlog_budget.refused

    def __enter__(self) -> MavlinkVehicleServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def mission_items(self) -> list[MissionItem]:
        """The stored mission, home (seq 0) included, as it would be downloaded."""
        return self.missions.items

    # ----- receive side ---------------------------------------------------------------------------

    def _handle(self, msg: Any) -> None:
        self.stats["rx_messages"] += 1
        self.stats["rx_by_type"][msg.get_type()] += 1
        self._log_for(self._asker, msg.get_msgbuf())
        handler = self._handlers.get(msg.get_type())
        if handler is None:
            return
        if not self._for_us(msg):
            self.stats["rx_not_for_us"] += 1
            return
        try:
            handler(msg)
        except Exception as exc:  # never let one message take the link down
            self.stats["handler_errors"] += 1
            self.say(mavlink.MAV_SEVERITY_WARNING, f"error handling {msg.get_type()}: {exc}")

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

    def _ignore(self, msg: Any) -> None:
        """Messages we accept and need not act on (heartbeats, legacy stream requests, mission acks)."""

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:  # a request: answer with our clock, echoing theirs (as ArduPilot does)
            self.reply(self._mav.timesync_encode(round((self._now_s - self._boot_epoch_s) * 1e9), msg.ts1))

    def _on_set_gps_global_origin(self, msg: Any) -> None:
        """The EKF origin is fixed where this vehicle was placed (its home: `serve --origin`), as on an
        ArduPilot whose origin is already set. The same origin (to MAVLink's own resolution) is
        confirmed with GPS_GLOBAL_ORIGIN; another is refused, said and counted, and GPS_GLOBAL_ORIGIN
        tells the sender the one in force: its positions would be about the wrong point otherwise."""
        mine = tm.origin_ints(self.home)
        theirs = (int(msg.latitude), int(msg.longitude), int(msg.altitude))
        if theirs != mine:
            self.stats["origin_refused"] += 1
            text = (f"origin refused: {theirs[0] / 1e7:.7f} {theirs[1] / 1e7:.7f} {theirs[2] / 1e3:g} m; EKF "
                    f"origin is {mine[0] / 1e7:.7f} {mine[1] / 1e7:.7f} {mine[2] / 1e3:g} m")
            if self.stats["origin_refused"] == 1:
                log.warning("%s", text)
            self.say(mavlink.MAV_SEVERITY_WARNING, text)
        self.reply(tm.gps_global_origin(self._mav, self.home, self._now_s))

    # ----- send side ------------------------------------------------------------------------------

    def _build_stream_message(self, msg_id: int) -> Any | None:
        return self._builders[msg_id](self._state or self.vehicle.state())

    def _home_position(self) -> Any:
        return tm.home_position(self._mav, self.home, self._now_s)

    @property
    def _boot_ms(self) -> int:
        return round((self._now_s - self._boot_epoch_s) * 1000) & 0xFFFFFFFF

    def _statustexts(self, severity: int, text: str) -> list[Any]:
        """STATUSTEXT, in 50-character chunks sharing an id when longer (MAVLink 2 chunking)."""
        raw = text.encode("ascii", "replace")
        if len(raw) <= STATUSTEXT_LEN:
            return [self._mav.statustext_encode(severity, raw)]
        self._statustext_id = self._statustext_id % 65535 + 1
        return [self._mav.statustext_encode(severity, raw[k:k + STATUSTEXT_LEN], self._statustext_id,
                                            k // STATUSTEXT_LEN)
                for k in range(0, len(raw), STATUSTEXT_LEN)]

    # ----- the Outbox the services send through (sitl.mavlink.outbox) -----------------------------

    def broadcast(self, msg: Any) -> None:
        """To every client (telemetry, the vehicle's news); always logged (until the tlog is full)."""
        buf = self._pack(msg)
        self.transport.send(buf)
        self._log(buf)

    def asker(self) -> Peer:
        return None if self._asker is _NO_ASKER else self._asker

    def reply(self, msg: Any) -> None:
        self.send_to(msg, self.asker())

    def send_to(self, msg: Any, peer: Peer) -> None:
        buf = self._pack(msg)
        send_to = getattr(self.transport, "send_to", None)
        if send_to is None:
            self.transport.send(buf)  # a single-client link
        else:
            send_to(buf, peer)
        self._log_for(peer, buf)

    def say(self, severity: int, text: str) -> None:
        self.say_to(self.asker(), severity, text)

    def say_to(self, peer: Peer, severity: int, text: str) -> None:
        """STATUSTEXT to one sender, within its budget (a flood of bad requests gets a trickle)."""
        if not self._statustext_budget.take(self._budget_key(peer), self._link_now()):
            self.stats["statustext_dropped"] = self._statustext_budget.refused
            return
        for msg in self._statustexts(severity, text):
            self.send_to(msg, peer)

    def announce(self, severity: int, text: str) -> None:
        for msg in self._statustexts(severity, text):
            self.broadcast(msg)

    _send = broadcast  # streams and the vehicle's own messages

    def _pack(self, msg: Any) -> bytes:
        buf = self.signer.pack(msg, self._mav) if self.signer is not None else msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        self.stats["tx_messages"] += 1
        self.stats["tx_by_type"][msg.get_type()] += 1
        return bytes(buf)

    def _log_for(self, peer: Peer, frame: bytes | bytearray) -> None:
        """Log a frame a sender caused (its own, or a reply to it), within that sender's budget."""
        if self._tlog is None:
            return
        if not self._tlog_budget.take(self._budget_key(peer), self._link_now()):
            self.stats["tlog_frames_skipped"] = self._tlog_budget.refused
            return
        self._log(frame)

    def _log(self, frame: bytes | bytearray) -> None:
        if self._tlog is None:
            return
        record = struct.pack(">Q", TLOG_EPOCH_US + round(self._now_s * 1e6)) + bytes(frame)
        if self._tlog_bytes + len(record) > self.limits.tlog_max_bytes:
            self._tlog.close()
            self._tlog = None
            self.stats["tlog_full"] = True
            log.warning("telemetry log %s reached its cap of %d bytes: nothing more is logged (raise it with "
                        "--tlog-max-mb)", self._tlog_path, self.limits.tlog_max_bytes)
            return
        self._tlog.write(record)
        self._tlog_bytes += len(record)


def _peer_name(peer: Peer) -> str:
    if isinstance(peer, tuple) and len(peer) == 2:
        return f"{peer[0]}:{peer[1]}"
    return str(peer)


# ----- networked mode -----------------------------------------------------------------------------

def run_realtime(server: MavlinkVehicleServer, vehicle: Vehicle, speedup: float = 1.0,
                 duration_s: float | None = None, stop_event: threading.Event | None = None, *,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep,
                 on_step: Callable[[], None] | None = None) -> float:
    """Step the vehicle and serve MAVLink, paced so simulated time runs `speedup` times the wall clock.

    Runs until duration_s of simulated time has passed or stop_event is set; returns the simulated
    seconds run. If the CPU cannot keep up it runs flat out (no catch-up skipping). `on_step` runs
    after every physics step (the networked SITL records the true pose for its emulated LiDAR).
    While it runs, the server's link is timed by `clock` (see `MavlinkVehicleServer.time_link_by`).
    """
    if not (math.isfinite(speedup) and speedup > 0):
        raise ValueError(f"speedup must be > 0, got {speedup}")
    t0_sim = vehicle.state().t_s
    t0_wall = clock()
    server.time_link_by(clock)
    try:
        server.update()
        t_sim = t0_sim
        while stop_event is None or not stop_event.is_set():
            if duration_s is not None and t_sim - t0_sim >= duration_s - 1e-9:
                break
            vehicle.step()
            server.update()
            if on_step is not None:
                on_step()
            t_sim = vehicle.state().t_s
            delay = t0_wall + (t_sim - t0_sim) / speedup - clock()
            if delay > 0:
                sleep(delay)
    finally:
        server.time_link_by(None)
    return t_sim - t0_sim
