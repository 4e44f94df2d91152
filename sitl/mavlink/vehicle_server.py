"""MAVLink 2 autopilot peer for any simulated `Vehicle`: what a GCS or the payload talks to in SITL.

`MavlinkVehicleServer` makes a `sitl.vehicle.api.Vehicle` look like an ArduCopter on a link:
heartbeat and telemetry streams, commands with COMMAND_ACK, the mission and parameter
micro-services, TIMESYNC, STATUSTEXT, and a .tlog of everything both ways. It has no thread and
no clock of its own; everything is timed by the vehicle's simulated clock, so a lockstep run is
deterministic and as fast as the CPU allows.

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

Choices, where MAVLink or ArduPilot leave room:

- Mission seq 0 is home, as in ArduPilot: it is stored as sent (and downloaded back unchanged) but
  never flown; vehicle item k is MAVLink seq k + 1 (MISSION_CURRENT, MISSION_ITEM_REACHED). With
  no mission the vehicle reports one item, home, as ArduPilot does.
- Global coordinates become local NED by a flat-earth approximation about the home position
  (`global_to_ned`): exact to millimetres over a building, wrong over kilometres. Global altitude
  is above home_alt_m; relative altitude above home. lat = lon = 0 on a NAV item means "where the
  previous item was" (ArduPilot: "here"). NAV_LAND lands on the floor, whatever its altitude.
- Supported items: NAV_WAYPOINT, NAV_TAKEOFF, NAV_LAND, DO_CHANGE_SPEED. DO_CHANGE_SPEED (param2
  m/s, > 0) sets PS_SPEED_MS when the vehicle starts the next NAV item, as ArduPilot runs DO items.
- An item with an out-of-order seq is answered MAV_MISSION_INVALID_SEQUENCE and the upload stays
  open (the expected item is requested again); an invalid item aborts the upload with its error.
- Parsing is our own framer around pymavlink's decoder: a frame that fails its CRC costs one byte,
  not the whole frame length, so a corrupt length byte cannot swallow the valid frames after it.
  Frames of message ids outside the ardupilotmega dialect cannot be checked and are skipped the
  same way.
- COMMAND_ACK for SET_MODE carries command = 11 (the message id), as ArduPilot sends it.
- Telemetry log timestamps are TLOG_EPOCH_US + simulated time, so two runs give identical logs
  (unless signing is on: signatures carry wall-clock timestamps).
- Signing (`signing=SigningConfig(...)`, `pilescan-sitl serve --signing-key FILE`): as the payload's
  links (`firmware_py.hal.mavlink_link`): everything sent is signed; unsigned, forged and replayed
  frames are refused (never handled, never logged) and counted in stats (`rx_unsigned`,
  `rx_bad_signature`, `rx_replayed`; `rx_signed`, `rx_unsigned_accepted`). On a listening
  `UdpTransport` a client only becomes a destination once one of its datagrams held an
  authenticated frame, so a client without the key hears nothing (and cannot aim our telemetry
  at a spoofed address).
- Parameters: the vehicle's (`PS_*`) and, with `extra_params` (any `ParamProvider`), more beside
  them, listed, read and set alike, sorted by name; `pilescan-sitl serve` serves its `SIM_PS_*`
  fault parameters this way (`sitl.faults.params`).
"""

from __future__ import annotations

import math
import os
import socket
import struct
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, Protocol

os.environ["MAVLINK20"] = "1"  # for mavutil users in this process; the v20 dialect below is MAVLink 2 anyway

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.mavlink_link import MavlinkFramer
from firmware_py.hal.signing import MavlinkSigner, SigningConfig
from sitl.vehicle.api import CommandRejected, FlightMode, NavItem, NavKind, Vehicle, VehicleState

TLOG_EPOCH_US = 1_704_067_200_000_000
"""2024-01-01T00:00:00Z: the wall-clock time of simulated t = 0 in logs and SYSTEM_TIME."""

EARTH_RADIUS_M = 6_378_137.0
MAX_MISSION_ITEMS = 1000
MISSION_TIMEOUT_S = 1.5
MISSION_MAX_RETRIES = 5
FORCE_DISARM_MAGIC = 21196
MAX_ALTITUDE_M = 100_000.0
STATUSTEXT_LEN = 50

STREAM_DEFAULT_HZ: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 50.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 4.0,
    mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.0,
}
"""Telemetry streams and their default rates (0 = off until asked for); SET_MESSAGE_INTERVAL changes them."""

NAV_COMMANDS = {mavlink.MAV_CMD_NAV_WAYPOINT: NavKind.WAYPOINT, mavlink.MAV_CMD_NAV_TAKEOFF: NavKind.TAKEOFF,
                mavlink.MAV_CMD_NAV_LAND: NavKind.LAND}
DO_COMMANDS = frozenset({mavlink.MAV_CMD_DO_CHANGE_SPEED})
GLOBAL_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT})
RELATIVE_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT})
LATLON_FRAMES = GLOBAL_FRAMES | RELATIVE_FRAMES
NAV_FRAMES = LATLON_FRAMES | {mavlink.MAV_FRAME_LOCAL_NED}
DO_FRAMES = NAV_FRAMES | {mavlink.MAV_FRAME_MISSION}
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
FLIGHT_SW_VERSION = (4 << 24) | (5 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
"""Reported as ArduCopter 4.5.0 so GCSs enable their ArduPilot features (mode names, MISSION_INT)."""


# ----- flat-earth geodesy -------------------------------------------------------------------------

def global_to_ned(lat_deg: float, lon_deg: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """North/east metres of a lat/lon from home, flat-earth (fine over a building, not over kilometres)."""
    north = math.radians(lat_deg - home_lat_deg) * EARTH_RADIUS_M
    east = math.radians(lon_deg - home_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))
    return north, east


def ned_to_global(north_m: float, east_m: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """Inverse of global_to_ned: lat/lon (deg) of a local north/east point."""
    lat = home_lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon = home_lon_deg + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))))
    return lat, lon


# ----- transports -------------------------------------------------------------------------------

class Transport(Protocol):
    """A byte link: send whole packets, receive whatever has arrived (b"" when nothing; never blocks)."""

    def send(self, data: bytes) -> None: ...

    def recv(self) -> bytes: ...

    def close(self) -> None: ...


class PipeTransport:
    """One end of an in-process byte pipe; thread-safe so a server thread and a client can share it."""

    def __init__(self) -> None:
        self._inbox: deque[bytes] = deque()
        self._lock = threading.Lock()
        self._peer: PipeTransport | None = None

    @classmethod
    def pair(cls) -> tuple[PipeTransport, PipeTransport]:
        a, b = cls(), cls()
        a._peer, b._peer = b, a
        return a, b

    def send(self, data: bytes) -> None:
        peer = self._peer
        if peer is None or not data:
            return
        with peer._lock:
            peer._inbox.append(bytes(data))

    def recv(self) -> bytes:
        with self._lock:
            data = b"".join(self._inbox)
            self._inbox.clear()
        return data

    def close(self) -> None:
        self._peer = None


def _parse_udp_url(url: str) -> tuple[str, str, int]:
    kind, sep, rest = url.partition(":")
    host, sep2, port_s = rest.rpartition(":")
    if not sep or not sep2 or kind not in ("udp", "udpin", "udpout") or not host:
        raise ValueError(f"expected udp:HOST:PORT, udpin:HOST:PORT or udpout:HOST:PORT, got {url!r}")
    try:
        port = int(port_s)
    except ValueError:
        raise ValueError(f"bad UDP port in {url!r}") from None
    if not 0 <= port <= 65535 or (kind == "udpout" and port == 0):
        raise ValueError(f"bad UDP port in {url!r}")
    return ("udpout" if kind == "udpout" else "udpin"), host, port


class UdpTransport:
    """UDP like ArduPilot SITL: "udp:HOST:PORT" listens there and replies to its clients;
    "udpout:HOST:PORT" sends to that fixed address. Port 0 listens on a free port (see local_address).

    A listening transport sends to every client heard within `peer_timeout_s` (at most `max_peers`),
    like a MAVLink router: a ground station and the companion's payload can share one port
    (ArduPilot would give each its own SERIALn port; one port is simpler to run by hand).
    """

    MAX_DATAGRAMS_PER_RECV = 1000

    def __init__(self, address: str, peer_timeout_s: float = 10.0, max_peers: int = 8,
                 clock: Callable[[], float] = time.monotonic) -> None:
        kind, host, port = _parse_udp_url(address)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._fixed_peer = kind == "udpout"
        self._peers: dict[tuple[str, int], float] = {}  # address -> last heard (clock seconds)
        self._peer_timeout_s, self._max_peers, self._clock = peer_timeout_s, max_peers, clock
        if self._fixed_peer:
            self._peers[(host, port)] = math.inf
        else:
            self._sock.bind((host, port))
        self.dropped_packets = 0

    @property
    def local_address(self) -> tuple[str, int]:
        return self._sock.getsockname()

    @property
    def peer_address(self) -> tuple[str, int] | None:
        """The most recently heard client (or the fixed peer)."""
        return max(self._peers, key=self._peers.__getitem__) if self._peers else None

    @property
    def peers(self) -> list[tuple[str, int]]:
        return list(self._peers)

    def send(self, data: bytes) -> None:
        if not self._peers:
            self.dropped_packets += 1  # nobody has talked to us yet
            return
        if not self._fixed_peer:
            oldest = self._clock() - self._peer_timeout_s
            for addr in [a for a, t in self._peers.items() if t < oldest]:
                del self._peers[addr]  # a client gone quiet: stop sending to it
        for addr in self._peers:
            try:
                self._sock.sendto(data, addr)
            except OSError:
                self.dropped_packets += 1

    def recv(self) -> bytes:
        """Every datagram received, joined; each sender becomes (or stays) a client."""
        got = self.recv_datagrams()
        for _data, addr in got:
            self.add_peer(addr)
        return b"".join(data for data, _addr in got)

    def recv_datagrams(self) -> list[tuple[bytes, tuple[str, int]]]:
        """Every datagram received, with its sender, WITHOUT learning the senders (see add_peer)."""
        got = []
        for _ in range(self.MAX_DATAGRAMS_PER_RECV):
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                break  # e.g. ICMP port unreachable reported on some platforms
            got.append((data, addr))
        return got

    def add_peer(self, addr: tuple[str, int]) -> None:
        """Send to addr from now on (a listening transport; refreshes a known client)."""
        if self._fixed_peer:
            return
        self._peers[addr] = self._clock()
        if len(self._peers) > self._max_peers:
            del self._peers[min(self._peers, key=self._peers.__getitem__)]

    def close(self) -> None:
        self._sock.close()


def make_transport(url: str) -> Transport:
    """Transport from a URL-like string: udp:HOST:PORT / udpin:HOST:PORT (listen), udpout:HOST:PORT."""
    if url.split(":", 1)[0] in ("udp", "udpin", "udpout"):
        return UdpTransport(url)
    raise ValueError(f"unsupported transport {url!r} (use udp:HOST:PORT or udpout:HOST:PORT)")



# ----- mission storage --------------------------------------------------------------------------

@dataclass(frozen=True)
class MissionItem:
    """One stored mission item, in MISSION_ITEM_INT encoding (x, y: degE7, metres x 1e4, or raw ints)."""

    seq: int
    frame: int
    command: int
    current: int
    autocontinue: int
    param1: float
    param2: float
    param3: float
    param4: float
    x: int
    y: int
    z: float
    mission_type: int = mavlink.MAV_MISSION_TYPE_MISSION


def _xy_scale(frame: int) -> float:
    if frame in LATLON_FRAMES:
        return 1e7
    if frame == mavlink.MAV_FRAME_LOCAL_NED:
        return 1e4
    return 1.0


def _int32(value: float) -> int | None:
    if not math.isfinite(value):
        return None
    v = round(value)
    return v if -(2**31) <= v < 2**31 else None


class _ItemError(Exception):
    """A mission item the vehicle cannot take; args = (MAV_MISSION_RESULT, reason)."""


def _decode_mission_item(msg: Any, is_int: bool) -> MissionItem:
    """Validate a MISSION_ITEM(_INT) and store it in INT encoding; _ItemError with the MISSION_ACK code."""
    cmd, frame = msg.command, msg.frame
    if cmd not in NAV_COMMANDS and cmd not in DO_COMMANDS:
        raise _ItemError(mavlink.MAV_MISSION_UNSUPPORTED, f"command {cmd} is not supported")
    is_nav = cmd in NAV_COMMANDS
    if frame not in (NAV_FRAMES if is_nav else DO_FRAMES):
        raise _ItemError(mavlink.MAV_MISSION_UNSUPPORTED_FRAME, f"frame {frame} is not supported for command {cmd}")
    scale = _xy_scale(frame)
    xf, yf = (msg.x / scale, msg.y / scale) if is_int else (float(msg.x), float(msg.y))
    z = float(msg.z)
    xi = msg.x if is_int else _int32(xf * scale)
    yi = msg.y if is_int else _int32(yf * scale)
    if is_nav:
        latlon = frame in LATLON_FRAMES
        if xi is None or not math.isfinite(xf) or (latlon and abs(xf) > 90.0):
            raise _ItemError(mavlink.MAV_MISSION_INVALID_PARAM5_X, f"x / latitude {xf} is invalid")
        if yi is None or not math.isfinite(yf) or (latlon and abs(yf) > 180.0):
            raise _ItemError(mavlink.MAV_MISSION_INVALID_PARAM6_Y, f"y / longitude {yf} is invalid")
        if not (math.isfinite(z) and abs(z) <= MAX_ALTITUDE_M):
            raise _ItemError(mavlink.MAV_MISSION_INVALID_PARAM7, f"z / altitude {z} is invalid")
    elif cmd == mavlink.MAV_CMD_DO_CHANGE_SPEED and not math.isfinite(msg.param2):
        raise _ItemError(mavlink.MAV_MISSION_INVALID_PARAM2, f"speed {msg.param2} is invalid")
    return MissionItem(msg.seq, frame, cmd, msg.current, msg.autocontinue, float(msg.param1), float(msg.param2),
                       float(msg.param3), float(msg.param4), xi or 0, yi or 0, z, msg.mission_type)


@dataclass
class _Upload:
    partner: tuple[int, int]
    count: int
    mission_type: int
    deadline_s: float
    items: list[MissionItem] = field(default_factory=list)
    retries: int = 0


@dataclass
class _Stream:
    default_interval_s: float
    interval_s: float
    next_due_s: float = 0.0


class _Unsupported(Exception):
    """A command or message id this vehicle does not implement (MAV_RESULT_UNSUPPORTED)."""


class ParamProvider(Protocol):
    """Parameters served beside the vehicle's own (e.g. `sitl.faults.params.FaultParams`: the SIM_PS_*)."""

    def names(self) -> list[str]:
        """The names now available (a vehicle parameter of the same name wins)."""

    def get(self, name: str) -> float: ...

    def set(self, name: str, value: float) -> float | None:
        """Set at once; KeyError for an unknown name, ValueError for a bad value (nothing changed).

        Returns the value the PARAM_VALUE acknowledging it carries, or None for get(name): an action
        parameter acknowledges what it did (a ground station such as MAVProxy re-sends a set until the
        value it sent comes back), then reads back its state.
        """


# ----- the server -------------------------------------------------------------------------------

class MavlinkVehicleServer:
    """Serves a Vehicle over MAVLink 2 as an ArduCopter-like autopilot; call update() after vehicle steps."""

    def __init__(self, vehicle: Vehicle, transport: Transport, tlog_path: str | os.PathLike[str] | None = None,
                 sysid: int = 1, compid: int = 1, home_lat_deg: float = 53.4668, home_lon_deg: float = -2.2339,
                 home_alt_m: float = 50.0, signing: SigningConfig | MavlinkSigner | None = None,
                 extra_params: ParamProvider | None = None) -> None:
        if not (math.isfinite(home_lat_deg) and abs(home_lat_deg) < 90 and math.isfinite(home_lon_deg)
                and abs(home_lon_deg) <= 180 and math.isfinite(home_alt_m)):
            raise ValueError(f"bad home position {home_lat_deg}, {home_lon_deg}, {home_alt_m}")
        self.vehicle = vehicle
        self.transport = transport
        self.extra_params = extra_params  # listed, read and set with the vehicle's parameters
        self.sysid, self.compid = sysid, compid
        self.home_lat_deg, self.home_lon_deg, self.home_alt_m = home_lat_deg, home_lon_deg, home_alt_m
        self._mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        if signing is not None and not isinstance(signing, MavlinkSigner):
            signing = MavlinkSigner(signing)
        self.signer: MavlinkSigner | None = signing
        if self.signer is not None:
            self.signer.attach(self._mav)  # the encoder signs; the framer's own decoder does not check
            self._framer = MavlinkFramer(mavlink.MAVLink(None), signer=self.signer)
        else:
            self._framer = MavlinkFramer(self._mav)  # the payload's framer: one parser for both ends
        self._tlog: BinaryIO | None = Path(tlog_path).open("wb") if tlog_path is not None else None
        self.stats: dict[str, Any] = {
            "rx_messages": 0, "rx_bad_bytes": 0, "rx_parse_errors": 0, "rx_not_for_us": 0,
            "tx_messages": 0, "handler_errors": 0, "rx_by_type": Counter(), "tx_by_type": Counter(),
            "rx_signed": 0, "rx_unsigned": 0, "rx_bad_signature": 0, "rx_replayed": 0, "rx_unsigned_accepted": 0,
        }
        self._now_s = 0.0
        self._boot_epoch_s = 0.0  # vehicle time at which the autopilot last booted (time_boot_ms 0)
        self._silent_until_s = -math.inf  # rebooting until then: deaf and mute
        self._state: VehicleState | None = None
        self._next_any_due_s = 0.0  # earliest next_due_s of any stream (skip the scan until then)
        self._streams = {mid: _Stream(self._interval(hz), self._interval(hz)) for mid, hz in STREAM_DEFAULT_HZ.items()}
        self._statustext_id = 0
        self._upload: _Upload | None = None
        self._set_stored_mission([self._home_item()])
        self._handlers: dict[str, Callable[[Any], None]] = {
            "HEARTBEAT": self._ignore, "REQUEST_DATA_STREAM": self._ignore, "MISSION_ACK": self._ignore,
            "TIMESYNC": self._on_timesync, "COMMAND_LONG": self._on_command_long, "COMMAND_INT": self._on_command_int,
            "SET_MODE": self._on_set_mode, "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read, "PARAM_SET": self._on_param_set,
            "MISSION_COUNT": self._on_mission_count, "MISSION_ITEM_INT": self._on_mission_item,
            "MISSION_ITEM": self._on_mission_item, "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "MISSION_REQUEST_INT": self._on_mission_request, "MISSION_REQUEST": self._on_mission_request,
            "MISSION_CLEAR_ALL": self._on_mission_clear_all,
        }
        self._builders: dict[int, Callable[[VehicleState], Any | None]] = {
            mavlink.MAVLINK_MSG_ID_HEARTBEAT: self._heartbeat,
            mavlink.MAVLINK_MSG_ID_SYS_STATUS: self._sys_status,
            mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: self._system_time,
            mavlink.MAVLINK_MSG_ID_ATTITUDE: self._attitude,
            mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: self._local_position,
            mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: self._global_position,
            mavlink.MAVLINK_MSG_ID_VFR_HUD: self._vfr_hud,
            mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: self._mission_current,
            mavlink.MAVLINK_MSG_ID_HOME_POSITION: lambda _s: self._home_position(),
        }
        self._commands: dict[int, Callable[[tuple[float, ...]], list[Any]]] = {
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM: self._cmd_arm_disarm,
            mavlink.MAV_CMD_NAV_TAKEOFF: self._cmd_takeoff,
            mavlink.MAV_CMD_MISSION_START: self._cmd_mission_start,
            mavlink.MAV_CMD_DO_SET_MODE: self._cmd_set_mode,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self._cmd_set_message_interval,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: self._cmd_get_message_interval,
            mavlink.MAV_CMD_REQUEST_MESSAGE: self._cmd_request_message,
            mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: self._cmd_autopilot_capabilities,
            mavlink.MAV_CMD_GET_HOME_POSITION: self._cmd_get_home_position,
        }

    # ----- main loop ------------------------------------------------------------------------------

    def update(self) -> None:
        """Handle everything received, report vehicle events, send the streams now due (simulated time)."""
        self._state = self.vehicle.state()
        self._now_s = self._state.t_s
        if self._now_s < self._silent_until_s:
            self.transport.recv()  # a rebooting autopilot hears nothing
            return
        if self.signer is not None and hasattr(self.transport, "recv_datagrams"):
            self._receive_authenticated_datagrams()
        else:
            data = self.transport.recv()
            if data:
                for msg in self._framer.feed(data):
                    self._handle(msg)
                self._update_rx_stats()
        self._report_vehicle_events()
        self._service_upload_timeout()
        self._send_due_streams()

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
        self._upload = None
        for stream in self._streams.values():
            stream.interval_s = stream.default_interval_s
            stream.next_due_s = self._boot_epoch_s
        self._next_any_due_s = self._boot_epoch_s
        self.stats["reboots"] = self.stats.get("reboots", 0) + 1

    def _receive_authenticated_datagrams(self) -> None:
        """Signed UDP: only a sender whose datagram held an authenticated frame becomes a client."""
        got = self.transport.recv_datagrams()
        for data, addr in got:
            msgs = self._framer.feed(data)
            if msgs:
                self.transport.add_peer(addr)
            for msg in msgs:
                self._handle(msg)
        if got:
            self._update_rx_stats()

    def _update_rx_stats(self) -> None:
        self.stats["rx_bad_bytes"] = self._framer.bad_bytes
        self.stats["rx_parse_errors"] = self._framer.bad_frames
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

    def __enter__(self) -> MavlinkVehicleServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def mission_items(self) -> list[MissionItem]:
        """The stored mission, home (seq 0) included, as it would be downloaded."""
        return list(self._items)

    # ----- receive side ---------------------------------------------------------------------------

    def _handle(self, msg: Any) -> None:
        self.stats["rx_messages"] += 1
        self.stats["rx_by_type"][msg.get_type()] += 1
        self._log(msg.get_msgbuf())
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
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"error handling {msg.get_type()}: {exc}")

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, self.compid)

    @staticmethod
    def _src(msg: Any) -> tuple[int, int]:
        return msg.get_srcSystem(), msg.get_srcComponent()

    def _ignore(self, msg: Any) -> None:
        """Messages we accept and need not act on (heartbeats, legacy stream requests, mission acks)."""

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:  # a request: answer with our clock, echoing theirs (as ArduPilot does)
            self._send(self._mav.timesync_encode(round((self._now_s - self._boot_epoch_s) * 1e9), msg.ts1))

    # ----- commands -------------------------------------------------------------------------------

    def _on_command_long(self, msg: Any) -> None:
        p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._run_command(msg, msg.command, p)

    def _on_command_int(self, msg: Any) -> None:
        p = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._run_command(msg, msg.command, p)

    def _on_set_mode(self, msg: Any) -> None:
        self._run_command(msg, mavlink.MAVLINK_MSG_ID_SET_MODE, (float(msg.base_mode), float(msg.custom_mode)),
                          handler=self._cmd_set_mode)

    def _run_command(self, msg: Any, command: int, params: tuple[float, ...],
                     handler: Callable[[tuple[float, ...]], list[Any]] | None = None) -> None:
        """Run a command and ACK it; then its replies, or a STATUSTEXT saying why it was refused."""
        handler = handler or self._commands.get(command)
        followups: list[Any] = []
        reason: object = None
        if handler is None:
            result = mavlink.MAV_RESULT_UNSUPPORTED
        else:
            try:
                followups = handler(params)
                result = mavlink.MAV_RESULT_ACCEPTED
            except _Unsupported as exc:
                result, reason = mavlink.MAV_RESULT_UNSUPPORTED, exc
            except (CommandRejected, ValueError, KeyError, OverflowError) as exc:
                result = mavlink.MAV_RESULT_DENIED
                reason = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        src_sys, src_comp = self._src(msg)
        self._send(self._mav.command_ack_encode(command, result, 0, 0, src_sys, src_comp))
        for m in followups:
            self._send(m)
        if reason is not None:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"{_command_name(command)}: {reason}")

    @staticmethod
    def _as_int(value: float, what: str) -> int:
        if not (math.isfinite(value) and value == int(value)):
            raise ValueError(f"{what} must be an integer, got {value}")
        return int(value)

    def _cmd_arm_disarm(self, p: tuple[float, ...]) -> list[Any]:
        if p[0] == 1:
            self.vehicle.arm()
        elif p[0] == 0:
            self.vehicle.disarm(force=p[1] == FORCE_DISARM_MAGIC)
        else:
            raise ValueError(f"param1 must be 1 (arm) or 0 (disarm), got {p[0]}")
        return []

    def _cmd_takeoff(self, p: tuple[float, ...]) -> list[Any]:
        self.vehicle.takeoff(p[6])
        return []

    def _cmd_mission_start(self, p: tuple[float, ...]) -> list[Any]:
        self.vehicle.start_mission()
        return []

    def _cmd_set_mode(self, p: tuple[float, ...]) -> list[Any]:
        base = self._as_int(p[0], "base mode")
        if not base & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            raise ValueError("only custom (ArduCopter) modes are supported: set MAV_MODE_FLAG_CUSTOM_MODE_ENABLED")
        number = self._as_int(p[1], "custom mode")
        try:
            mode = FlightMode(number)
        except ValueError:
            raise ValueError(f"unknown flight mode {number}") from None
        self.vehicle.set_mode(mode)
        return []

    def _cmd_set_message_interval(self, p: tuple[float, ...]) -> list[Any]:
        stream = self._stream(p[0])
        interval_us = p[1]
        if interval_us == 0:
            stream.interval_s = stream.default_interval_s
        elif interval_us == -1:
            stream.interval_s = 0.0
        elif math.isfinite(interval_us) and interval_us > 0:
            stream.interval_s = interval_us * 1e-6
        else:
            raise ValueError(f"interval {interval_us} us is invalid")
        stream.next_due_s = self._now_s
        self._next_any_due_s = 0.0  # recompute at the next update
        return []

    def _cmd_get_message_interval(self, p: tuple[float, ...]) -> list[Any]:
        msg_id = self._as_int(p[0], "message id")
        stream = self._stream(p[0])
        interval_us = round(stream.interval_s * 1e6) if stream.interval_s > 0 else -1
        return [self._mav.message_interval_encode(msg_id, interval_us)]

    def _cmd_request_message(self, p: tuple[float, ...]) -> list[Any]:
        msg_id = self._as_int(p[0], "message id")
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return [self._autopilot_version()]
        if msg_id in self._streams:
            msg = self._build_stream_message(msg_id)
            if msg is None:
                raise ValueError(f"message {msg_id} is not available now")
            return [msg]
        raise _Unsupported(f"message {msg_id} cannot be requested")

    def _cmd_autopilot_capabilities(self, p: tuple[float, ...]) -> list[Any]:
        return [self._autopilot_version()]

    def _cmd_get_home_position(self, p: tuple[float, ...]) -> list[Any]:
        return [self._home_position()]

    def _stream(self, msg_id: float) -> _Stream:
        stream = self._streams.get(self._as_int(msg_id, "message id"))
        if stream is None:
            raise _Unsupported(f"message {msg_id:g} is not streamed")
        return stream

    # ----- parameters -----------------------------------------------------------------------------

    def _param_names(self) -> list[str]:
        """The vehicle's parameters and the extra ones (extra_params), sorted by name as ArduPilot does."""
        extra = self.extra_params.names() if self.extra_params is not None else []
        return sorted(set(self.vehicle.params).union(extra))

    def _param_value(self, name: str) -> float:
        if name in self.vehicle.params:
            return self.vehicle.params[name]
        return self.extra_params.get(name)

    def _set_param(self, name: str, value: float) -> float | None:
        """Set a vehicle or an extra parameter; the value to acknowledge with (None: read it back)."""
        if name in self.vehicle.params or self.extra_params is None or name not in self.extra_params.names():
            self.vehicle.set_param(name, value)  # KeyError for a name nobody has
            return None
        return self.extra_params.set(name, value)

    def _send_param(self, name: str, value: float | None = None) -> None:
        names = self._param_names()
        value = self._param_value(name) if value is None else value
        self._send(self._mav.param_value_encode(name.encode("ascii", "replace")[:16], value,
                                                mavlink.MAV_PARAM_TYPE_REAL32, len(names), names.index(name)))

    def _on_param_request_list(self, msg: Any) -> None:
        for name in self._param_names():
            self._send_param(name)

    def _on_param_request_read(self, msg: Any) -> None:
        names = self._param_names()
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(names[msg.param_index])
        elif msg.param_id in names:
            self._send_param(msg.param_id)

    def _on_param_set(self, msg: Any) -> None:
        name = msg.param_id
        ack = None
        try:
            ack = self._set_param(name, msg.param_value)
        except KeyError:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"unknown parameter {name}")
            return
        except ValueError as exc:
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"param {name} not set: {exc}")
        self._send_param(name, ack)

    # ----- mission upload -------------------------------------------------------------------------

    def _on_mission_count(self, msg: Any) -> None:
        partner, mtype = self._src(msg), msg.mission_type
        if self._upload is not None and self._upload.partner != partner:
            self._mission_ack(partner, mavlink.MAV_MISSION_DENIED, mtype)
            return
        self._upload = None
        if mtype != mavlink.MAV_MISSION_TYPE_MISSION:
            ok = msg.count == 0  # an empty fence / rally list is fine; we keep none
            self._mission_ack(partner, mavlink.MAV_MISSION_ACCEPTED if ok else mavlink.MAV_MISSION_UNSUPPORTED, mtype)
            return
        if msg.count > MAX_MISSION_ITEMS:
            self._mission_ack(partner, mavlink.MAV_MISSION_NO_SPACE, mtype)
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"mission of {msg.count} items: at most {MAX_MISSION_ITEMS}")
            return
        if msg.count == 0:
            self._accept_mission(partner, [])
            return
        self._upload = _Upload(partner, msg.count, mtype, self._now_s + MISSION_TIMEOUT_S)
        self._request_item(self._upload)

    def _request_item(self, up: _Upload) -> None:
        self._send(self._mav.mission_request_int_encode(up.partner[0], up.partner[1], len(up.items), up.mission_type))
        up.deadline_s = self._now_s + MISSION_TIMEOUT_S

    def _on_mission_item(self, msg: Any) -> None:
        up = self._upload
        if up is None or self._src(msg) != up.partner or msg.mission_type != up.mission_type:
            return
        expected = len(up.items)
        if msg.seq < expected:
            return  # a repeat of an item we have (our request crossed it)
        if msg.seq > expected:
            self._mission_ack(up.partner, mavlink.MAV_MISSION_INVALID_SEQUENCE, up.mission_type)
            self._request_item(up)
            return
        try:
            item = _decode_mission_item(msg, msg.get_type() == "MISSION_ITEM_INT")
        except _ItemError as exc:
            code, reason = exc.args
            self._upload = None
            self._mission_ack(up.partner, code, up.mission_type)
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"mission item {msg.seq} rejected: {reason}")
            return
        up.items.append(item)
        up.retries = 0
        if len(up.items) < up.count:
            self._request_item(up)
        else:
            self._upload = None
            self._accept_mission(up.partner, up.items)

    def _service_upload_timeout(self) -> None:
        up = self._upload
        if up is None or self._now_s < up.deadline_s:
            return
        up.retries += 1
        if up.retries > MISSION_MAX_RETRIES:
            self._upload = None
            self._mission_ack(up.partner, mavlink.MAV_MISSION_OPERATION_CANCELLED, up.mission_type)
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"mission upload timed out at item {len(up.items)}")
        else:
            self._request_item(up)

    def _accept_mission(self, partner: tuple[int, int], items: list[MissionItem]) -> None:
        """Load the uploaded items into the vehicle; only then do they replace the stored mission."""
        stored = items or [self._home_item()]
        try:
            nav, nav_seq, do_items = self._plan(stored)
            self.vehicle.load_mission(nav)
        except (CommandRejected, ValueError) as exc:
            self._mission_ack(partner, mavlink.MAV_MISSION_DENIED, mavlink.MAV_MISSION_TYPE_MISSION)
            self._statustext(mavlink.MAV_SEVERITY_WARNING, f"mission not loaded: {exc}")
            return
        self._set_stored_mission(stored, nav_seq, do_items)
        self._mission_ack(partner, mavlink.MAV_MISSION_ACCEPTED, mavlink.MAV_MISSION_TYPE_MISSION)
        if items:
            self._statustext(mavlink.MAV_SEVERITY_INFO, f"mission received: {len(items) - 1} items after home")

    def _plan(self, items: list[MissionItem]) -> tuple[list[NavItem], list[int], list[tuple[int, int, MissionItem]]]:
        """NavItems for the vehicle (home, seq 0, left out), their seqs, and DO items with the nav index
        they run before."""
        nav: list[NavItem] = []
        nav_seq: list[int] = []
        do_items: list[tuple[int, int, MissionItem]] = []
        prev_ne = (0.0, 0.0)
        for item in items[1:]:
            kind = NAV_COMMANDS.get(item.command)
            if kind is None:
                do_items.append((item.seq, len(nav), item))
                continue
            n, e, d = self._item_ned(item, prev_ne)
            nav.append(NavItem(kind, n, e, 0.0 if kind is NavKind.LAND else d))
            nav_seq.append(item.seq)
            prev_ne = (n, e)
        return nav, nav_seq, do_items

    def _item_ned(self, item: MissionItem, prev_ne: tuple[float, float]) -> tuple[float, float, float]:
        if item.frame == mavlink.MAV_FRAME_LOCAL_NED:
            return item.x / 1e4, item.y / 1e4, item.z
        if item.x == 0 and item.y == 0:
            n, e = prev_ne  # lat/lon 0 means "here" (ArduPilot)
        else:
            n, e = global_to_ned(item.x / 1e7, item.y / 1e7, self.home_lat_deg, self.home_lon_deg)
        alt = item.z - self.home_alt_m if item.frame in GLOBAL_FRAMES else item.z
        return n, e, -alt

    def _set_stored_mission(self, items: list[MissionItem], nav_seq: list[int] | None = None,
                            do_items: list[tuple[int, int, MissionItem]] | None = None) -> None:
        self._items = items
        self._nav_seq = nav_seq or []
        self._do_items = do_items or []
        self._do_done: set[int] = set()
        self._last_current = -1
        self._last_seq = 0
        self._mission_started = False
        self._mission_complete = False

    def _home_item(self) -> MissionItem:
        return MissionItem(0, mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0.0, 0.0, 0.0, 0.0,
                           round(self.home_lat_deg * 1e7), round(self.home_lon_deg * 1e7), self.home_alt_m)

    def _mission_ack(self, partner: tuple[int, int], result: int, mission_type: int) -> None:
        self._send(self._mav.mission_ack_encode(partner[0], partner[1], result, mission_type))

    # ----- mission download and clear -------------------------------------------------------------

    def _on_mission_request_list(self, msg: Any) -> None:
        count = len(self._items) if msg.mission_type == mavlink.MAV_MISSION_TYPE_MISSION else 0
        src = self._src(msg)
        self._send(self._mav.mission_count_encode(src[0], src[1], count, msg.mission_type))

    def _on_mission_request(self, msg: Any) -> None:
        src = self._src(msg)
        if msg.mission_type != mavlink.MAV_MISSION_TYPE_MISSION or not 0 <= msg.seq < len(self._items):
            self._mission_ack(src, mavlink.MAV_MISSION_INVALID_SEQUENCE, msg.mission_type)
            return
        it = self._items[msg.seq]
        common = (src[0], src[1], it.seq, it.frame, it.command, it.current, it.autocontinue,
                  it.param1, it.param2, it.param3, it.param4)
        if msg.get_type() == "MISSION_REQUEST_INT":
            self._send(self._mav.mission_item_int_encode(*common, it.x, it.y, it.z, it.mission_type))
        else:
            scale = _xy_scale(it.frame)
            self._send(self._mav.mission_item_encode(*common, it.x / scale, it.y / scale, it.z, it.mission_type))

    def _on_mission_clear_all(self, msg: Any) -> None:
        if msg.mission_type in (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_ALL):
            self._upload = None
            self._accept_mission(self._src(msg), [])
        else:
            self._mission_ack(self._src(msg), mavlink.MAV_MISSION_ACCEPTED, msg.mission_type)

    # ----- vehicle events -------------------------------------------------------------------------

    def _report_vehicle_events(self) -> None:
        for index in self.vehicle.pop_reached():
            if 0 <= index < len(self._nav_seq):
                self._send(self._mav.mission_item_reached_encode(self._nav_seq[index]))
                self._run_do_items(index + 1)
                if index == len(self._nav_seq) - 1:
                    self._mission_complete = True
        current = self.vehicle.current_item()
        if 0 <= current < len(self._nav_seq) and current != self._last_current:
            if current == 0:
                self._do_done.clear()  # (re)started: DO items run again
            self._run_do_items(current)
            self._mission_started, self._mission_complete = True, False
            self._last_seq = self._nav_seq[current]
        self._last_current = current
        for text in self.vehicle.pop_status_text():
            self._statustext(mavlink.MAV_SEVERITY_INFO, text)

    def _run_do_items(self, before_nav_index: int) -> None:
        """Run the DO items that sit just before nav item before_nav_index (when the vehicle starts it)."""
        for seq, trigger, item in self._do_items:
            if trigger != before_nav_index or seq in self._do_done:
                continue
            self._do_done.add(seq)
            if item.command == mavlink.MAV_CMD_DO_CHANGE_SPEED and item.param2 > 0:
                try:
                    self.vehicle.set_param("PS_SPEED_MS", item.param2)
                except (KeyError, ValueError) as exc:
                    self._statustext(mavlink.MAV_SEVERITY_WARNING, f"mission item {seq}: {exc}")
            self._send(self._mav.mission_item_reached_encode(seq))

    # ----- streams --------------------------------------------------------------------------------

    @staticmethod
    def _interval(hz: float) -> float:
        return 1.0 / hz if hz > 0 else 0.0

    def _send_due_streams(self) -> None:
        now = self._now_s
        if now + 1e-9 < self._next_any_due_s:
            return  # nothing due: most physics steps (200 Hz physics, 50 Hz streams)
        for msg_id, stream in self._streams.items():
            if stream.interval_s <= 0 or now + 1e-9 < stream.next_due_s:
                continue
            msg = self._build_stream_message(msg_id)
            if msg is not None:
                self._send(msg)
            stream.next_due_s += stream.interval_s
            if stream.next_due_s <= now + 1e-9:
                stream.next_due_s = now + stream.interval_s  # fell behind (rare updates): no bursts
        due = [st.next_due_s for st in self._streams.values() if st.interval_s > 0]
        self._next_any_due_s = min(due) if due else math.inf

    def _build_stream_message(self, msg_id: int) -> Any | None:
        return self._builders[msg_id](self._state or self.vehicle.state())

    @property
    def _boot_ms(self) -> int:
        return round((self._now_s - self._boot_epoch_s) * 1000) & 0xFFFFFFFF

    def _heartbeat(self, s: VehicleState) -> Any:
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if s.armed else 0)
        status = mavlink.MAV_STATE_ACTIVE if s.armed else mavlink.MAV_STATE_STANDBY
        return self._mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                          base, int(s.mode), status, 3)

    def _sys_status(self, s: VehicleState) -> Any:
        mv = _clamp_int(s.battery_voltage_v * 1000, 0, 65535)
        errors = _clamp_int(self._framer.bad_frames, 0, 65535)
        return self._mav.sys_status_encode(0, 0, 0, 0, mv, -1, -1, 0, errors, 0, 0, 0, 0)

    def _system_time(self, s: VehicleState) -> Any:
        return self._mav.system_time_encode(TLOG_EPOCH_US + round(s.t_s * 1e6), self._boot_ms)

    def _attitude(self, s: VehicleState) -> Any:
        return self._mav.attitude_encode(self._boot_ms, s.roll_rad, s.pitch_rad, s.yaw_rad,
                                         s.rollspeed_rad_s, s.pitchspeed_rad_s, s.yawspeed_rad_s)

    def _local_position(self, s: VehicleState) -> Any:
        return self._mav.local_position_ned_encode(self._boot_ms, *s.pos_ned_m, *s.vel_ned_m_s)

    def _global_position(self, s: VehicleState) -> Any:
        n, e, d = s.pos_ned_m
        lat, lon = ned_to_global(n, e, self.home_lat_deg, self.home_lon_deg)
        vel_cm = [_clamp_int(v * 100, -32768, 32767) for v in s.vel_ned_m_s]
        return self._mav.global_position_int_encode(
            self._boot_ms, _clamp_int(lat * 1e7, -(2**31), 2**31 - 1), _clamp_int(lon * 1e7, -(2**31), 2**31 - 1),
            _clamp_int((self.home_alt_m - d) * 1000, -(2**31), 2**31 - 1), _clamp_int(-d * 1000, -(2**31), 2**31 - 1),
            *vel_cm, _heading_cdeg(s.yaw_rad))

    def _vfr_hud(self, s: VehicleState) -> Any:
        ground = math.hypot(s.vel_ned_m_s[0], s.vel_ned_m_s[1])
        return self._mav.vfr_hud_encode(ground, ground, _heading_cdeg(s.yaw_rad) // 100, 50 if s.armed else 0,
                                        self.home_alt_m - s.pos_ned_m[2], -s.vel_ned_m_s[2])

    def _mission_current(self, s: VehicleState) -> Any | None:
        if len(self._items) <= 1:
            return None  # home only: no mission
        if self.vehicle.current_item() >= 0:
            state = mavlink.MISSION_STATE_ACTIVE
        elif self._mission_complete:
            state = mavlink.MISSION_STATE_COMPLETE
        elif self._mission_started:
            state = mavlink.MISSION_STATE_PAUSED
        else:
            state = mavlink.MISSION_STATE_NOT_STARTED
        return self._mav.mission_current_encode(self._last_seq, len(self._items) - 1, state)

    def _home_position(self) -> Any:
        return self._mav.home_position_encode(
            round(self.home_lat_deg * 1e7), round(self.home_lon_deg * 1e7), round(self.home_alt_m * 1000),
            0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, TLOG_EPOCH_US + round(self._now_s * 1e6))

    def _autopilot_version(self) -> Any:
        return self._mav.autopilot_version_encode(CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, list(b"pilescan"),
                                                  [0] * 8, [0] * 8, 0, 0, 0)

    # ----- send side ------------------------------------------------------------------------------

    def _statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT, in 50-character chunks sharing an id when longer (MAVLink 2 chunking)."""
        raw = text.encode("ascii", "replace")
        if len(raw) <= STATUSTEXT_LEN:
            self._send(self._mav.statustext_encode(severity, raw))
            return
        self._statustext_id = self._statustext_id % 65535 + 1
        for k in range(0, len(raw), STATUSTEXT_LEN):
            chunk = raw[k:k + STATUSTEXT_LEN]
            self._send(self._mav.statustext_encode(severity, chunk, self._statustext_id, k // STATUSTEXT_LEN))

    def _send(self, msg: Any) -> None:
        buf = self.signer.pack(msg, self._mav) if self.signer is not None else msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        self.transport.send(buf)
        self._log(buf)
        self.stats["tx_messages"] += 1
        self.stats["tx_by_type"][msg.get_type()] += 1

    def _log(self, frame: bytes | bytearray) -> None:
        if self._tlog is not None:
            self._tlog.write(struct.pack(">Q", TLOG_EPOCH_US + round(self._now_s * 1e6)) + bytes(frame))


def _command_name(command: int) -> str:
    """Short operator-facing name: 'COMPONENT_ARM_DISARM' for MAV_CMD_COMPONENT_ARM_DISARM."""
    if command == mavlink.MAVLINK_MSG_ID_SET_MODE:
        return "SET_MODE"
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name.removeprefix("MAV_CMD_") if entry is not None else f"command {command}"


def _clamp_int(value: float, lo: int, hi: int) -> int:
    if not math.isfinite(value):
        return 0
    return max(lo, min(hi, round(value)))


def _heading_cdeg(yaw_rad: float) -> int:
    """Heading 0..35999 centidegrees, as GLOBAL_POSITION_INT wants it."""
    return round(math.degrees(yaw_rad) * 100) % 36000 if math.isfinite(yaw_rad) else 0


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
    """
    if not (math.isfinite(speedup) and speedup > 0):
        raise ValueError(f"speedup must be > 0, got {speedup}")
    t0_sim = vehicle.state().t_s
    t0_wall = clock()
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
    return t_sim - t0_sim
