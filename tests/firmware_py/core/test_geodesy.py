"""Flat-earth geodesy about home."""

import math

import pytest

from firmware_py.core.geodesy import Home, global_to_ned, ned_to_global

HOME_LAT, HOME_LON, HOME_ALT = 53.4668, -2.2339, 50.0


def test_that_flat_earth_conversion_round_trips_and_a_metre_is_a_metre():
    lat, lon = ned_to_global(30.0, -45.0, HOME_LAT, HOME_LON)
    assert global_to_ned(lat, lon, HOME_LAT, HOME_LON) == (pytest.approx(30.0, abs=1e-9), pytest.approx(-45.0,
                                                                                                         abs=1e-9))
    lat1, _ = ned_to_global(1.0, 0.0, HOME_LAT, HOME_LON)
    assert (lat1 - HOME_LAT) * 111_320 == pytest.approx(1.0, rel=0.01)


def test_that_home_converts_both_ways_about_itself():
    home = Home(HOME_LAT, HOME_LON, HOME_ALT)
    assert home.to_ned(*home.to_global(12.0, -3.0)) == (pytest.approx(12.0, abs=1e-9), pytest.approx(-3.0, abs=1e-9))
    assert home.to_global(0.0, 0.0) == (HOME_LAT, HOME_LON)


@pytest.mark.parametrize(("lat", "lon", "alt"), [(90.0, 0.0, 0.0), (math.nan, 0.0, 0.0), (0.0, 181.0, 0.0),
                                                 (0.0, 0.0, math.inf)])
def test_that_a_home_off_the_earth_is_refused(lat, lon, alt):
    with pytest.raises(ValueError, match=r"latitude|longitude|altitude"):
        Home(lat, lon, alt)
