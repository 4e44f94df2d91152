"""How close the vehicle's true path came to the building and the pile: a flight that touches a wall, the roof or
the pile crashed.

The autopilot flies on its estimate (`sitl.sensing.pose_drift`), so an estimate a metre off puts the true
vehicle a metre off the planned path; near a wall that is a collision, which a real flight does not survive
and the physics here would not stop. `closest_approach` finds the nearest approach to the four walls and the
roof over the true trajectory; `fly` refuses to write a survey whose vehicle reached a surface
(within `f450_reach_m`) and records the approach in truth.json. The floor is left out: the vehicle takes off from
it and lands on it. Over the pile the vertical room matters: an altitude reference that drifts up (a barometer
indoors) flies the vehicle down by as much, and a mission planned low over a tall pile has little to give;
`pile_approach` finds how far the vehicle's landing gear (`f450_below_m`) and propellers (`f450_rotor_height_m`)
stayed above the pile under them, over the survey (a lockstep flight starts below the first waypoint, which may lie
inside a pile).
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from firmware_py.core.storage import Storage

INCH_M = 0.0254
UNIT_M = {"M": 1.0, "IN": INCH_M, "FT": 12 * INCH_M}
"""JSBSim's length units, in metres."""


def _jsbsim_file(*parts: str) -> ET.Element:
    """The root element of a file the `jsbsim` wheel ships (parts: its path under JSBSim's root)."""
    import jsbsim

    return ET.parse(Path(jsbsim.get_default_root_dir()).joinpath(*parts)).getroot()


def _coord_m(loc: ET.Element, axis: str) -> float:
    """One coordinate of a JSBSim <location>, in metres (its unit attribute, metres by default)."""
    return float(loc.findtext(axis)) * UNIT_M[loc.get("unit", "M").upper()]


def _f450_thrusters() -> list[ET.Element]:
    return list(_jsbsim_file("aircraft", "F450", "Propulsion.xml").iter("thruster"))


@cache
def _f450_cg_z_m() -> float:
    cg = next((loc for loc in _jsbsim_file("aircraft", "F450", "Mass.xml").iter("location")
               if loc.get("name") == "CG"), None)
    if cg is None:
        raise RuntimeError("the F450 model shipped with jsbsim declares no centre of gravity")
    return _coord_m(cg, "z")


@cache
def f450_reach_m() -> float:
    """How far JSBSim's F450 reaches from its centre: its farthest propeller hub plus that propeller's radius,
    read from the model the `jsbsim` wheel ships (0.233 m + 9.4 in / 2 = 0.353 m)."""
    reach = 0.0
    for thruster in _f450_thrusters():
        loc = thruster.find("location")
        hub = math.hypot(_coord_m(loc, "x"), _coord_m(loc, "y"))
        prop = _jsbsim_file("engine", f"{thruster.get('file')}.xml").find("diameter")
        dia = float(prop.text) * UNIT_M[prop.get("unit", "IN").upper()]
        reach = max(reach, hub + dia / 2.0)
    if not reach > 0:
        raise RuntimeError("the F450 model shipped with jsbsim declares no thruster")
    return reach


@cache
def f450_below_m() -> float:
    """How far JSBSim's F450 reaches below its centre of gravity: its lowest ground contact (the landing gear), read
    from the model the `jsbsim` wheel ships (0.152 m)."""
    contacts = [c.find("location") for c in _jsbsim_file("aircraft", "F450", "Gear.xml").iter("contact")]
    if not contacts:
        raise RuntimeError("the F450 model shipped with jsbsim declares no ground contact")
    below = max(_f450_cg_z_m() - _coord_m(loc, "z") for loc in contacts)
    if not below > 0:
        raise RuntimeError("the F450 model's ground contacts are not below its centre of gravity")
    return below


@cache
def f450_rotor_height_m() -> float:
    """How far JSBSim's F450's propellers turn above its centre of gravity (the lowest thruster, read from the model the
    `jsbsim` wheel ships: 0.025 m): out at the propellers' circle, that is the vehicle's underside."""
    heights = [_coord_m(loc, "z") - _f450_cg_z_m() for t in _f450_thrusters()
               if (loc := t.find("location")) is not None]
    if not heights:
        raise RuntimeError("the F450 model shipped with jsbsim declares no thruster")
    return min(heights)


RIM_POINTS = 8
"""Points on the propellers' circle (`f450_reach_m`) where the pile under the vehicle is looked at, beside its centre:
45 deg apart, a pile's crest narrower than the gap between two (0.27 m at the F450's reach) is missed."""


@dataclass(frozen=True)
class Approach:
    """The nearest the true vehicle centre came to a wall or the roof, or the least room the vehicle left under it over
    the pile (`pile_approach`); t_s on the trajectory's clock."""

    distance_m: float  # signed: negative beyond the surface (outside the building)
    surface: str  # "the wall x = 0" ...
    t_s: float

    def to_dict(self) -> dict:
        return {"distance_m": round(self.distance_m, 4), "surface": self.surface, "t_s": round(self.t_s, 3)}


def closest_approach(t_s: np.ndarray, true_w_m: np.ndarray, storage: Storage) -> Approach | None:
    """The nearest approach of a true trajectory (storage frame W, (N, 3) m) to the walls and the roof (None:
    no finite position)."""
    near = storage.nearest_surface(true_w_m)
    if near is None:
        return None
    i, distance, surface = near
    return Approach(distance, surface, float(np.asarray(t_s, dtype=float)[i]))


def collision(approach: Approach | None, reach_m: float) -> str | None:
    """Why the flight crashed (None: it kept clear): the vehicle reached a wall or the roof."""
    if approach is None or approach.distance_m > reach_m:
        return None
    where = (f"{-approach.distance_m:.2f} m beyond it, outside the building" if approach.distance_m < 0
             else f"{approach.distance_m:.2f} m from it")
    return (f"the vehicle hit {approach.surface} at t = {approach.t_s:.0f} s: its true centre came {where}, "
            f"and its propellers reach {reach_m:.2f} m")


def pile_approach(t_s: np.ndarray, true_w_m: np.ndarray, heights_below_m, reach_m: float, below_m: float,
                  rotor_m: float) -> Approach | None:
    """The nearest the vehicle came to the pile over a true trajectory (storage frame W, (N, 3) m): the least of its
    landing gear's height above the pile straight below its centre (below_m: how far the gear reaches below the centre)
    and its propellers' above the highest pile under their circle (RIM_POINTS on the circle of reach_m, the propellers
    turning rotor_m above the centre); negative: it went into the pile. heights_below_m: (x, y) -> the ground's height
    below (`sitl.world.raycast.World.heights_below_m`: 0 on the floor). None: no finite position, or no pile taller than
    the landing gear under the vehicle (the floor, and a pile's thin toe, are where it takes off and lands)."""
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(true_w_m, dtype=float).reshape(-1, 3)
    ok = np.isfinite(w).all(axis=1) & np.isfinite(t)
    if not ok.any():
        return None
    t, w = t[ok], w[ok]
    # a position every quarter reach along the path: the physics' hundreds of states a second cost 0.9 s a flight,
    # which the test suite paid on every one; the room is then overstated by at most the slope under the centre times
    # half that step (4 cm on a 45 deg crest, steeper than any material's angle of repose)
    step = np.concatenate([[0.0], np.linalg.norm(np.diff(w, axis=0), axis=1)])
    bins = np.floor(np.cumsum(step) / (0.25 * reach_m))
    keep = np.concatenate([[True], np.diff(bins) > 0]) if len(bins) > 1 else np.ones(len(w), dtype=bool)
    t, w = t[keep], w[keep]
    ang = np.arange(RIM_POINTS) * (2.0 * math.pi / RIM_POINTS)
    ring = np.vstack([[0.0, 0.0], reach_m * np.column_stack([np.cos(ang), np.sin(ang)])])  # (1 + RIM_POINTS, 2)
    xy = (w[:, None, :2] + ring[None, :, :]).reshape(-1, 2)
    h = np.asarray(heights_below_m(xy), dtype=float).reshape(len(w), len(ring))
    rim = h[:, 1:].max(axis=1)
    # material no taller than the landing gear is ground the vehicle stands on, as the floor (a pile's toe thins to
    # millimetres, and a served flight's take-off spot beside one had its gear 2 mm "into" it, on its springs)
    gap = np.minimum(np.where(h[:, 0] > below_m, w[:, 2] - below_m - h[:, 0], math.inf),
                     np.where(rim > below_m, w[:, 2] + rotor_m - rim, math.inf))
    if not np.isfinite(gap).any():
        return None
    i = int(np.argmin(gap))
    return Approach(float(gap[i]), "the pile", float(t[i]))


def f450_pile_approach(t_s: np.ndarray, true_w_m: np.ndarray, heights_below_m) -> Approach | None:
    """`pile_approach` for JSBSim's F450 (its reach, landing gear and propellers, read from the model)."""
    return pile_approach(t_s, true_w_m, heights_below_m, f450_reach_m(), f450_below_m(), f450_rotor_height_m())


def pile_collision(approach: Approach | None) -> str | None:
    """Why the flight crashed into the pile (None: its landing gear and propellers stayed above it: `pile_approach`)."""
    if approach is None or approach.distance_m > 0.0:
        return None
    return (f"the vehicle hit the pile at t = {approach.t_s:.0f} s: its landing gear or propellers came "
            f"{-approach.distance_m:.2f} m into the pile's surface")
