"""Flat-earth geodesy about a home position: how mission items and GLOBAL_POSITION_INT meet local NED.

Exact to millimetres over a building, wrong over kilometres: a stockpile survey never leaves the
building, and a flat earth keeps the conversion exactly invertible (a plan round-trips).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

EARTH_RADIUS_M = 6_378_137.0


def global_to_ned(lat_deg: float, lon_deg: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """North/east metres of a lat/lon from home, flat-earth (fine over a building, not over kilometres)."""
    north = math.radians(lat_deg - home_lat_deg) * EARTH_RADIUS_M
    east = math.radians(lon_deg - home_lon_deg) * EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))
    return north, east


def ned_to_global(north_m: float, east_m: float, home_lat_deg: float, home_lon_deg: float) -> tuple[float, float]:
    """Inverse of global_to_ned: lat/lon (deg) of a local north/east point."""
    lat = home_lat_deg + math.degrees(north_m / EARTH_RADIUS_M)
    lon = home_lon_deg + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(home_lat_deg))))
    return lat, lon


@dataclass(frozen=True)
class Home:
    """The autopilot's home: the origin of local NED (global altitude is above alt_m, relative above home)."""

    lat_deg: float
    lon_deg: float
    alt_m: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lat_deg) and abs(self.lat_deg) < 90 and math.isfinite(self.lon_deg)
                and abs(self.lon_deg) <= 180 and math.isfinite(self.alt_m)):
            raise ValueError(f"bad home position {self.lat_deg}, {self.lon_deg}, {self.alt_m}")

    def to_ned(self, lat_deg: float, lon_deg: float) -> tuple[float, float]:
        return global_to_ned(lat_deg, lon_deg, self.lat_deg, self.lon_deg)

    def to_global(self, north_m: float, east_m: float) -> tuple[float, float]:
        return ned_to_global(north_m, east_m, self.lat_deg, self.lon_deg)
