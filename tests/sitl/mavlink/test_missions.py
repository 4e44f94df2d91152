"""The mission micro-service: upload, download, clear, and the vehicle flying the plan."""

import math
import os

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.geodesy import ned_to_global
from sitl.vehicle.api import FlightMode, NavKind
from tests.sitl.mavlink.lockstep_gcs import (
    HOME_ALT,
    HOME_LAT,
    HOME_LON,
    RECTANGLE,
    Gcs,
    count,
    fields,
    item_int,
    latlon_e7,
    survey_mission,
)


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



def test_that_on_a_wall_clock_link_an_upload_waits_for_the_ground_station_in_wall_clock_seconds():
    gcs = Gcs()
    wall = [0.0]
    gcs.server.time_link_by(lambda: wall[0])
    gcs.send(gcs.mav.mission_count_encode(1, 1, 3))
    msgs = gcs.run(30.0)  # at a high speed-up: much simulated time, no time at all for the ground station
    assert [m.seq for m in msgs if m.get_type() == "MISSION_REQUEST_INT"] == [0]
    wall[0] += 1.6
    msgs = gcs.run(0.1)
    assert [m.seq for m in msgs if m.get_type() == "MISSION_REQUEST_INT"] == [0]  # asked again, not cancelled
    assert count(msgs, "MISSION_ACK") == 0
    gcs.send(survey_mission()[0])
    assert gcs.expect("MISSION_REQUEST_INT").seq == 1

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
