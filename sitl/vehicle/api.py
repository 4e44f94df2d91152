"""What a simulated vehicle offers to the layers around it (MAVLink server, lockstep runner, tests).

The MAVLink vehicle (`sitl/mavlink/server.py`) speaks to any object with this interface: the
flight-dynamics vehicle (`sitl/vehicle/jsbsim_vehicle.py`) or the kinematic one (`sitl/vehicle/kinematic_vehicle.py`).
All positions are local NED, metres; angles radians; time is simulated seconds since boot.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np


class NavKind(enum.Enum):
    TAKEOFF = "takeoff"
    WAYPOINT = "waypoint"
    LAND = "land"


@dataclass(frozen=True)
class NavItem:
    """One mission item, already in local NED (the MAVLink layer converts frames)."""

    kind: NavKind
    north_m: float
    east_m: float
    down_m: float

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.north_m, self.east_m, self.down_m)):
            raise ValueError(f"mission item position must be finite, got {self}")


class FlightMode(enum.IntEnum):
    """ArduCopter custom mode numbers, so standard GCS tools map names to numbers themselves."""

    STABILIZE = 0
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    LAND = 9


@dataclass(frozen=True)
class VehicleState:
    t_s: float
    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float
    pitchspeed_rad_s: float
    yawspeed_rad_s: float
    armed: bool
    mode: FlightMode
    landed: bool
    energy_j: float
    battery_voltage_v: float


class PlantState(NamedTuple):
    """The rigid body at one physics step, as the plant reports it: local NED, m, m/s, rad, rad/s.

    A NamedTuple, not a dataclass: the lockstep SITL keeps one per physics step and reads them at
    every LiDAR sample, and it is still a tuple for code that unpacks it.
    """

    north_m: float
    east_m: float
    down_m: float
    vn_m_s: float
    ve_m_s: float
    vd_m_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float
    pitchspeed_rad_s: float
    yawspeed_rad_s: float

    @classmethod
    def of(cls, s: VehicleState) -> PlantState:
        """The plant state of any vehicle's `VehicleState`."""
        return cls(*s.pos_ned_m, *s.vel_ned_m_s, s.roll_rad, s.pitch_rad, s.yaw_rad, s.rollspeed_rad_s,
                   s.pitchspeed_rad_s, s.yawspeed_rad_s)


PLANT_STATE_DTYPE = np.dtype([(name, np.float64) for name in PlantState._fields])
"""A recorded flight: one `PlantState` per physics step, fields by name (`states["yaw_rad"]`)."""


class CommandRejected(Exception):
    """A command that cannot be done in the vehicle's current state (maps to MAV_RESULT_DENIED)."""


class Vehicle(Protocol):
    """The simulated vehicle, stepped by its owner; never sleeps, never reads a wall clock."""

    dt_s: float
    """Physics step, s."""

    params: dict[str, float]
    """Settable parameters by name (e.g. 'PS_SPEED_MS', 'PS_YAW_RATE_DPS', 'PS_ALT_M'); see set_param."""

    def state(self) -> VehicleState: ...

    def step(self) -> None:
        """Advance one physics step of dt_s."""

    def arm(self) -> None:
        """Arm the motors; CommandRejected if not landed or already flying."""

    def disarm(self, force: bool = False) -> None:
        """Disarm; CommandRejected in flight unless force."""

    def set_mode(self, mode: FlightMode) -> None:
        """Change flight mode; CommandRejected for unsupported modes or AUTO without a mission."""

    def takeoff(self, altitude_m: float) -> None:
        """GUIDED take-off to altitude_m above the floor; CommandRejected unless armed and landed."""

    def load_mission(self, items: list[NavItem]) -> None:
        """Replace the mission (not while executing it in AUTO)."""

    def start_mission(self) -> None:
        """MAV_CMD_MISSION_START: fly the mission from item 0 (arms into AUTO if landed and armed)."""

    def set_param(self, name: str, value: float) -> None:
        """Set a parameter; KeyError for unknown names, ValueError for bad values."""

    def pop_reached(self) -> list[int]:
        """Mission item indices reached since the last call (for MISSION_ITEM_REACHED)."""

    def current_item(self) -> int:
        """Index of the mission item being flown (MISSION_CURRENT), or -1."""

    def pop_status_text(self) -> list[str]:
        """Messages for the operator since the last call (STATUSTEXT)."""
