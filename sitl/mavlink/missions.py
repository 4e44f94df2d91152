"""The mission micro-service: upload, download and clear, and the vehicle's progress through the plan.

Choices, where MAVLink or ArduPilot leave room:

- Mission seq 0 is home, as in ArduPilot: it is stored as sent (and downloaded back unchanged) but
  never flown; vehicle item k is MAVLink seq k + 1 (MISSION_CURRENT, MISSION_ITEM_REACHED). With
  no mission the vehicle reports one item, home, as ArduPilot does.
- Global coordinates become local NED about home (`firmware_py.core.geodesy`). Global altitude is
  above home_alt_m; relative altitude above home. lat = lon = 0 on a NAV item means "where the
  previous item was" (ArduPilot: "here"). NAV_LAND lands on the floor, whatever its altitude.
- Supported items: NAV_WAYPOINT, NAV_TAKEOFF, NAV_LAND, DO_CHANGE_SPEED. DO_CHANGE_SPEED (param2
  m/s, > 0) sets PS_SPEED_MS when the vehicle starts the next NAV item, as ArduPilot runs DO items.
- An item with an out-of-order seq is answered MAV_MISSION_INVALID_SEQUENCE and the upload stays
  open (the expected item is requested again); an invalid item aborts the upload with its error.
- An unanswered request is repeated after MISSION_TIMEOUT_S of the link's clock (the server's: the
  wall clock in `run_realtime`), since the ground station answers in its own time, not the vehicle's.
- The protocol's messages (requests, acks, items, counts) and refusals' reasons go to the client
  that is uploading or asking, never to the others; a mission that was loaded, the items reached
  and mission completion are the vehicle's news, for every client (and the operator's log).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.geodesy import Home
from sitl.mavlink.outbox import Outbox, Peer
from sitl.vehicle.api import CommandRejected, NavItem, NavKind, Vehicle

log = logging.getLogger(__name__)

MAX_MISSION_ITEMS = 1000
MISSION_TIMEOUT_S = 1.5
MISSION_MAX_RETRIES = 5
MAX_ALTITUDE_M = 100_000.0

NAV_COMMANDS = {mavlink.MAV_CMD_NAV_WAYPOINT: NavKind.WAYPOINT, mavlink.MAV_CMD_NAV_TAKEOFF: NavKind.TAKEOFF,
                mavlink.MAV_CMD_NAV_LAND: NavKind.LAND}
DO_COMMANDS = frozenset({mavlink.MAV_CMD_DO_CHANGE_SPEED})
GLOBAL_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT})
RELATIVE_FRAMES = frozenset({mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT, mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT})
LATLON_FRAMES = GLOBAL_FRAMES | RELATIVE_FRAMES
NAV_FRAMES = LATLON_FRAMES | {mavlink.MAV_FRAME_LOCAL_NED}
DO_FRAMES = NAV_FRAMES | {mavlink.MAV_FRAME_MISSION}


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
    peer: Peer  # where the partner's messages come from (the link's name for it)
    count: int
    mission_type: int
    deadline_s: float
    items: list[MissionItem] = field(default_factory=list)
    retries: int = 0


def _src(msg: Any) -> tuple[int, int]:
    return msg.get_srcSystem(), msg.get_srcComponent()


class Missions:
    """The stored mission and its protocol; replies and news go out through `out`.

    `link_now` is the clock the upload timeout runs on (the server's link clock).
    """

    def __init__(self, vehicle: Vehicle, home: Home, mav: Any, out: Outbox, link_now: Callable[[], float]) -> None:
        self.vehicle, self.home, self._mav, self._out = vehicle, home, mav, out
        self._link_now = link_now
        self._upload: _Upload | None = None
        self._set_stored_mission([self._home_item()])
        self.handlers: dict[str, Callable[[Any], None]] = {
            "MISSION_COUNT": self._on_mission_count, "MISSION_ITEM_INT": self._on_mission_item,
            "MISSION_ITEM": self._on_mission_item, "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "MISSION_REQUEST_INT": self._on_mission_request, "MISSION_REQUEST": self._on_mission_request,
            "MISSION_CLEAR_ALL": self._on_mission_clear_all,
        }
        """Message type -> handler, for the messages this service answers."""

    @property
    def items(self) -> list[MissionItem]:
        """The stored mission, home (seq 0) included, as it would be downloaded."""
        return list(self._items)

    def cancel_upload(self) -> None:
        self._upload = None

    def restart_timer(self) -> None:
        """An upload in progress gets a whole timeout from now (the link clock changed)."""
        if self._upload is not None:
            self._upload.deadline_s = self._link_now() + MISSION_TIMEOUT_S

    # ----- upload ---------------------------------------------------------------------------------

    def _on_mission_count(self, msg: Any) -> None:
        partner, mtype = _src(msg), msg.mission_type
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
            self._out.say(mavlink.MAV_SEVERITY_WARNING, f"mission of {msg.count} items: at most {MAX_MISSION_ITEMS}")
            return
        if msg.count == 0:
            self._accept_mission(partner, [])
            return
        self._upload = _Upload(partner, self._out.asker(), msg.count, mtype, self._link_now() + MISSION_TIMEOUT_S)
        self._request_item(self._upload)

    def _request_item(self, up: _Upload) -> None:
        self._out.send_to(self._mav.mission_request_int_encode(up.partner[0], up.partner[1], len(up.items),
                                                               up.mission_type), up.peer)
        up.deadline_s = self._link_now() + MISSION_TIMEOUT_S

    def _on_mission_item(self, msg: Any) -> None:
        up = self._upload
        if up is None or _src(msg) != up.partner or msg.mission_type != up.mission_type:
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
            self._out.say(mavlink.MAV_SEVERITY_WARNING, f"mission item {msg.seq} rejected: {reason}")
            return
        up.items.append(item)
        up.retries = 0
        if len(up.items) < up.count:
            self._request_item(up)
        else:
            self._upload = None
            self._accept_mission(up.partner, up.items)

    def service_upload_timeout(self) -> None:
        """Request the awaited item again when the partner has been quiet a timeout; give up after retries."""
        up = self._upload
        if up is None or self._link_now() < up.deadline_s:
            return
        up.retries += 1
        if up.retries > MISSION_MAX_RETRIES:
            self._upload = None
            self._out.send_to(self._mav.mission_ack_encode(up.partner[0], up.partner[1],
                                                           mavlink.MAV_MISSION_OPERATION_CANCELLED, up.mission_type),
                              up.peer)
            self._out.say_to(up.peer, mavlink.MAV_SEVERITY_WARNING, f"mission upload timed out at item {len(up.items)}")
            log.warning("mission upload timed out at item %d of %d", len(up.items), up.count)
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
            self._out.say(mavlink.MAV_SEVERITY_WARNING, f"mission not loaded: {exc}")
            return
        self._set_stored_mission(stored, nav_seq, do_items)
        self._mission_ack(partner, mavlink.MAV_MISSION_ACCEPTED, mavlink.MAV_MISSION_TYPE_MISSION)
        if items:
            self._out.announce(mavlink.MAV_SEVERITY_INFO, f"mission received: {len(items) - 1} items after home")
            log.info("mission uploaded: %d items after home", len(items) - 1)
        else:
            log.info("mission cleared")

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
            n, e = self.home.to_ned(item.x / 1e7, item.y / 1e7)
        alt = item.z - self.home.alt_m if item.frame in GLOBAL_FRAMES else item.z
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
                           round(self.home.lat_deg * 1e7), round(self.home.lon_deg * 1e7), self.home.alt_m)

    def _mission_ack(self, partner: tuple[int, int], result: int, mission_type: int) -> None:
        """To the asker (every ack answers a message being handled)."""
        self._out.reply(self._mav.mission_ack_encode(partner[0], partner[1], result, mission_type))

    # ----- download and clear ---------------------------------------------------------------------

    def _on_mission_request_list(self, msg: Any) -> None:
        count = len(self._items) if msg.mission_type == mavlink.MAV_MISSION_TYPE_MISSION else 0
        src = _src(msg)
        self._out.reply(self._mav.mission_count_encode(src[0], src[1], count, msg.mission_type))

    def _on_mission_request(self, msg: Any) -> None:
        src = _src(msg)
        if msg.mission_type != mavlink.MAV_MISSION_TYPE_MISSION or not 0 <= msg.seq < len(self._items):
            self._mission_ack(src, mavlink.MAV_MISSION_INVALID_SEQUENCE, msg.mission_type)
            return
        it = self._items[msg.seq]
        common = (src[0], src[1], it.seq, it.frame, it.command, it.current, it.autocontinue,
                  it.param1, it.param2, it.param3, it.param4)
        if msg.get_type() == "MISSION_REQUEST_INT":
            self._out.reply(self._mav.mission_item_int_encode(*common, it.x, it.y, it.z, it.mission_type))
        else:
            scale = _xy_scale(it.frame)
            self._out.reply(self._mav.mission_item_encode(*common, it.x / scale, it.y / scale, it.z,
                                                          it.mission_type))

    def _on_mission_clear_all(self, msg: Any) -> None:
        if msg.mission_type in (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_ALL):
            self._upload = None
            self._accept_mission(_src(msg), [])
        else:
            self._mission_ack(_src(msg), mavlink.MAV_MISSION_ACCEPTED, msg.mission_type)

    # ----- the vehicle's progress -----------------------------------------------------------------

    def report_vehicle_events(self) -> None:
        """MISSION_ITEM_REACHED for what the vehicle reached; DO items run as it starts the NAV items after them."""
        for index in self.vehicle.pop_reached():
            if 0 <= index < len(self._nav_seq):
                self._out.broadcast(self._mav.mission_item_reached_encode(self._nav_seq[index]))
                self._run_do_items(index + 1)
                if index == len(self._nav_seq) - 1:
                    self._mission_complete = True  # the vehicle announces it (its STATUSTEXT, in the log too)
        current = self.vehicle.current_item()
        if 0 <= current < len(self._nav_seq) and current != self._last_current:
            if current == 0:
                self._do_done.clear()  # (re)started: DO items run again
            self._run_do_items(current)
            self._mission_started, self._mission_complete = True, False
            self._last_seq = self._nav_seq[current]
        self._last_current = current

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
                    self._out.announce(mavlink.MAV_SEVERITY_WARNING, f"mission item {seq}: {exc}")
            self._out.broadcast(self._mav.mission_item_reached_encode(seq))

    def mission_current(self) -> Any | None:
        """The MISSION_CURRENT stream's message; None with no mission (home only), as ArduPilot."""
        if len(self._items) <= 1:
            return None
        if self.vehicle.current_item() >= 0:
            state = mavlink.MISSION_STATE_ACTIVE
        elif self._mission_complete:
            state = mavlink.MISSION_STATE_COMPLETE
        elif self._mission_started:
            state = mavlink.MISSION_STATE_PAUSED
        else:
            state = mavlink.MISSION_STATE_NOT_STARTED
        return self._mav.mission_current_encode(self._last_seq, len(self._items) - 1, state)
