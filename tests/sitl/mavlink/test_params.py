"""The parameter micro-service: list, read, set."""

import math
import os

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tests.sitl.mavlink.lockstep_gcs import (
    ALT_M,
    Gcs,
    survey_mission,
)


def test_that_param_request_list_sends_every_parameter_as_real32_with_count_and_index():
    gcs = Gcs()
    gcs.send(gcs.mav.param_request_list_encode(1, 1))
    values = [m for m in gcs.run(0.1) if m.get_type() == "PARAM_VALUE"]
    assert {m.param_id: m.param_value for m in values} == pytest.approx(gcs.vehicle.params)
    n = len(gcs.vehicle.params)
    assert sorted(m.param_index for m in values) == list(range(n))
    assert {m.param_count for m in values} == {n} and {m.param_type for m in values} == {9}


def test_that_the_ekf_source_parameters_read_as_ardupilot_s_and_refuse_a_set():
    gcs = Gcs()
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"EK3_SRC1_POSZ", -1))
    assert (m := gcs.expect("PARAM_VALUE")).param_id == "EK3_SRC1_POSZ" and m.param_value == 1.0  # barometer
    gcs.send(gcs.mav.param_set_encode(1, 1, b"EK3_SRC1_POSZ", 2.0, mavlink.MAV_PARAM_TYPE_REAL32))
    msgs = gcs.run(0.1)
    assert "read-only" in "".join(m.text for m in msgs if m.get_type() == "STATUSTEXT")  # chunked: 50 a message
    assert [m.param_value for m in msgs if m.get_type() == "PARAM_VALUE"] == [1.0]  # the value kept, read back


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
