"""The site: the storage frame's corner on Earth and its heading, and the frame it gives about an EKF origin."""

import math

import numpy as np
import pytest

from firmware_py.core.geodesy import GeodeticPoint, global_to_ned, ned_to_global
from firmware_py.core.site import DEFAULT_SITE, Site, parse_heading_deg, parse_origin

SYDNEY = Site.of(-33.9, 151.2, 30.0, 30.0)


def test_that_the_frame_about_the_sites_own_corner_has_its_origin_there_and_the_sites_heading():
    frame = SYDNEY.frame_about(SYDNEY.corner)
    assert frame.origin_ned_m == (0.0, 0.0, 0.0)
    assert frame.heading_rad == pytest.approx(math.radians(30.0))
    assert SYDNEY.frame_about() == frame


def test_that_the_default_site_is_the_one_every_earlier_flight_used():
    assert DEFAULT_SITE.corner.as_tuple() == (53.4668, -2.2339, 50.0)
    assert DEFAULT_SITE.frame_about() == DEFAULT_SITE.frame_about(DEFAULT_SITE.corner)
    assert DEFAULT_SITE.frame_about().heading_rad == 0.0


def test_that_a_point_of_the_building_has_the_same_latitude_whichever_ekf_origin_is_used():
    """W -> NED about an EKF origin -> global must not depend on the origin (to flat-earth accuracy)."""
    ekf = GeodeticPoint(-33.9003, 151.2004, 29.2)  # ~33 m south, ~37 m east, 0.8 m lower than the corner
    p_w = np.array([40.0, 25.0, 3.0])
    globals_ = []
    for origin in (SYDNEY.corner, ekf):
        n, e, d = SYDNEY.frame_about(origin).w_to_ned(p_w)
        lat, lon = ned_to_global(n, e, origin.lat_deg, origin.lon_deg)
        globals_.append((lat, lon, origin.alt_m - d))
    (lat0, lon0, alt0), (lat1, lon1, alt1) = globals_
    n_err, e_err = global_to_ned(lat1, lon1, lat0, lon0)
    assert math.hypot(n_err, e_err) < 1e-3 and alt1 == pytest.approx(alt0, abs=1e-9)
    assert alt0 == pytest.approx(30.0 + 3.0)


def test_that_the_corner_seen_from_another_ekf_origin_is_offset_by_the_geodetic_difference():
    ekf = GeodeticPoint(-33.9, 151.2 - math.degrees(10.0 / (6_378_137.0 * math.cos(math.radians(-33.9)))), 31.0)
    frame = SYDNEY.frame_about(ekf)
    assert frame.origin_ned_m == pytest.approx((0.0, 10.0, 1.0), abs=1e-9)  # 10 m east, 1 m below the origin


def test_that_the_site_record_round_trips_in_degrees():
    d = SYDNEY.to_dict()
    assert d == {"lat_deg": -33.9, "lon_deg": 151.2, "alt_m": 30.0, "heading_deg": 30.0}
    assert Site.from_dict(d) == SYDNEY


@pytest.mark.parametrize(("record", "match"), [
    ([1, 2], "JSON object"), ({"lat_deg": 1.0, "lon_deg": 2.0, "alt_m": 3.0}, "heading_deg"),
    ({"lat_deg": "1", "lon_deg": 2.0, "alt_m": 3.0, "heading_deg": 0.0}, "lat_deg must be a number"),
    ({"lat_deg": 95.0, "lon_deg": 2.0, "alt_m": 3.0, "heading_deg": 0.0}, "latitude"),
    ({"lat_deg": 1.0, "lon_deg": 2.0, "alt_m": 3.0, "heading_deg": 720.0}, "heading"),
])
def test_that_a_bad_site_record_is_refused_naming_the_key(record, match):
    with pytest.raises(ValueError, match=match):
        Site.from_dict(record)


@pytest.mark.parametrize(("text", "match"), [
    ("1,2", "LAT,LON,ALT"), ("1,2,3,4", "LAT,LON,ALT"), ("", "LAT,LON,ALT"), ("x,2,3", "latitude is not a number"),
    ("1,,3", "longitude is not a number"), ("90,0,0", "latitude"), ("-90.5,0,0", "latitude"),
    ("0,180.01,0", "longitude"), ("0,-181,0", "longitude"), ("nan,0,0", "finite"), ("0,inf,0", "finite"),
    ("0,0,-inf", "finite"), ("0,0,20000", "altitude"),
])
def test_that_a_bad_origin_is_refused_saying_what_is_wrong(text, match):
    with pytest.raises(ValueError, match=match):
        parse_origin(text)


@pytest.mark.parametrize("text", ["-33.9,151.2,30", " -33.9, 151.2 , 30 ", "89.9,-180,-400"])
def test_that_a_good_origin_parses(text):
    p = parse_origin(text)
    assert p == GeodeticPoint(*(float(v) for v in text.split(",")))


@pytest.mark.parametrize(("text", "ok"), [("30", True), ("-360", True), ("360", True), ("360.5", False),
                                          ("-1e9", False), ("nan", False), ("inf", False), ("north", False)])
def test_that_a_heading_is_accepted_only_within_plus_minus_360_deg(text, ok):
    if ok:
        assert parse_heading_deg(text) == float(text)
    else:
        with pytest.raises(ValueError, match=r"heading|number"):
            parse_heading_deg(text)


def test_that_a_building_across_the_antimeridian_stays_one_building():
    corner = GeodeticPoint(-16.8, 179.9999, 5.0)
    lat, lon = ned_to_global(0.0, 50.0, corner.lat_deg, corner.lon_deg)
    assert -180.0 <= lon < -179.99  # wrapped, not 180.0004
    assert global_to_ned(lat, lon, corner.lat_deg, corner.lon_deg) == (pytest.approx(0.0, abs=1e-6),
                                                                      pytest.approx(50.0, abs=1e-6))
