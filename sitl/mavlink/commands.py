"""The command micro-service: COMMAND_LONG, COMMAND_INT and SET_MODE, each answered by a COMMAND_ACK.

A refused command is acked DENIED (UNSUPPORTED when we lack it) and followed by a STATUSTEXT
saying why, so an operator at MAVProxy sees the reason and not just "failed". COMMAND_ACK for
SET_MODE carries command = 11 (the message id), as ArduPilot sends it. The ack, the messages a
command asks for and the reason for a refusal go to the asker alone.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink.outbox import Outbox
from sitl.mavlink.streams import StreamSchedule
from sitl.vehicle.api import CommandRejected, FlightMode, Vehicle

FORCE_DISARM_MAGIC = 21196
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2)
FLIGHT_SW_VERSION = (4 << 24) | (5 << 16) | (0 << 8) | mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL
"""Reported as ArduCopter 4.5.0 so GCSs enable their ArduPilot features (mode names, MISSION_INT)."""

Params7 = tuple[float, ...]


class _Unsupported(Exception):
    """A command or message id this vehicle does not implement (MAV_RESULT_UNSUPPORTED)."""


def command_name(command: int) -> str:
    """Short operator-facing name: 'COMPONENT_ARM_DISARM' for MAV_CMD_COMPONENT_ARM_DISARM."""
    if command == mavlink.MAVLINK_MSG_ID_SET_MODE:
        return "SET_MODE"
    entry = mavlink.enums["MAV_CMD"].get(command)
    return entry.name.removeprefix("MAV_CMD_") if entry is not None else f"command {command}"


def _as_int(value: float, what: str) -> int:
    if not (math.isfinite(value) and value == int(value)):
        raise ValueError(f"{what} must be an integer, got {value}")
    return int(value)


class Commands:
    """Runs commands on the vehicle and on the stream schedule; replies and reasons go to the asker (`out`).

    `build(msg_id)` encodes a streamed message now (REQUEST_MESSAGE); `home_position()` encodes
    HOME_POSITION; `link_now()` is the clock the schedule runs on.
    """

    def __init__(self, vehicle: Vehicle, streams: StreamSchedule, mav: Any, out: Outbox,
                 build: Callable[[int], Any | None], home_position: Callable[[], Any],
                 link_now: Callable[[], float]) -> None:
        self.vehicle, self.streams, self._mav, self._out = vehicle, streams, mav, out
        self._build, self._home_position, self._link_now = build, home_position, link_now
        self._commands: dict[int, Callable[[Params7], list[Any]]] = {
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
        self.handlers: dict[str, Callable[[Any], None]] = {
            "COMMAND_LONG": self._on_command_long, "COMMAND_INT": self._on_command_int, "SET_MODE": self._on_set_mode,
        }
        """Message type -> handler, for the messages this service answers."""

    def _on_command_long(self, msg: Any) -> None:
        p = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._run_command(msg, msg.command, p)

    def _on_command_int(self, msg: Any) -> None:
        p = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._run_command(msg, msg.command, p)

    def _on_set_mode(self, msg: Any) -> None:
        self._run_command(msg, mavlink.MAVLINK_MSG_ID_SET_MODE, (float(msg.base_mode), float(msg.custom_mode)),
                          handler=self._cmd_set_mode)

    def _run_command(self, msg: Any, command: int, params: Params7,
                     handler: Callable[[Params7], list[Any]] | None = None) -> None:
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
        self._out.reply(self._mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                                     msg.get_srcComponent()))
        for m in followups:
            self._out.reply(m)
        if reason is not None:
            self._out.say(mavlink.MAV_SEVERITY_WARNING, f"{command_name(command)}: {reason}")

    # ----- the vehicle ----------------------------------------------------------------------------

    def _cmd_arm_disarm(self, p: Params7) -> list[Any]:
        if p[0] == 1:
            self.vehicle.arm()
        elif p[0] == 0:
            self.vehicle.disarm(force=p[1] == FORCE_DISARM_MAGIC)
        else:
            raise ValueError(f"param1 must be 1 (arm) or 0 (disarm), got {p[0]}")
        return []

    def _cmd_takeoff(self, p: Params7) -> list[Any]:
        self.vehicle.takeoff(p[6])
        return []

    def _cmd_mission_start(self, p: Params7) -> list[Any]:
        self.vehicle.start_mission()
        return []

    def _cmd_set_mode(self, p: Params7) -> list[Any]:
        base = _as_int(p[0], "base mode")
        if not base & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            raise ValueError("only custom (ArduCopter) modes are supported: set MAV_MODE_FLAG_CUSTOM_MODE_ENABLED")
        number = _as_int(p[1], "custom mode")
        try:
            mode = FlightMode(number)
        except ValueError:
            raise ValueError(f"unknown flight mode {number}") from None
        self.vehicle.set_mode(mode)
        return []

    # ----- messages -------------------------------------------------------------------------------

    def _streamed(self, msg_id: float) -> int:
        mid = _as_int(msg_id, "message id")
        if mid not in self.streams:
            raise _Unsupported(f"message {msg_id:g} is not streamed")
        return mid

    def _cmd_set_message_interval(self, p: Params7) -> list[Any]:
        self.streams.set_interval(self._streamed(p[0]), p[1], self._link_now())
        return []

    def _cmd_get_message_interval(self, p: Params7) -> list[Any]:
        mid = self._streamed(p[0])
        return [self._mav.message_interval_encode(mid, self.streams.interval_us(mid))]

    def _cmd_request_message(self, p: Params7) -> list[Any]:
        msg_id = _as_int(p[0], "message id")
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return [self._autopilot_version()]
        if msg_id in self.streams:
            msg = self._build(msg_id)
            if msg is None:
                raise ValueError(f"message {msg_id} is not available now")
            return [msg]
        raise _Unsupported(f"message {msg_id} cannot be requested")

    def _cmd_autopilot_capabilities(self, p: Params7) -> list[Any]:
        return [self._autopilot_version()]

    def _cmd_get_home_position(self, p: Params7) -> list[Any]:
        return [self._home_position()]

    def _autopilot_version(self) -> Any:
        return self._mav.autopilot_version_encode(CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, list(b"pilescan"),
                                                  [0] * 8, [0] * 8, 0, 0, 0)
