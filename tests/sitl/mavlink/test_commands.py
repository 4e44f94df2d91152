"""Commands: COMMAND_LONG / COMMAND_INT / SET_MODE, acked, refused with a reason."""

import math
import os

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.vehicle.api import FlightMode
from tests.sitl.mavlink.lockstep_gcs import (
    Gcs,
    count,
    status_text,
)


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
