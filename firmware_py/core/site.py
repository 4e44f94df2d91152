"""Where the building stands on Earth: the storage frame's floor corner and the heading of its x axis.

A survey is planned, flown and measured in three frames that must agree: the building's own W
(`firmware_py.core.frames`), the autopilot's local NED about its EKF origin, and the global
latitude / longitude / altitude of a mission plan and of GLOBAL_POSITION_INT. A `Site` ties W to the
globe: the corner W's origin sits on (deg, deg, m above mean sea level) and the heading of W's x axis
(the building's length) clockwise from true north. Given the EKF origin, it gives the `StorageFrame`
the payload and the ground station use (`Site.frame_about`): the corner's offset from that origin in
NED, by the same flat-earth mapping the plans and the autopilot use (`firmware_py.core.geodesy`), and
the heading. When the EKF origin is the corner (what `pilescan-payload --origin` sends by default)
the frame's origin is (0, 0, 0).

Degrees at the user's end (options, files), radians inside.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any

from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.numbers import is_finite_number

HEADING_LIMIT_DEG = 360.0
"""A heading is accepted within +-360 deg (so -90 and 270 both work); beyond that it is a typo."""


@dataclass(frozen=True)
class Site:
    """The building on Earth (module docstring).

    Attributes:
        corner: W's origin, the floor corner its x (length) and y (width) axes leave from.
        heading_rad: heading of W's x axis, clockwise from true north (W's y axis is 90 deg to its left).
    """

    corner: GeodeticPoint
    heading_rad: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.corner, GeodeticPoint):
            raise ValueError(f"site corner must be a GeodeticPoint, got {self.corner!r}")
        h = self.heading_rad
        if not is_finite_number(h) \
                or abs(h) > math.radians(HEADING_LIMIT_DEG):
            raise ValueError(f"heading must be a finite angle within +-{HEADING_LIMIT_DEG:g} deg, got {h!r} rad")

    @classmethod
    def of(cls, lat_deg: float, lon_deg: float, alt_m: float, heading_deg: float = 0.0) -> Site:
        """A site from the user's units (degrees)."""
        check_heading_deg(heading_deg)
        return cls(GeodeticPoint(lat_deg, lon_deg, alt_m), math.radians(heading_deg))

    @property
    def heading_deg(self) -> float:
        return math.degrees(self.heading_rad)

    def frame_about(self, ekf_origin: GeodeticPoint | None = None) -> StorageFrame:
        """The storage frame in the local NED frame of an autopilot whose EKF origin is ekf_origin
        (None: the corner itself, so the frame's origin is (0, 0, 0))."""
        origin_ned = (0.0, 0.0, 0.0) if ekf_origin is None or ekf_origin == self.corner \
            else self.corner.ned_from(ekf_origin)
        return StorageFrame(origin_ned_m=origin_ned, heading_rad=float(self.heading_rad))

    def describe(self) -> str:
        """One line for people: the corner and the heading, in degrees."""
        c = self.corner
        return (f"corner {c.lat_deg:.7f}, {c.lon_deg:.7f}, {c.alt_m:g} m MSL; "
                f"x axis heading {self.heading_deg:g} deg from north")

    def to_dict(self) -> dict[str, float]:
        """The "site" record of log headers and truth.json (degrees, as a person would read them)."""
        c = self.corner
        return {"lat_deg": float(c.lat_deg), "lon_deg": float(c.lon_deg), "alt_m": float(c.alt_m),
                "heading_deg": round(self.heading_deg, 9)}  # 30, not 29.999999999999996: a nano-degree is nothing

    @classmethod
    def from_dict(cls, d: Any) -> Site:
        """Parse a "site" record; ValueError naming the missing or bad key."""
        if not isinstance(d, dict):
            raise ValueError(f"site must be a JSON object, got {type(d).__name__}")
        vals = []
        for key in ("lat_deg", "lon_deg", "alt_m", "heading_deg"):
            if key not in d:
                raise ValueError(f"site lacks {key!r}")
            v = d[key]
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f"site {key} must be a number, got {v!r}")
            vals.append(float(v))
        return cls.of(*vals)


SAME_SITE_TOLERANCE_M = 0.01
"""Two records place the same building when their corners agree to 1 cm (a tape's, what the files write)..."""
SAME_SITE_HEADING_DEG = 0.01
"""... and their x axes to 0.01 deg."""


def site_difference(a: Site, b: Site) -> str | None:
    """Why two sites are not the same building's place (corners or x axes apart), or None: the one test the
    ground station's merge and the gap planner both apply."""
    off = math.hypot(*a.corner.ned_from(b.corner))
    turn = (a.heading_deg - b.heading_deg + 180.0) % 360.0 - 180.0
    if off > SAME_SITE_TOLERANCE_M:
        return f"the buildings' corners are {off:.2f} m apart"
    if abs(turn) > SAME_SITE_HEADING_DEG:
        return f"the buildings' x axes are {abs(turn):g} deg apart"
    return None


def check_heading_deg(heading_deg: float) -> float:
    """The heading, if finite and within +-HEADING_LIMIT_DEG; ValueError otherwise."""
    if not is_finite_number(heading_deg):
        raise ValueError(f"heading must be a finite number of degrees, got {heading_deg!r}")
    if abs(heading_deg) > HEADING_LIMIT_DEG:
        raise ValueError(f"heading must be within +-{HEADING_LIMIT_DEG:g} deg, got {heading_deg:g}")
    return float(heading_deg)


def parse_origin(text: str) -> GeodeticPoint:
    """'LAT,LON,ALT' (deg, deg, m MSL) -> GeodeticPoint; ValueError saying what is wrong."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 3:
        raise ValueError(f"expected LAT,LON,ALT (three numbers separated by commas), got {text!r}")
    vals = []
    for name, p in zip(("latitude", "longitude", "altitude"), parts, strict=True):
        try:
            vals.append(float(p))
        except ValueError:
            raise ValueError(f"{name} is not a number: {p!r}") from None
    return GeodeticPoint(*vals)


def parse_heading_deg(text: str) -> float:
    """A heading in degrees from text; ValueError saying what is wrong."""
    try:
        v = float(text)
    except ValueError:
        raise ValueError(f"not a number: {text!r}") from None
    return check_heading_deg(v)


DEFAULT_SITE = Site.of(53.4668, -2.2339, 50.0, 0.0)
"""The SITL's site when none is given: the one every simulated flight used before sites existed."""


def origin_arg(text: str) -> GeodeticPoint:
    """argparse type of --origin (its message, in one line)."""
    try:
        return parse_origin(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def heading_arg(text: str) -> float:
    """argparse type of --heading (its message, in one line)."""
    try:
        return parse_heading_deg(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_site_options(parser: argparse.ArgumentParser | Any, *, default: Site | None) -> None:
    """--origin LAT,LON,ALT and --heading DEG on a program's parser (or an argument group); both default
    to None, and `site_from_args` fills in `default` for what was not given."""
    where = (f"default {default.corner.lat_deg:g},{default.corner.lon_deg:g},{default.corner.alt_m:g}"
             if default is not None else "default: none")
    parser.add_argument("--origin", type=origin_arg, default=None, metavar="LAT,LON,ALT",
                        help="the storage frame's floor corner on Earth: latitude, longitude (deg) and altitude "
                             f"(m above mean sea level) ({where})")
    heading = default.heading_deg if default is not None else 0.0
    parser.add_argument("--heading", type=heading_arg, default=None, metavar="DEG",
                        help="heading of the building's x axis (its length) from true north, clockwise, deg, "
                             f"within +-{HEADING_LIMIT_DEG:g} (default {heading:g})")


def site_from_args(origin: GeodeticPoint | None, heading_deg: float | None, default: Site) -> Site:
    """The site --origin / --heading give, each falling back to default's."""
    corner = origin if origin is not None else default.corner
    heading = heading_deg if heading_deg is not None else default.heading_deg
    return Site(corner, math.radians(heading))
