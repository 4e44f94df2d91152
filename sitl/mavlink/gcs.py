"""A scripted ground station (pymavlink): upload a plan, arm, AUTO, wait until landed and disarmed.

What an operator does with MAVProxy (`wp load`, `arm throttle`, `mode auto`), as a function, for
the networked SITL run (`python -m tools.fly_networked`) and its test. It speaks only standard
MAVLink, so it flies ArduPilot SITL the same way.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymavlink import mavutil, mavwp

from firmware_py.core.safe_read import InputError, read_bounded

COPTER_AUTO = 3
"""ArduCopter's custom mode number for AUTO (what `pilescan-sitl serve` reports too)."""


class GcsError(RuntimeError):
    """The vehicle did not do what was asked in time (the message says what and why)."""


class ScriptedGcs:
    """One pymavlink connection to the autopilot, as a GCS (system 255)."""

    def __init__(self, url: str, timeout_s: float = 10.0, say: Callable[[str], None] | None = None,
                 signing_key: bytes | None = None) -> None:
        if signing_key is not None and mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
            os.environ["MAVLINK20"] = "1"  # signing is MAVLink 2 only; mavutil picks the version from this
            mavutil.set_dialect("ardupilotmega")
        self.conn = mavutil.mavlink_connection(url, source_system=255, source_component=190, autoreconnect=True)
        if signing_key is not None:  # as MAVProxy's `signing key`: sign ours, check theirs
            self.conn.setup_signing(signing_key, sign_outgoing=True)
        self.say = say or (lambda _m: None)
        self._last_hb = 0.0
        self._heartbeat()
        hb = self.wait(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1, timeout_s)
        if hb is None:
            raise GcsError(f"no HEARTBEAT from an autopilot on {url} within {timeout_s:g} s")
        self.target = (hb.get_srcSystem(), hb.get_srcComponent())
        self.armed = bool(hb.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def close(self) -> None:
        self.conn.close()

    def _heartbeat(self) -> None:
        now = time.monotonic()
        if now - self._last_hb >= 1.0:
            self.conn.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self._last_hb = now

    def wait(self, pred: Callable[[Any], bool], timeout_s: float) -> Any | None:
        """The first message satisfying pred (keeping our heartbeat going and the armed state current)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self._heartbeat()
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            if m is None:
                continue
            kind = m.get_type()
            if kind == "HEARTBEAT" and m.get_srcComponent() == 1:
                self.armed = bool(m.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
            elif kind == "STATUSTEXT":
                self.say(f"vehicle: {m.text}")
            if pred(m):
                return m
        return None

    def upload(self, plan: str | Path, timeout_s: float = 20.0) -> int:
        """Upload a QGC WPL 110 plan with the mission protocol; returns the item count."""
        items = load_plan(plan, self.target)
        n = len(items)
        self.conn.mav.mission_count_send(*self.target, n)
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            m = self.wait(lambda m: m.get_type() in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"),
                           end - time.monotonic())
            if m is None:
                break
            if m.get_type() == "MISSION_ACK":
                if m.type != mavutil.mavlink.MAV_MISSION_ACCEPTED:
                    raise GcsError(f"mission upload refused: MAV_MISSION_RESULT {m.type}")
                self.say(f"mission of {n} items accepted")
                return n
            if not 0 <= m.seq < n:
                raise GcsError(f"the vehicle asked for mission item {m.seq} of a {n}-item plan")
            self.conn.mav.send(items[m.seq])
        raise GcsError(f"mission upload of {plan} timed out after {timeout_s:g} s")

    def command(self, command: int, *params: float, timeout_s: float = 5.0) -> None:
        p = [*params, *[0.0] * (7 - len(params))]
        self.conn.mav.command_long_send(*self.target, command, 0, *p)
        ack = self.wait(lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, timeout_s)
        if ack is None:
            raise GcsError(f"no COMMAND_ACK for command {command} within {timeout_s:g} s")
        if ack.result != mavutil.mavlink.MAV_RESULT_ACCEPTED:
            raise GcsError(f"command {command} refused: MAV_RESULT {ack.result}")

    def arm(self) -> None:
        self.command(mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        self.say("armed")

    def auto(self) -> None:
        self.command(mavutil.mavlink.MAV_CMD_DO_SET_MODE, mavutil.mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                     COPTER_AUTO)
        self.say("mode AUTO")

    def wait_disarmed(self, timeout_s: float) -> None:
        """Until the vehicle has landed and disarmed (the plan's last item is a LAND)."""
        end = time.monotonic() + timeout_s
        is_hb = lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1  # noqa: E731
        if self.wait(lambda m: is_hb(m) and self.armed, 5.0) is None:  # a heartbeat since arming says so
            raise GcsError("the vehicle never reported itself armed")
        if self.wait(lambda m: is_hb(m) and not self.armed, end - time.monotonic()) is None:
            raise GcsError(f"the vehicle was still armed after {timeout_s:g} s")


MAX_PLAN_BYTES = 16 * 1024 * 1024
"""Largest mission plan read: a full 65,535-item mission in QGC WPL text is under 10 MB."""


def load_plan(plan: str | Path, target: tuple[int, int] = (1, 1)) -> list[Any]:
    """The MISSION_ITEM_INT messages of a QGC WPL 110 plan, each checked to fit its wire format (so an upload
    never fails half-way); GcsError naming the file (and the item) for anything else."""
    try:  # a regular file of a plausible size (65,535 items of ~100 bytes), never a FIFO or a device
        first = read_bounded(plan, MAX_PLAN_BYTES, "mission plan").decode("utf-8").split("\n", 1)[0].strip()
    except InputError as exc:
        raise GcsError(str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise GcsError(f"cannot read mission plan {plan}: {exc}") from None
    if first != "QGC WPL 110":
        raise GcsError(f"{plan}: not a QGC WPL 110 mission plan")
    loader = mavwp.MAVWPLoader(target_system=target[0], target_component=target[1])
    try:
        n = loader.load(str(plan))
    except (mavwp.MAVWPError, ValueError, OSError) as exc:  # ValueError: a number that is not one
        raise GcsError(f"{plan}: malformed mission plan: {exc}") from None
    if n == 0:
        raise GcsError(f"{plan}: no mission items")
    items, mav = [], mavutil.mavlink.MAVLink(None)
    for seq in range(n):
        w = loader.wp(seq)
        try:
            msg = mavutil.mavlink.MAVLink_mission_item_int_message(
                *target, seq, w.frame, w.command, w.current, w.autocontinue, w.param1, w.param2, w.param3, w.param4,
                round(w.x * 1e7), round(w.y * 1e7), w.z)
            msg.pack(mav)  # struct.error / OverflowError for a value the message cannot carry
        except (struct.error, OverflowError, ValueError) as exc:
            raise GcsError(f"{plan}: mission item {seq} cannot be sent: {exc}") from None
        items.append(msg)
    return items


def fly_plan(url: str, plan: str | Path, timeout_s: float, say: Callable[[str], None] | None = None,
             fly_s: float | None = None, signing_key: bytes | None = None) -> None:
    """Upload, arm, AUTO, and wait for the landing: one survey flight, as an operator would fly it.
    With fly_s, return that long after AUTO instead (the vehicle flies on)."""
    gcs = ScriptedGcs(url, say=say, signing_key=signing_key)
    try:
        gcs.upload(plan)
        gcs.arm()
        gcs.auto()
        if fly_s is not None:
            gcs.wait(lambda m: False, fly_s)  # keep our heartbeat going meanwhile
        else:
            gcs.wait_disarmed(timeout_s)
    finally:
        gcs.close()
