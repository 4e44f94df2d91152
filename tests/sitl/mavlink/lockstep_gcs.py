"""The tests' ground station: pymavlink's encoder and parser on the far end of an in-process pipe.

Shared by the server's tests and by tests elsewhere that need a lockstep GCS (faults, plans).
"""

import math
import os

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.geodesy import ned_to_global
from sitl.mavlink.server import MavlinkVehicleServer
from sitl.mavlink.transport import PipeTransport
from sitl.vehicle.api import FlightMode
from sitl.vehicle.kinematic_vehicle import KinematicVehicle

HOME_LAT, HOME_LON, HOME_ALT = 53.4668, -2.2339, 50.0
ALT_M = 2.0
RECTANGLE = [(1.0, 1.0), (5.0, 1.0), (5.0, 4.0), (1.0, 4.0)]
GCS_SYS, GCS_COMP = 255, 190
REL_INT = mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT


class RecordingVehicle(KinematicVehicle):
    """The kinematic vehicle, keeping the NavItems the server loaded into it."""

    loaded: list | None = None

    def load_mission(self, items):
        super().load_mission(items)
        self.loaded = list(items)


def fast_vehicle() -> RecordingVehicle:
    return RecordingVehicle(speed_m_s=2.0, yaw_rate_max_rad_s=math.radians(90), altitude_m=ALT_M, climb_rate_m_s=2.0)


class Gcs:
    """The test's ground station: pymavlink's encoder/parser on the far end of an in-process pipe.

    Lockstep: each tick steps the vehicle, lets the server update, and parses what arrived into
    `pending`; expect() consumes up to the first match (like recv_match), run() takes everything.
    """

    def __init__(self, vehicle=None, tlog_path=None, **server_kw):
        self.vehicle = vehicle or fast_vehicle()
        server_end, self.end = PipeTransport.pair()
        self.server = MavlinkVehicleServer(self.vehicle, server_end, tlog_path=tlog_path, **server_kw)
        self.mav = mavlink.MAVLink(None, srcSystem=GCS_SYS, srcComponent=GCS_COMP)
        self.mav.robust_parsing = True
        self.pending: list = []

    def send(self, msg) -> None:
        self.end.send(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256

    def tick(self, step: bool = True) -> None:
        if step:
            self.vehicle.step()
        self.server.update()
        data = self.end.recv()
        msgs = (self.mav.parse_buffer(data) or []) if data else []
        self.pending += [m for m in msgs if m.get_type() != "BAD_DATA"]

    def run(self, seconds: float) -> list:
        """Everything received so far and during the next `seconds` of simulated time."""
        self.tick(step=False)
        for _ in range(round(seconds / self.vehicle.dt_s)):
            self.tick()
        out, self.pending = self.pending, []
        return out

    def expect(self, mtype: str, cond=lambda m: True, within_s: float = 3.0):
        for k in range(round(within_s / self.vehicle.dt_s) + 1):
            self.tick(step=k > 0)
            for i, m in enumerate(self.pending):
                if m.get_type() == mtype and cond(m):
                    del self.pending[:i + 1]
                    return m
        raise AssertionError(f"no {mtype} within {within_s} s")

    def command(self, command: int, *params: float) -> int:
        p = [*params, *[0.0] * (7 - len(params))]
        self.send(self.mav.command_long_encode(1, 1, command, 0, *p))
        return self.expect("COMMAND_ACK", lambda m: m.command == command).result

    def set_mode(self, mode: FlightMode) -> int:
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, int(mode))

    def upload(self, items) -> int:
        """Mission upload protocol, answering each request with the item asked for; the MISSION_ACK type."""
        self.send(self.mav.mission_count_encode(1, 1, len(items)))
        for _ in range(len(items) + 1):
            m = self._next_mission_reply()
            if m.get_type() == "MISSION_ACK":
                return m.type
            self.send(items[m.seq])
        raise AssertionError("upload did not end")

    def _next_mission_reply(self):
        for k in range(300):
            self.tick(step=k > 0)
            for i, m in enumerate(self.pending):
                if m.get_type() in ("MISSION_REQUEST_INT", "MISSION_ACK"):
                    del self.pending[:i + 1]
                    return m
        raise AssertionError("no MISSION_REQUEST_INT or MISSION_ACK")

    def download(self) -> list:
        self.send(self.mav.mission_request_list_encode(1, 1))
        count = self.expect("MISSION_COUNT").count
        items = []
        for seq in range(count):
            self.send(self.mav.mission_request_int_encode(1, 1, seq))
            items.append(self.expect("MISSION_ITEM_INT", lambda m, s=seq: m.seq == s))
        self.send(self.mav.mission_ack_encode(1, 1, mavlink.MAV_MISSION_ACCEPTED))
        return items


def item_int(seq, command=mavlink.MAV_CMD_NAV_WAYPOINT, frame=REL_INT, x=0, y=0, z=ALT_M, p1=0.0, p2=0.0):
    return mavlink.MAVLink_mission_item_int_message(1, 1, seq, frame, command, 0, 1, p1, p2, 0.0, 0.0, x, y, z, 0)


def latlon_e7(north_m: float, east_m: float) -> tuple[int, int]:
    lat, lon = ned_to_global(north_m, east_m, HOME_LAT, HOME_LON)
    return round(lat * 1e7), round(lon * 1e7)


def survey_mission() -> list:
    """Home + take-off + the four corners of a rectangle + land, as MAVProxy would send it."""
    items = [item_int(0, frame=mavlink.MAV_FRAME_GLOBAL, x=round(HOME_LAT * 1e7), y=round(HOME_LON * 1e7),
                      z=HOME_ALT),
             item_int(1, mavlink.MAV_CMD_NAV_TAKEOFF, z=ALT_M)]
    for k, (n, e) in enumerate(RECTANGLE, start=2):
        items.append(item_int(k, x=latlon_e7(n, e)[0], y=latlon_e7(n, e)[1]))
    items.append(item_int(len(items), mavlink.MAV_CMD_NAV_LAND, z=0.0))
    return items


FIELDS = ("seq", "frame", "command", "current", "autocontinue", "param1", "param2", "param3", "param4", "x", "y", "z")


def fields(m) -> tuple:
    return tuple(getattr(m, f) for f in FIELDS)


def status_text(msgs) -> str:
    """All STATUSTEXT text received, chunks joined."""
    return "".join(m.text for m in msgs if m.get_type() == "STATUSTEXT")


def count(msgs, mtype: str) -> int:
    return sum(m.get_type() == mtype for m in msgs)
