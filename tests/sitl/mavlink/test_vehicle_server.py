import math
import os
import random
import threading
import time

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink.vehicle_server import (
    TLOG_EPOCH_US,
    MavlinkVehicleServer,
    PipeTransport,
    UdpTransport,
    global_to_ned,
    make_transport,
    ned_to_global,
    run_realtime,
)
from sitl.vehicle.api import FlightMode, NavKind
from sitl.vehicle.kinematic_vehicle import KinematicVehicle

mavutil.set_dialect("ardupilotmega")  # MAVLink 2, whatever imported mavutil first

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

    def __init__(self, vehicle=None, tlog_path=None):
        self.vehicle = vehicle or fast_vehicle()
        server_end, self.end = PipeTransport.pair()
        self.server = MavlinkVehicleServer(self.vehicle, server_end, tlog_path=tlog_path)
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


# ----- identity and streams -----------------------------------------------------------------------

def test_that_the_server_announces_an_ardupilot_quadrotor_in_stabilize_once_a_second():
    gcs = Gcs()
    msgs = gcs.run(3.0)
    hbs = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert len(hbs) == 4  # t = 0, 1, 2, 3
    hb = hbs[-1]
    assert (hb.type, hb.autopilot, hb.custom_mode) == (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                       FlightMode.STABILIZE)
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.system_status == mavlink.MAV_STATE_STANDBY
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1


def test_that_the_default_streams_run_at_their_rates_in_simulated_time():
    gcs = Gcs()
    gcs.run(0.5)
    msgs = gcs.run(2.0)
    assert count(msgs, "ATTITUDE") == pytest.approx(100, abs=2)
    assert count(msgs, "LOCAL_POSITION_NED") == pytest.approx(100, abs=2)
    assert count(msgs, "GLOBAL_POSITION_INT") == pytest.approx(10, abs=1)
    assert count(msgs, "SYS_STATUS") == pytest.approx(2, abs=1)
    assert count(msgs, "SYSTEM_TIME") == pytest.approx(2, abs=1)
    assert count(msgs, "MISSION_CURRENT") == 0  # no mission yet
    att = [m for m in msgs if m.get_type() == "ATTITUDE"][-1]
    assert att.time_boot_ms == round(gcs.vehicle.state().t_s * 1000)
    st = [m for m in msgs if m.get_type() == "SYSTEM_TIME"][-1]
    assert st.time_unix_usec == TLOG_EPOCH_US + st.time_boot_ms * 1000
    sys_status = [m for m in msgs if m.get_type() == "SYS_STATUS"][-1]
    assert sys_status.voltage_battery == 16000


def test_that_global_position_is_home_plus_the_local_offset():
    gcs = Gcs(RecordingVehicle(home_ned_m=(10.0, -20.0, 0.0)))
    gpi = gcs.expect("GLOBAL_POSITION_INT")
    n, e = global_to_ned(gpi.lat / 1e7, gpi.lon / 1e7, HOME_LAT, HOME_LON)
    assert (n, e) == (pytest.approx(10.0, abs=0.02), pytest.approx(-20.0, abs=0.02))
    assert (gpi.alt, gpi.relative_alt) == (50_000, 0)


def test_that_set_message_interval_changes_the_attitude_rate_and_can_disable_and_restore_it():
    gcs = Gcs()
    assert count(gcs.run(1.0), "ATTITUDE") == pytest.approx(50, abs=1)
    attitude = mavlink.MAVLINK_MSG_ID_ATTITUDE
    assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, attitude, 100_000) == mavlink.MAV_RESULT_ACCEPTED
    gcs.run(0.2)
    assert count(gcs.run(1.0), "ATTITUDE") == pytest.approx(10, abs=1)
    gcs.send(gcs.mav.command_long_encode(1, 1, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, 0, attitude, 0, 0, 0, 0, 0, 0))
    assert gcs.expect("MESSAGE_INTERVAL").interval_us == 100_000
    assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, attitude, -1) == mavlink.MAV_RESULT_ACCEPTED
    assert count(gcs.run(1.0), "ATTITUDE") == 0
    assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, attitude, 0) == mavlink.MAV_RESULT_ACCEPTED
    gcs.run(0.2)
    assert count(gcs.run(1.0), "ATTITUDE") == pytest.approx(50, abs=1)


@pytest.mark.parametrize(("msg_id", "interval", "result"), [
    (9999, 100_000, mavlink.MAV_RESULT_UNSUPPORTED),
    (mavlink.MAVLINK_MSG_ID_ATTITUDE, -5, mavlink.MAV_RESULT_DENIED),
    (mavlink.MAVLINK_MSG_ID_ATTITUDE, math.nan, mavlink.MAV_RESULT_DENIED),
    (math.nan, 100_000, mavlink.MAV_RESULT_DENIED)])
def test_that_set_message_interval_refuses_unknown_messages_and_bad_intervals(msg_id, interval, result):
    gcs = Gcs()
    assert gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, interval) == result
    assert count(gcs.run(1.0), "ATTITUDE") == pytest.approx(50, abs=1)


def test_that_timesync_requests_are_answered_with_simulated_nanoseconds_and_the_request_echoed():
    gcs = Gcs()
    gcs.run(1.23)
    gcs.send(gcs.mav.timesync_encode(0, 987_654_321))
    reply = gcs.expect("TIMESYNC")
    assert (reply.tc1, reply.ts1) == (1_230_000_000, 987_654_321)
    gcs.send(gcs.mav.timesync_encode(5, 1))  # a reply to someone else's request: not answered
    assert count(gcs.run(0.1), "TIMESYNC") == 0


def test_that_request_message_gives_autopilot_version_home_position_and_streamed_messages():
    gcs = Gcs()
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == 0
    version = gcs.expect("AUTOPILOT_VERSION")
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    assert version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert gcs.command(mavlink.MAV_CMD_GET_HOME_POSITION) == mavlink.MAV_RESULT_ACCEPTED
    home = gcs.expect("HOME_POSITION")
    assert (home.latitude, home.longitude, home.altitude) == (534668000, -22339000, 50000)
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION) == 0
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_SYS_STATUS) == 0
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 9999) == mavlink.MAV_RESULT_UNSUPPORTED


def test_that_legacy_request_data_stream_is_ignored_without_error():
    gcs = Gcs()
    gcs.send(gcs.mav.request_data_stream_encode(1, 1, mavlink.MAV_DATA_STREAM_ALL, 4, 1))
    msgs = gcs.run(1.0)
    assert gcs.server.stats["rx_by_type"]["REQUEST_DATA_STREAM"] == 1
    assert gcs.server.stats["handler_errors"] == 0 and count(msgs, "ATTITUDE") == pytest.approx(50, abs=1)


# ----- commands -----------------------------------------------------------------------------------

def test_that_arm_and_mode_changes_show_in_the_heartbeat_and_vehicle_status_texts_are_forwarded():
    gcs = Gcs()
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.expect("STATUSTEXT").text == "armed"
    assert gcs.set_mode(FlightMode.GUIDED) == mavlink.MAV_RESULT_ACCEPTED
    hb = gcs.expect("HEARTBEAT")
    assert hb.custom_mode == FlightMode.GUIDED and hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    assert hb.system_status == mavlink.MAV_STATE_ACTIVE


def test_that_set_mode_message_and_command_int_change_the_mode_too():
    gcs = Gcs()
    gcs.send(gcs.mav.set_mode_encode(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, FlightMode.LOITER))
    ack = gcs.expect("COMMAND_ACK")
    assert (ack.command, ack.result) == (mavlink.MAVLINK_MSG_ID_SET_MODE, mavlink.MAV_RESULT_ACCEPTED)
    assert gcs.vehicle.state().mode is FlightMode.LOITER
    gcs.send(gcs.mav.command_int_encode(1, 1, 0, mavlink.MAV_CMD_DO_SET_MODE, 0, 0, 1, FlightMode.GUIDED, 0, 0,
                                        0, 0, 0))
    assert gcs.expect("COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.vehicle.state().mode is FlightMode.GUIDED


def test_that_guided_takeoff_by_command_climbs_to_the_altitude():
    gcs = Gcs()
    gcs.set_mode(FlightMode.GUIDED)
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    assert gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0) == mavlink.MAV_RESULT_ACCEPTED
    pos = gcs.expect("LOCAL_POSITION_NED", lambda m: m.z <= -3.0 + 1e-6, within_s=5.0)
    assert (pos.x, pos.y) == (0.0, 0.0)


def _in_flight(gcs: Gcs) -> None:
    gcs.set_mode(FlightMode.GUIDED)
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 3.0)
    gcs.run(1.0)


@pytest.mark.parametrize(("setup", "command", "params", "reason"), [
    ("guided", mavlink.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, 3.0), "armed"),
    ("armed", mavlink.MAV_CMD_DO_SET_MODE, (1, FlightMode.AUTO), "no mission"),
    ("armed", mavlink.MAV_CMD_MISSION_START, (), "no mission"),
    ("flying", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (1,), "already armed"),
    ("flying", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (0,), "in flight"),
    ("flying", mavlink.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, 3.0), "landed"),
    ("guided", mavlink.MAV_CMD_DO_SET_MODE, (1, 99), "unknown flight mode 99"),
    ("guided", mavlink.MAV_CMD_DO_SET_MODE, (0, FlightMode.LOITER), "custom"),
    ("guided", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, (0.5,), "param1"),
])
def test_that_commands_in_the_wrong_state_are_denied_with_the_reason_in_a_statustext(setup, command, params, reason):
    gcs = Gcs()
    if setup == "flying":
        _in_flight(gcs)
    else:
        gcs.set_mode(FlightMode.GUIDED)
        if setup == "armed":
            gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    gcs.run(0.1)
    before = gcs.vehicle.state()
    assert gcs.command(command, *params) == mavlink.MAV_RESULT_DENIED
    assert reason in status_text(gcs.run(0.05))
    after = gcs.vehicle.state()
    assert (after.armed, after.mode, after.landed) == (before.armed, before.mode, before.landed)


def test_that_a_forced_disarm_in_flight_is_accepted():
    gcs = Gcs()
    _in_flight(gcs)
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196) == mavlink.MAV_RESULT_ACCEPTED
    s = gcs.vehicle.state()
    assert not s.armed and s.landed


def test_that_unknown_commands_are_unsupported_and_commands_for_another_system_are_ignored():
    gcs = Gcs()
    assert gcs.command(31000) == mavlink.MAV_RESULT_UNSUPPORTED
    gcs.send(gcs.mav.command_long_encode(7, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
    assert count(gcs.run(0.5), "COMMAND_ACK") == 0
    assert not gcs.vehicle.state().armed and gcs.server.stats["rx_not_for_us"] == 1


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, 1e30, -1.0])
def test_that_every_command_with_hostile_params_is_acked_and_never_crashes(value):
    gcs = Gcs()
    commands = [mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_MISSION_START,
                mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL,
                mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                mavlink.MAV_CMD_GET_HOME_POSITION]
    for cmd in commands:
        gcs.send(gcs.mav.command_long_encode(1, 1, cmd, 0, *[value] * 7))
    acks = [m.command for m in gcs.run(0.1) if m.get_type() == "COMMAND_ACK"]
    assert acks == commands
    assert gcs.server.stats["handler_errors"] == 0


# ----- parameters ---------------------------------------------------------------------------------

def test_that_param_request_list_sends_every_parameter_as_real32_with_count_and_index():
    gcs = Gcs()
    gcs.send(gcs.mav.param_request_list_encode(1, 1))
    values = [m for m in gcs.run(0.1) if m.get_type() == "PARAM_VALUE"]
    assert {m.param_id: m.param_value for m in values} == pytest.approx(gcs.vehicle.params)
    assert sorted(m.param_index for m in values) == [0, 1, 2]
    assert {m.param_count for m in values} == {3} and {m.param_type for m in values} == {9}


def test_that_param_request_read_works_by_name_and_by_index():
    gcs = Gcs()
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"PS_ALT_M", -1))
    assert gcs.expect("PARAM_VALUE").param_value == pytest.approx(ALT_M)
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"", 0))
    first = gcs.expect("PARAM_VALUE")
    assert first.param_index == 0 and first.param_id == sorted(gcs.vehicle.params)[0]


def test_that_param_set_of_ps_speed_ms_is_echoed_and_takes_effect_in_flight():
    gcs = Gcs()
    gcs.send(gcs.mav.param_set_encode(1, 1, b"PS_SPEED_MS", 3.5, mavlink.MAV_PARAM_TYPE_REAL32))
    echo = gcs.expect("PARAM_VALUE")
    assert (echo.param_id, echo.param_value) == ("PS_SPEED_MS", 3.5)
    assert gcs.upload(survey_mission()) == mavlink.MAV_MISSION_ACCEPTED
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    gcs.command(mavlink.MAV_CMD_MISSION_START)
    msgs = gcs.run(6.0)
    speeds = [math.hypot(m.vx, m.vy) for m in msgs if m.get_type() == "LOCAL_POSITION_NED"]
    assert max(speeds) == pytest.approx(3.5)


@pytest.mark.parametrize(("name", "value", "reason"), [(b"NO_SUCH_PARAM", 1.0, "unknown parameter NO_SUCH_PARAM"),
                                                       (b"PS_SPEED_MS", math.nan, "nan"),
                                                       (b"PS_SPEED_MS", 99.0, "99")])
def test_that_param_set_of_an_unknown_name_or_bad_value_changes_nothing_and_says_why(name, value, reason):
    gcs = Gcs()
    before = dict(gcs.vehicle.params)
    gcs.send(gcs.mav.param_set_encode(1, 1, name, value, mavlink.MAV_PARAM_TYPE_REAL32))
    msgs = gcs.run(0.1)
    assert any(m.get_type() == "STATUSTEXT" and reason in m.text for m in msgs)
    echoes = [m for m in msgs if m.get_type() == "PARAM_VALUE"]
    if name == b"NO_SUCH_PARAM":
        assert echoes == []
    else:
        assert [m.param_value for m in echoes] == [pytest.approx(before["PS_SPEED_MS"])]
    assert gcs.vehicle.params == before and gcs.server.stats["handler_errors"] == 0


# ----- missions -----------------------------------------------------------------------------------

@pytest.mark.parametrize("start", ["set_mode", "do_set_mode", "mission_start"])
def test_that_a_survey_mission_uploads_downloads_identically_and_every_item_is_reached(start):
    gcs = Gcs()
    mission = survey_mission()
    assert gcs.upload(mission) == mavlink.MAV_MISSION_ACCEPTED
    assert [fields(m) for m in gcs.download()] == [fields(m) for m in mission]
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    if start == "set_mode":
        gcs.send(gcs.mav.set_mode_encode(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, FlightMode.AUTO))
        assert gcs.expect("COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
    elif start == "do_set_mode":
        assert gcs.set_mode(FlightMode.AUTO) == mavlink.MAV_RESULT_ACCEPTED
    else:
        assert gcs.command(mavlink.MAV_CMD_MISSION_START) == mavlink.MAV_RESULT_ACCEPTED
    msgs = []
    for _ in range(60):
        msgs += gcs.run(1.0)
        if not gcs.vehicle.state().armed:
            break
    reached = [m.seq for m in msgs if m.get_type() == "MISSION_ITEM_REACHED"]
    assert reached == [1, 2, 3, 4, 5, 6]
    currents = {m.seq for m in msgs if m.get_type() == "MISSION_CURRENT"}
    assert {2, 3, 4, 5} <= currents and 0 not in currents
    assert any(m.get_type() == "STATUSTEXT" and m.text == "mission complete" for m in msgs)
    # the corners were flown where the lat/lon put them
    positions = [(m.x, m.y) for m in msgs if m.get_type() == "LOCAL_POSITION_NED"]
    for corner in RECTANGLE:
        assert min(math.dist(p, corner) for p in positions) < 0.12
    msgs = gcs.run(1.5)
    last_hb = [m for m in msgs if m.get_type() == "HEARTBEAT"][-1]
    assert not last_hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    current = [m for m in msgs if m.get_type() == "MISSION_CURRENT"][-1]
    assert (current.seq, current.total, current.mission_state) == (6, 6, mavlink.MISSION_STATE_COMPLETE)


def test_that_mission_frames_convert_to_local_ned_and_home_is_not_flown():
    gcs = Gcs()
    lat, lon = latlon_e7(3.0, -4.0)
    items = [item_int(0, frame=mavlink.MAV_FRAME_GLOBAL, x=round(HOME_LAT * 1e7), y=round(HOME_LON * 1e7), z=HOME_ALT),
             item_int(1, mavlink.MAV_CMD_NAV_TAKEOFF, z=2.5),
             item_int(2, x=lat, y=lon, z=3.0),                                             # relative altitude
             item_int(3, frame=mavlink.MAV_FRAME_GLOBAL_INT, x=lat, y=lon, z=HOME_ALT + 4.0),  # above sea level
             item_int(4, frame=mavlink.MAV_FRAME_LOCAL_NED, x=12_500, y=-20_000, z=-5.0),  # metres x 1e4, down
             item_int(5, mavlink.MAV_CMD_NAV_LAND, z=7.0)]                                  # lat/lon 0: "here"
    assert gcs.upload(items) == mavlink.MAV_MISSION_ACCEPTED
    loaded = gcs.vehicle.loaded
    assert [it.kind for it in loaded] == [NavKind.TAKEOFF, NavKind.WAYPOINT, NavKind.WAYPOINT, NavKind.WAYPOINT,
                                          NavKind.LAND]
    assert loaded[0].down_m == -2.5
    for it, down in zip(loaded[1:3], (-3.0, -4.0), strict=True):
        assert (it.north_m, it.east_m, it.down_m) == (pytest.approx(3.0, abs=0.01), pytest.approx(-4.0, abs=0.01),
                                                      pytest.approx(down))
    assert (loaded[3].north_m, loaded[3].east_m, loaded[3].down_m) == (1.25, -2.0, -5.0)
    assert (loaded[4].north_m, loaded[4].east_m, loaded[4].down_m) == (1.25, -2.0, 0.0)


def test_that_a_float_mission_item_is_accepted_and_a_non_int_request_is_answered_in_degrees():
    gcs = Gcs()
    lat, lon = ned_to_global(2.0, 2.0, HOME_LAT, HOME_LON)
    home = mavlink.MAVLink_mission_item_message(1, 1, 0, 0, 16, 0, 1, 0, 0, 0, 0, HOME_LAT, HOME_LON, HOME_ALT, 0)
    wp = mavlink.MAVLink_mission_item_message(1, 1, 1, 3, 16, 0, 1, 0, 0, 0, 0, lat, lon, 2.0, 0)
    assert gcs.upload([home, wp]) == mavlink.MAV_MISSION_ACCEPTED
    gcs.send(gcs.mav.mission_request_encode(1, 1, 1))
    item = gcs.expect("MISSION_ITEM")
    # MISSION_ITEM carries float32 degrees (~0.5 m here): why MISSION_ITEM_INT exists
    assert (item.x, item.y, item.z) == (pytest.approx(lat, abs=1e-5), pytest.approx(lon, abs=1e-5), 2.0)
    assert gcs.vehicle.loaded[0].north_m == pytest.approx(2.0, abs=0.5)


HOME_ITEM = item_int(0, frame=mavlink.MAV_FRAME_GLOBAL, x=round(HOME_LAT * 1e7), y=round(HOME_LON * 1e7), z=HOME_ALT)


@pytest.mark.parametrize(("bad_item", "error"), [
    (mavlink.MAVLink_mission_item_message(1, 1, 1, 3, 16, 0, 1, 0, 0, 0, 0, math.nan, HOME_LON, 2.0, 0),
     mavlink.MAV_MISSION_INVALID_PARAM5_X),
    (item_int(1, x=950_000_000, y=0), mavlink.MAV_MISSION_INVALID_PARAM5_X),
    (item_int(1, x=534_668_000, y=2_000_000_000), mavlink.MAV_MISSION_INVALID_PARAM6_Y),
    (mavlink.MAVLink_mission_item_message(1, 1, 1, 3, 16, 0, 1, 0, 0, 0, 0, HOME_LAT, math.inf, 2.0, 0),
     mavlink.MAV_MISSION_INVALID_PARAM6_Y),
    (item_int(1, x=534_668_000, y=-22_339_000, z=math.nan), mavlink.MAV_MISSION_INVALID_PARAM7),
    (item_int(1, frame=mavlink.MAV_FRAME_GLOBAL_TERRAIN_ALT_INT), mavlink.MAV_MISSION_UNSUPPORTED_FRAME),
    (item_int(1, frame=mavlink.MAV_FRAME_MISSION), mavlink.MAV_MISSION_UNSUPPORTED_FRAME),
    (item_int(1, command=mavlink.MAV_CMD_NAV_LOITER_UNLIM), mavlink.MAV_MISSION_UNSUPPORTED),
    (item_int(1, command=mavlink.MAV_CMD_DO_CHANGE_SPEED, frame=mavlink.MAV_FRAME_MISSION, p2=math.nan),
     mavlink.MAV_MISSION_INVALID_PARAM2),
])
def test_that_a_malformed_mission_item_gets_its_mission_ack_error_and_leaves_the_old_mission(bad_item, error):
    gcs = Gcs()
    assert gcs.upload(survey_mission()) == mavlink.MAV_MISSION_ACCEPTED
    assert gcs.upload([HOME_ITEM, bad_item, item_int(2)]) == error
    assert any(m.get_type() == "STATUSTEXT" and "mission item 1 rejected" in m.text for m in gcs.run(0.05))
    assert len(gcs.download()) == len(survey_mission())
    assert len(gcs.vehicle.loaded) == len(survey_mission()) - 1


def test_that_an_out_of_order_item_gets_invalid_sequence_and_the_upload_can_still_finish():
    gcs = Gcs()
    mission = survey_mission()
    gcs.send(gcs.mav.mission_count_encode(1, 1, len(mission)))
    assert gcs.expect("MISSION_REQUEST_INT").seq == 0
    gcs.send(mission[2])
    assert gcs.expect("MISSION_ACK").type == mavlink.MAV_MISSION_INVALID_SEQUENCE
    for seq in range(len(mission)):
        req = gcs.expect("MISSION_REQUEST_INT", lambda m, s=seq: m.seq == s)
        gcs.send(mission[req.seq])
    assert gcs.expect("MISSION_ACK").type == mavlink.MAV_MISSION_ACCEPTED


def test_that_more_than_a_thousand_items_get_no_space():
    gcs = Gcs()
    gcs.send(gcs.mav.mission_count_encode(1, 1, 1001))
    assert gcs.expect("MISSION_ACK").type == mavlink.MAV_MISSION_NO_SPACE


def test_that_an_unanswered_upload_is_requested_again_on_a_simulated_timeout_then_cancelled():
    gcs = Gcs()
    gcs.send(gcs.mav.mission_count_encode(1, 1, 3))
    msgs = gcs.run(12.0)
    requests = [m for m in msgs if m.get_type() == "MISSION_REQUEST_INT"]
    assert [m.seq for m in requests] == [0] * 6  # first request + 5 retries
    acks = [m.type for m in msgs if m.get_type() == "MISSION_ACK"]
    assert acks == [mavlink.MAV_MISSION_OPERATION_CANCELLED]


def test_that_mission_clear_all_leaves_only_home():
    gcs = Gcs()
    gcs.upload(survey_mission())
    gcs.send(gcs.mav.mission_clear_all_encode(1, 1))
    assert gcs.expect("MISSION_ACK").type == mavlink.MAV_MISSION_ACCEPTED
    home = gcs.download()
    assert len(home) == 1 and (home[0].x, home[0].y) == (534668000, -22339000)
    assert gcs.vehicle.loaded == []
    assert count(gcs.run(1.5), "MISSION_CURRENT") == 0


def test_that_the_mission_cannot_be_replaced_while_flying_it():
    gcs = Gcs()
    gcs.upload(survey_mission())
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    gcs.command(mavlink.MAV_CMD_MISSION_START)
    gcs.run(1.0)
    assert gcs.upload(survey_mission()[:3]) == mavlink.MAV_MISSION_DENIED
    assert len(gcs.download()) == len(survey_mission())


def test_that_do_change_speed_sets_the_speed_when_the_vehicle_gets_to_it():
    gcs = Gcs()
    mission = survey_mission()
    change = item_int(2, mavlink.MAV_CMD_DO_CHANGE_SPEED, frame=mavlink.MAV_FRAME_MISSION, p1=1, p2=3.0, z=0.0)
    items = [*mission[:2], change, *[item_int(m.seq + 1, m.command, m.frame, m.x, m.y, m.z) for m in mission[2:]]]
    assert gcs.upload(items) == mavlink.MAV_MISSION_ACCEPTED
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    gcs.command(mavlink.MAV_CMD_MISSION_START)
    gcs.run(0.5)
    assert gcs.vehicle.params["PS_SPEED_MS"] == 2.0  # still taking off
    msgs = gcs.run(4.0)
    assert gcs.vehicle.params["PS_SPEED_MS"] == 3.0
    assert [m.seq for m in msgs if m.get_type() == "MISSION_ITEM_REACHED"][:2] == [1, 2]


def test_that_fence_and_rally_lists_are_empty_and_empty_uploads_of_them_are_accepted():
    gcs = Gcs()
    gcs.send(gcs.mav.mission_request_list_encode(1, 1, mavlink.MAV_MISSION_TYPE_FENCE))
    assert gcs.expect("MISSION_COUNT").count == 0
    gcs.send(gcs.mav.mission_count_encode(1, 1, 0, mavlink.MAV_MISSION_TYPE_RALLY))
    assert gcs.expect("MISSION_ACK").type == mavlink.MAV_MISSION_ACCEPTED
    gcs.send(gcs.mav.mission_count_encode(1, 1, 2, mavlink.MAV_MISSION_TYPE_FENCE))
    assert gcs.expect("MISSION_ACK").type == mavlink.MAV_MISSION_UNSUPPORTED


# ----- robustness, logging ------------------------------------------------------------------------

def test_that_garbage_and_bit_flipped_frames_never_raise_and_valid_frames_after_them_are_handled():
    gcs = Gcs()
    rng = random.Random(7)
    valid = gcs.mav.param_request_read_encode(1, 1, b"PS_ALT_M", -1).pack(gcs.mav)
    for trial in range(200):
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 400)))
        flipped = bytearray(valid)
        bit = rng.randrange(len(flipped) * 8)
        flipped[bit // 8] ^= 1 << (bit % 8)
        gcs.end.send(junk + bytes(flipped) + bytes([0xFD, 0xFF]))  # ends in a frame header claiming 255 bytes
        if trial % 20 == 0:
            gcs.tick()
    before = gcs.server.stats["rx_by_type"]["PARAM_REQUEST_READ"]
    gcs.end.send(valid + valid)
    gcs.send(gcs.mav.heartbeat_encode(6, 8, 0, 0, 0))
    for _ in range(20):  # enough bytes to complete (and reject) any frame the garbage began
        gcs.send(gcs.mav.heartbeat_encode(6, 8, 0, 0, 0))
    msgs = gcs.run(0.05)
    assert count(msgs, "PARAM_VALUE") >= 2
    assert gcs.server.stats["rx_by_type"]["PARAM_REQUEST_READ"] - before >= 2
    assert gcs.server.stats["rx_parse_errors"] > 0 and gcs.server.stats["rx_bad_bytes"] > 0
    assert gcs.server.stats["handler_errors"] == 0


def test_that_a_frame_with_a_corrupt_length_does_not_swallow_the_frames_after_it():
    gcs = Gcs()
    request = gcs.mav.param_request_read_encode(1, 1, b"PS_ALT_M", -1).pack(gcs.mav)
    broken = bytearray(request)
    broken[1] = 200  # payload length: the parser would wait for 200 bytes
    gcs.end.send(bytes(broken) + request + request * 8)
    assert count(gcs.run(0.0), "PARAM_VALUE") == 9


def test_that_the_tlog_holds_both_directions_with_simulated_timestamps(tmp_path):
    path = tmp_path / "flight.tlog"
    gcs = Gcs(tlog_path=path)
    gcs.run(0.5)
    gcs.send(gcs.mav.param_request_list_encode(1, 1))
    gcs.run(0.5)
    gcs.server.close()
    log = mavutil.mavlink_connection(str(path))
    seen = {}
    while (m := log.recv_match()) is not None:
        seen.setdefault((m.get_srcSystem(), m.get_type()), m._timestamp)
    log.close()
    assert (GCS_SYS, "PARAM_REQUEST_LIST") in seen
    assert (1, "HEARTBEAT") in seen and (1, "PARAM_VALUE") in seen and (1, "ATTITUDE") in seen
    assert seen[(GCS_SYS, "PARAM_REQUEST_LIST")] == pytest.approx(TLOG_EPOCH_US / 1e6 + 0.5)
    assert seen[(1, "HEARTBEAT")] == pytest.approx(TLOG_EPOCH_US / 1e6)


def test_that_two_identical_runs_write_identical_tlogs(tmp_path):
    def flight(path):
        gcs = Gcs(tlog_path=path)
        gcs.upload(survey_mission())
        gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        gcs.command(mavlink.MAV_CMD_MISSION_START)
        gcs.run(5.0)
        gcs.server.close()
        return path.read_bytes()

    first = flight(tmp_path / "a.tlog")
    assert len(first) > 10_000 and first == flight(tmp_path / "b.tlog")


def test_that_long_status_texts_are_sent_in_chunks():
    gcs = Gcs()
    gcs.send(gcs.mav.param_set_encode(1, 1, b"PS_YAW_RATE_DPS", 1e6, mavlink.MAV_PARAM_TYPE_REAL32))
    texts = [m for m in gcs.run(0.05) if m.get_type() == "STATUSTEXT"]
    assert len(texts) >= 2 and len({m.id for m in texts}) == 1 and texts[0].id != 0
    assert [m.chunk_seq for m in texts] == list(range(len(texts)))
    assert "outside" in "".join(m.text for m in texts)


# ----- transports, geodesy, pacing ----------------------------------------------------------------

def test_that_pipe_transports_carry_bytes_both_ways_in_order():
    a, b = PipeTransport.pair()
    a.send(b"one")
    a.send(b"two")
    b.send(b"back")
    assert (b.recv(), b.recv(), a.recv()) == (b"onetwo", b"", b"back")


@pytest.mark.parametrize("url", ["tcp:127.0.0.1:5760", "udp:127.0.0.1", "udp:127.0.0.1:port", "udpout:1.2.3.4:0",
                                 "serial:/dev/ttyS0:57600"])
def test_that_make_transport_refuses_what_it_cannot_open(url):
    with pytest.raises(ValueError):
        make_transport(url)


def test_that_flat_earth_conversion_round_trips_and_a_metre_is_a_metre():
    lat, lon = ned_to_global(30.0, -45.0, HOME_LAT, HOME_LON)
    assert global_to_ned(lat, lon, HOME_LAT, HOME_LON) == (pytest.approx(30.0, abs=1e-9), pytest.approx(-45.0,
                                                                                                         abs=1e-9))
    lat1, _ = ned_to_global(1.0, 0.0, HOME_LAT, HOME_LON)
    assert (lat1 - HOME_LAT) * 111_320 == pytest.approx(1.0, rel=0.01)


def test_that_run_realtime_paces_simulated_time_at_the_speedup_against_the_wall_clock():
    vehicle = fast_vehicle()
    a, _ = PipeTransport.pair()
    server = MavlinkVehicleServer(vehicle, a)
    wall = [100.0]
    slept = []

    def sleep(dt):
        slept.append(dt)
        wall[0] += dt

    ran = run_realtime(server, vehicle, speedup=4.0, duration_s=2.0, clock=lambda: wall[0], sleep=sleep)
    assert ran == pytest.approx(2.0) and vehicle.state().t_s == pytest.approx(2.0)
    assert wall[0] - 100.0 == pytest.approx(0.5)  # 2 s simulated at 4x
    assert len(slept) == 200


def test_that_run_realtime_stops_when_asked():
    vehicle = fast_vehicle()
    server = MavlinkVehicleServer(vehicle, PipeTransport())
    stop = threading.Event()
    stop.set()
    assert run_realtime(server, vehicle, stop_event=stop) == 0.0
    with pytest.raises(ValueError):
        run_realtime(server, vehicle, speedup=0.0)


# ----- over real UDP ------------------------------------------------------------------------------

def test_that_a_mavutil_client_flies_a_mission_over_udp():
    vehicle = fast_vehicle()
    transport = UdpTransport("udp:127.0.0.1:0")
    server = MavlinkVehicleServer(vehicle, transport)
    stop = threading.Event()
    thread = threading.Thread(target=run_realtime, args=(server, vehicle),
                              kwargs={"speedup": 20.0, "duration_s": 600.0, "stop_event": stop}, daemon=True)
    thread.start()
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{transport.local_address[1]}", source_system=GCS_SYS,
                                      source_component=GCS_COMP)
    deadline = time.monotonic() + 15.0

    def wait(mtype, cond=lambda m: True):
        while time.monotonic() < deadline:
            m = conn.recv_match(type=mtype, blocking=True, timeout=0.5)
            if m is not None and cond(m):
                return m
        raise AssertionError(f"no {mtype} over UDP")

    try:
        conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        hb = wait("HEARTBEAT")
        assert (hb.type, hb.autopilot) == (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
        assert conn.flightmode == "STABILIZE"  # mavutil maps the ArduCopter mode number itself
        mission = survey_mission()
        conn.mav.mission_count_send(1, 1, len(mission))
        while True:
            m = wait(["MISSION_REQUEST_INT", "MISSION_ACK"])
            if m.get_type() == "MISSION_ACK":
                assert m.type == mavlink.MAV_MISSION_ACCEPTED
                break
            conn.mav.send(mission[m.seq])
        conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert wait("COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
        conn.mav.set_mode_send(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, FlightMode.AUTO)
        assert wait("COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
        reached = [wait("MISSION_ITEM_REACHED").seq for _ in range(6)]
        assert reached == [1, 2, 3, 4, 5, 6]
        wait("HEARTBEAT")
        assert conn.flightmode == "AUTO"
    finally:
        stop.set()
        thread.join(timeout=5.0)
        conn.close()
        transport.close()
    assert not thread.is_alive()
