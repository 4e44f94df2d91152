"""Flat-earth geodesy about a home position: how mission items and GLOBAL_POSITION_INT meet local NED.

`global_to_ned` / `ned_to_global` are ArduPilot's own convention (a sphere of the equatorial radius: its
LOCATION_SCALING_FACTOR), which is what both ends of a MAVLink link use to turn a mission item or a global position
into local NED and back, so a plan round-trips exactly. On the real Earth that sphere is off by up to 0.7 % (north
to south at the equator): 100 m of building is 99.3 m of it. Where a point's true place on the globe matters (the
georeferenced exports), `ned_to_wgs84` uses the WGS-84 ellipsoid's radii of curvature at the home: the tangent plane
there, true to millimetres over a building.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_py.core.numbers import is_finite_number

EARTH_RADIUS_M = 6_378_137.0


def global_to_ned(lat_deg: float, lon_deg: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """North/east metres of a lat/lon from home, flat-earth (fine over a building, not over kilometres)."""
    north = math.radians(lat_deg - home_lat_deg) * EARTH_RADIUS_M
    east = math.radians(wrap_deg(lon_deg - home_lon_deg)) * EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))
    return north, east


def ned_to_global(north_m: float, east_m: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """Inverse of global_to_ned: lat/lon (deg) of a local north/east point."""
    lat = home_lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon = home_lon_deg + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))))
    return lat, wrap_deg(lon)


WGS84_A_M = 6_378_137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def radii_of_curvature_m(lat_deg: float) -> tuple[float, float]:
    """The WGS-84 ellipsoid's meridian and prime-vertical radii of curvature (m) at a latitude: a metre north is
    1 / meridian radians of latitude, a metre east 1 / (prime vertical x cos(latitude)) radians of longitude."""
    s2 = math.sin(math.radians(lat_deg)) ** 2
    w = math.sqrt(1.0 - WGS84_E2 * s2)
    return WGS84_A_M * (1.0 - WGS84_E2) / w**3, WGS84_A_M / w


def ned_to_wgs84(north_m: float, east_m: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """WGS-84 lat/lon (deg) of a local north/east point, on the ellipsoid's tangent plane at home (module
    docstring: where the truth matters; a MAVLink link uses `ned_to_global`)."""
    meridian, prime = radii_of_curvature_m(home_lat_deg)
    lat = home_lat_deg + math.degrees(north_m / meridian)
    lon = home_lon_deg + math.degrees(east_m / (prime * math.cos(math.radians(home_lat_deg))))
    return lat, wrap_deg(lon)


def wrap_deg(angle_deg: float) -> float:
    """An angle within [-180, 180] deg: a building across the antimeridian stays one building.
    Left untouched when already within (no rounding where nothing wraps)."""
    if -180.0 <= angle_deg <= 180.0:
        return angle_deg
    return (angle_deg + 180.0) % 360.0 - 180.0


ALT_MIN_M, ALT_MAX_M = -1000.0, 10_000.0
"""Altitudes (m above mean sea level) a building on Earth can have: below the Dead Sea shore (-430 m),
above any summit (8,849 m), with margin; outside them a value is a typo (feet? a sign?)."""


@dataclass(frozen=True)
class GeodeticPoint:
    """A point on Earth: latitude, longitude (deg, WGS-84) and altitude above mean sea level (m).

    As the origin of a local NED frame (an autopilot's home / EKF origin) it converts both ways; global
    altitude is above alt_m, relative altitude above it.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float

    def __post_init__(self) -> None:
        for name, v in (("latitude", self.lat_deg), ("longitude", self.lon_deg), ("altitude", self.alt_m)):
            if not is_finite_number(v):
                raise ValueError(f"{name} must be a finite number, got {v!r}")
        if not -90.0 < self.lat_deg < 90.0:
            raise ValueError(f"latitude must be between -90 and 90 deg (a pole has no east), got {self.lat_deg:g}")
        if not -180.0 <= self.lon_deg <= 180.0:
            raise ValueError(f"longitude must be within -180..180 deg, got {self.lon_deg:g}")
        if not ALT_MIN_M <= self.alt_m <= ALT_MAX_M:
            raise ValueError(f"altitude must be {ALT_MIN_M:g}..{ALT_MAX_M:g} m above mean sea level, "
                             f"got {self.alt_m:g}")

    def as_tuple(self) -> tuple[float, float, float]:
        return (float(self.lat_deg), float(self.lon_deg), float(self.alt_m))

    def to_ned(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        """North/east metres of a lat/lon from this point."""
        return global_to_ned(lat_deg, lon_deg, self.lat_deg, self.lon_deg)

    def to_global(self, north_m: float, east_m: float) -> tuple[float, float]:
        """Lat/lon of a point north/east metres from this one."""
        return ned_to_global(north_m, east_m, self.lat_deg, self.lon_deg)

    def ned_from(self, origin: GeodeticPoint) -> tuple[float, float, float]:
        """This point in the local NED frame about origin (down: the altitude difference)."""
        n, e = origin.to_ned(self.lat_deg, self.lon_deg)
        return (n, e, float(origin.alt_m - self.alt_m))


Home = GeodeticPoint
"""The autopilot's home: the origin of local NED (the SITL's autopilot uses its EKF origin as home)."""
