"""The served autopilot's EKF origin is its home, the site's corner: GPS_GLOBAL_ORIGIN, HOME_POSITION and
GLOBAL_POSITION_INT all about it, and a SET_GPS_GLOBAL_ORIGIN naming another point refused and said."""

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.site import DEFAULT_SITE
from tests.sitl.mavlink.lockstep_gcs import Gcs

SYDNEY = GeodeticPoint(-33.9, 151.2, 30.0)
SYDNEY_E7 = (-339_000_000, 1_512_000_000, 30_000)


def test_that_a_matching_origin_is_confirmed_and_nothing_is_said():
    gcs = Gcs(home=SYDNEY)
    gcs.send(gcs.mav.set_gps_global_origin_encode(1, *SYDNEY_E7))
    m = gcs.expect("GPS_GLOBAL_ORIGIN")
    assert (m.latitude, m.longitude, m.altitude) == SYDNEY_E7
    assert not [t for t in gcs.run(0.5) if t.get_type() == "STATUSTEXT"]
    assert gcs.server.stats["origin_refused"] == 0


def test_that_another_origin_is_refused_said_and_the_one_in_force_given_back():
    gcs = Gcs(home=SYDNEY)
    gcs.send(gcs.mav.set_gps_global_origin_encode(1, 534_668_000, -22_339_000, 50_000))  # the default site's
    text = gcs.expect("STATUSTEXT")
    assert text.severity == mavlink.MAV_SEVERITY_WARNING and "refused" in text.text and "origin" in text.text
    m = gcs.expect("GPS_GLOBAL_ORIGIN")
    assert (m.latitude, m.longitude, m.altitude) == SYDNEY_E7
    assert gcs.server.stats["origin_refused"] == 1


def test_that_the_origin_can_be_requested_and_home_is_the_same_point():
    gcs = Gcs(home=SYDNEY)
    assert gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN) == \
        mavlink.MAV_RESULT_ACCEPTED
    m = gcs.expect("GPS_GLOBAL_ORIGIN")
    assert (m.latitude, m.longitude, m.altitude) == SYDNEY_E7
    assert gcs.command(mavlink.MAV_CMD_GET_HOME_POSITION) == mavlink.MAV_RESULT_ACCEPTED
    h = gcs.expect("HOME_POSITION")
    assert (h.latitude, h.longitude, h.altitude) == SYDNEY_E7


def test_that_global_position_is_the_local_position_about_the_origin():
    gcs = Gcs(home=SYDNEY)
    gcs.run(1.0)
    g = gcs.expect("GLOBAL_POSITION_INT")
    n, e, d = gcs.vehicle.state().pos_ned_m
    gn, ge = SYDNEY.to_ned(g.lat / 1e7, g.lon / 1e7)
    assert math.hypot(gn - n, ge - e) < 0.1  # within a stream period's travel (the vehicle is still here)
    assert g.alt / 1e3 == pytest.approx(SYDNEY.alt_m - d, abs=0.1)


def test_that_the_default_home_is_the_default_sites_corner():
    assert Gcs().server.home == DEFAULT_SITE.corner
    with pytest.raises(ValueError, match="GeodeticPoint"):
        Gcs(home=(1.0, 2.0, 3.0))
