"""The storage frame on Earth: metres of the building are metres of the ellipsoid, and UTM only where it is defined."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_py.core.site import Site
from ground.exports.georef import Georef


@pytest.mark.parametrize("lat_deg", [0.5, 45.0, 70.0, -60.0])
@pytest.mark.parametrize("heading_deg", [0.0, 90.0])
def test_that_a_hundred_metres_of_building_are_a_hundred_metres_of_the_earth(lat_deg, heading_deg):
    """On a UTM zone's central meridian the grid's scale is k0 = 0.9996 in every direction. The autopilot's sphere,
    used here before, gave 99.291 m north to south at 0.5 deg and 100.257 m east to west at 70 deg."""
    site = Site.of(lat_deg, 3.0, 50.0, heading_deg)  # 3 deg E: zone 31's central meridian
    east, north, _ = Georef(site).w_to_utm(np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0]]))
    assert math.hypot(east[1] - east[0], north[1] - north[0]) == pytest.approx(99.96, abs=0.002)
    assert math.hypot(east[2] - east[0], north[2] - north[0]) == pytest.approx(99.96, abs=0.002)


@pytest.mark.parametrize("lat_deg", [84.1, 89.9999, -80.1])
def test_that_a_site_beyond_the_utm_zones_is_not_georeferenced_and_says_why(lat_deg):
    """At 89.9999 N a building reached past the pole: PROJ refused its latitudes and the report wrote no file."""
    header = {"site": Site.of(lat_deg, 10.0, 50.0, 0.0).to_dict(), "storage_frame": {"heading_rad": 0.0}}
    georef, why = Georef.from_header(header)
    assert georef is None and "outside UTM's 80 S to 84 N" in why
    assert Georef.from_header({**header, "site": Site.of(83.9, 10.0, 50.0, 0.0).to_dict()})[0] is not None
