"""Telemetry streams: default rates, SET/GET_MESSAGE_INTERVAL, REQUEST_MESSAGE (lockstep, simulated time)."""

import math
import os

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.geodesy import global_to_ned
from sitl.mavlink.streams import TLOG_EPOCH_US
from sitl.vehicle.api import FlightMode
from tests.sitl.mavlink.lockstep_gcs import (
    HOME_LAT,
    HOME_LON,
    Gcs,
    RecordingVehicle,
    count,
)


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
