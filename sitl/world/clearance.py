"""How close the vehicle's true path came to the building: a flight that touches a wall or the roof crashed.

The autopilot flies on its estimate (`sitl.sensing.pose_drift`), so an estimate a metre off puts the true
vehicle a metre off the planned path; near a wall that is a collision, which a real flight does not survive
and the physics here would not stop. `closest_approach` finds the nearest approach to the four walls and the
roof over the true trajectory; `fly` refuses to write a survey whose vehicle reached a surface
(within `f450_reach_m`) and records the approach in truth.json. The floor is left out: the vehicle takes off from
it and lands on it.
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


@cache
def f450_reach_m() -> float:
    """How far JSBSim's F450 reaches from its centre: its farthest propeller hub plus that propeller's radius,
    read from the model the `jsbsim` wheel ships (0.233 m + 9.4 in / 2 = 0.353 m)."""
    import jsbsim

    root = Path(jsbsim.get_default_root_dir())
    reach = 0.0
    for thruster in ET.parse(root / "aircraft" / "F450" / "Propulsion.xml").getroot().iter("thruster"):
        loc = thruster.find("location")
        hub = math.hypot(float(loc.findtext("x")), float(loc.findtext("y"))) * UNIT_M[loc.get("unit", "M").upper()]
        prop = ET.parse(root / "engine" / f"{thruster.get('file')}.xml").getroot().find("diameter")
        dia = float(prop.text) * UNIT_M[prop.get("unit", "IN").upper()]
        reach = max(reach, hub + dia / 2.0)
    if not reach > 0:
        raise RuntimeError("the F450 model shipped with jsbsim declares no thruster")
    return reach


@dataclass(frozen=True)
class Approach:
    """The nearest the true vehicle centre came to a wall or the roof (t_s on the trajectory's clock)."""

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
