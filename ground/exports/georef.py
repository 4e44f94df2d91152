"""The storage frame W on Earth, for the georeferenced exports: W -> WGS-84 longitude/latitude -> UTM.

W is tied to the globe by the log header's ``site`` (`firmware_py.core.site`): the corner W's origin sits on
and the heading of W's x axis. A point of W goes to the corner's local north/east by the storage frame's
rotation about the corner, then to latitude/longitude on the WGS-84 ellipsoid's tangent plane at the corner
(`firmware_py.core.geodesy.ned_to_wgs84`, true to millimetres over a building; not the autopilot's sphere, which
MAVLink's conversions share but which is up to 0.7 % off the real Earth), then to UTM by PROJ (through
rasterio), which accounts for the grid convergence: at the default site the UTM grid is turned 0.6 deg from
true north, 0.6 m over a 60 m building, so the raster's affine transform cannot simply be the heading. Heights
become altitudes above mean sea level: the site's corner altitude (m MSL, as the user gave it) plus z.

The projected CRS is the WGS 84 / UTM zone of the site's corner (standard 6-degree zones; the Norway and
Svalbard exceptions are ignored, which only picks the neighbouring zone, still a valid projection), compound
with EPSG:5714 "MSL height" for z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.geodesy import radii_of_curvature_m
from firmware_py.core.site import Site

HEADING_AGREEMENT_DEG = 0.01
"""The site's heading and the storage frame's (both in the log header) must agree to this: the points were
placed with the frame's, the globe is reached with the site's; beyond it the header contradicts itself."""
UTM_LAT_RANGE_DEG = (-80.0, 84.0)
"""Where the UTM zones are defined (EPSG's areas of use for WGS 84 / UTM): beyond them a building may reach past a
pole, and PROJ refused the latitudes (a report with no files at all)."""
MSL_HEIGHT_EPSG = 5714
"""EPSG's vertical CRS "MSL height": what the site's altitude is given in."""


@dataclass(frozen=True)
class Georef:
    """W on Earth (module docstring)."""

    site: Site

    @classmethod
    def from_header(cls, header: dict) -> tuple[Georef | None, str | None]:
        """The header's site as a Georef, or None and why not (no site: None, None; a malformed or
        contradicting one: None and a one-line reason for the report's warnings)."""
        raw = header.get("site")
        if raw is None:
            return None, None
        try:
            site = Site.from_dict(raw)
        except ValueError as exc:
            return None, f"log header site is malformed ({exc}): exports not georeferenced"
        if not UTM_LAT_RANGE_DEG[0] <= site.corner.lat_deg <= UTM_LAT_RANGE_DEG[1]:
            lo, hi = UTM_LAT_RANGE_DEG
            return None, (f"the site's latitude {site.corner.lat_deg:g} deg is outside UTM's {-lo:g} S to {hi:g} N "
                          "(the poles take polar stereographic grids, not written here): exports not georeferenced")
        frame = header.get("storage_frame") or {}
        heading = frame.get("heading_rad") if isinstance(frame, dict) else None
        if isinstance(heading, int | float) and not isinstance(heading, bool):
            diff = (math.degrees(heading) - site.heading_deg + 180.0) % 360.0 - 180.0
            if abs(diff) > HEADING_AGREEMENT_DEG:
                return None, (f"log header site heading {site.heading_deg:g} deg differs from its storage frame's "
                              f"{math.degrees(heading):g} deg: exports not georeferenced")
        return cls(site), None

    @property
    def utm_zone(self) -> int:
        return int((self.site.corner.lon_deg + 180.0) // 6.0) % 60 + 1

    @property
    def utm_epsg(self) -> int:
        """WGS 84 / UTM zone N (326zz) or S (327zz) of the corner."""
        return (32600 if self.site.corner.lat_deg >= 0 else 32700) + self.utm_zone

    @property
    def crs_text(self) -> str:
        """The compound CRS as PROJ reads it: UTM + MSL height."""
        return f"EPSG:{self.utm_epsg}+{MSL_HEIGHT_EPSG}"

    def w_to_ne(self, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """North and east metres from the corner (the storage frame about the corner: `StorageFrame.w_to_ned`)."""
        ned = self.site.frame_about().w_to_ned(np.asarray(points_w, dtype=float).reshape(-1, 3))
        return ned[:, 0], ned[:, 1]

    def w_to_lonlat_alt(self, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Longitude, latitude (deg, WGS-84) and altitude (m MSL) of points in W: `geodesy.ned_to_wgs84`,
        vectorised (tests hold the two together)."""
        p = np.asarray(points_w, dtype=float).reshape(-1, 3)
        north, east = self.w_to_ne(p)
        c = self.site.corner
        meridian, prime = radii_of_curvature_m(c.lat_deg)
        lat = c.lat_deg + np.degrees(north / meridian)
        lon = c.lon_deg + np.degrees(east / (prime * math.cos(math.radians(c.lat_deg))))
        lon = (lon + 180.0) % 360.0 - 180.0 if np.any(np.abs(lon) > 180.0) else lon
        return lon, lat, c.alt_m + p[:, 2]

    def w_to_utm(self, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Easting, northing (m, this UTM zone) and altitude (m MSL) of points in W (PROJ, via rasterio)."""
        from rasterio.warp import transform

        lon, lat, alt = self.w_to_lonlat_alt(points_w)
        if len(lon) == 0:
            return np.empty(0), np.empty(0), np.empty(0)
        east, north = transform("EPSG:4326", f"EPSG:{self.utm_epsg}", lon, lat)
        return np.asarray(east, dtype=float), np.asarray(north, dtype=float), alt
