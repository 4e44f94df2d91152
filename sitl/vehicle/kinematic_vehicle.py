"""Kinematic quadcopter: a point mass that flies NavItems exactly, for tests and the quick SITL mode.

It implements `sitl.vehicle.api.Vehicle` with no dynamics at all, so MAVLink plumbing, mission
logic and the payload can be exercised thousands of times faster than with the flight-dynamics
plant. Behaviour, chosen to be simple and predictable:

- Starts landed, disarmed, in STABILIZE, at home on the floor (down = 0, the floor is down = 0).
- Modes: STABILIZE, GUIDED, LOITER (all three hover in place when airborne), AUTO (flies the
  mission) and LAND (descends and disarms). RTL is not supported (CommandRejected).
- Arming needs landed, disarmed and an armable mode: AUTO and LAND are not armable, as in
  ArduCopter; arm in STABILIZE/GUIDED/LOITER, then switch to AUTO or send MISSION_START.
- GUIDED take-off climbs vertically at the climb rate.
- AUTO flies the items in order. TAKEOFF climbs vertically to the item's altitude (-down) where
  the vehicle is (north/east ignored, as ArduCopter ignores take-off lat/lon); an altitude below
  0.5 m means "the default", PS_ALT_M. WAYPOINT first yaws in place towards the waypoint at the
  yaw-rate limit until the heading error is below 1 deg, then flies the straight 3D line to it at
  PS_SPEED_MS horizontally (the climb/descent rate capped at the climb rate, slowing the whole
  motion so the path stays straight). An item is reached within 0.1 m (3D). LAND descends where
  the vehicle is to the floor, lands and disarms; the mission ends there. Targets below the floor
  are taken as on the floor.
- After the last item (if not LAND) the vehicle hovers and switches to LOITER ("mission complete").
- Leaving AUTO mid-mission pauses it; entering AUTO again resumes the interrupted item (ArduPilot
  does the same); a finished or newly loaded mission starts from item 0.
- A forced disarm in the air stops everything and drops the vehicle to the floor at once: the
  point mass has no fall dynamics, and a test only needs to see that it ends landed and disarmed.
- Energy is a placeholder power model, P = 180 W hover + 20 W per m/s of speed, integrated while
  airborne; the battery voltage sags linearly with energy used (16.0 V full, 1 V per 100 kJ,
  never below 13.0 V). The flight-dynamics plant computes real motor power.

Deterministic: time is step count x dt_s; no wall clock, no sleeping.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from firmware_py.core.pose_source import EKF_SOURCE_PARAMS
from sitl.sensing.pose_drift import PoseErrorProfile, ekf_source_params
from sitl.vehicle.api import CommandRejected, FlightMode, NavItem, NavKind, VehicleState
from sitl.vehicle.autopilot import wrap_pi

PARAM_LIMITS: dict[str, tuple[float, float]] = {
    "PS_SPEED_MS": (0.05, 15.0),
    "PS_YAW_RATE_DPS": (0.1, 360.0),
    "PS_ALT_M": (0.5, 100.0),
}
"""Settable parameters and their inclusive ranges (degrees at the interface, like ArduPilot)."""

ACCEPT_RADIUS_M = 0.1
HEADING_TOLERANCE_RAD = math.radians(1.0)
MIN_TAKEOFF_ALT_M = 0.5
HOVER_POWER_W = 180.0
POWER_PER_SPEED_W_PER_M_S = 20.0
FULL_VOLTAGE_V = 16.0
VOLTAGE_DROP_V_PER_J = 1.0e-5
MIN_VOLTAGE_V = 13.0

SUPPORTED_MODES = frozenset({FlightMode.STABILIZE, FlightMode.GUIDED, FlightMode.LOITER,
                             FlightMode.AUTO, FlightMode.LAND})
UNARMABLE_MODES = frozenset({FlightMode.AUTO, FlightMode.LAND})


def _check_positive(name: str, value: float) -> float:
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value}")
    return float(value)


class KinematicVehicle:
    """Point-mass quadcopter implementing the Vehicle protocol (see the module docstring)."""

    def __init__(self, dt_s: float = 0.01, speed_m_s: float = 1.0, yaw_rate_max_rad_s: float = math.radians(30),
                 altitude_m: float = 12.0, climb_rate_m_s: float = 1.0,
                 home_ned_m: Sequence[float] = (0.0, 0.0, 0.0)) -> None:
        self.dt_s = _check_positive("dt_s", dt_s)
        self.climb_rate_m_s = _check_positive("climb_rate_m_s", climb_rate_m_s)
        home = tuple(float(v) for v in home_ned_m)
        if len(home) != 3 or not all(math.isfinite(v) for v in home) or home[2] != 0.0:
            raise ValueError(f"home must be a finite NED point on the floor (down = 0), got {home_ned_m}")
        self.params: dict[str, float] = {}
        self.set_param("PS_SPEED_MS", speed_m_s)
        self.set_param("PS_YAW_RATE_DPS", math.degrees(yaw_rate_max_rad_s))
        self.set_param("PS_ALT_M", altitude_m)
        self.params.update(ekf_source_params(PoseErrorProfile.NONE))  # an exact pose: what a good fix reports

        self._steps = 0
        self._pos = list(home)
        self._vel = (0.0, 0.0, 0.0)
        self._yaw = 0.0
        self._yawspeed = 0.0
        self._armed = False
        self._landed = True
        self._mode = FlightMode.STABILIZE
        self._energy_j = 0.0
        self._mission: tuple[NavItem, ...] = ()
        self._index = -1  # item being flown in AUTO, else -1
        self._resume_index = 0
        self._target: tuple[float, float, float] | None = None
        self._aligned = False
        self._guided_target_down: float | None = None
        self._reached: list[int] = []
        self._status: list[str] = []

    # ----- parameters -------------------------------------------------------------------------

    @property
    def speed_m_s(self) -> float:
        return self.params["PS_SPEED_MS"]

    @property
    def yaw_rate_max_rad_s(self) -> float:
        return math.radians(self.params["PS_YAW_RATE_DPS"])

    @property
    def altitude_m(self) -> float:
        return self.params["PS_ALT_M"]

    def set_param(self, name: str, value: float) -> None:
        """Set a parameter; KeyError for unknown names, ValueError for NaN or out-of-range values."""
        if name in EKF_SOURCE_PARAMS:
            raise ValueError(f"{name} is read-only in the SITL: the vehicle's pose is exact")
        if name not in PARAM_LIMITS:
            raise KeyError(f"unknown parameter {name!r}")
        lo, hi = PARAM_LIMITS[name]
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number, got {value!r}") from None
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"{name} = {value} is outside {lo:g}..{hi:g}")
        self.params[name] = v

    # ----- state ------------------------------------------------------------------------------

    @property
    def t_s(self) -> float:
        return self._steps * self.dt_s

    def state(self) -> VehicleState:
        """Snapshot at the current simulated time."""
        return VehicleState(
            t_s=self.t_s, pos_ned_m=(self._pos[0], self._pos[1], self._pos[2]), vel_ned_m_s=self._vel,
            roll_rad=0.0, pitch_rad=0.0, yaw_rad=self._yaw,
            rollspeed_rad_s=0.0, pitchspeed_rad_s=0.0, yawspeed_rad_s=self._yawspeed,
            armed=self._armed, mode=self._mode, landed=self._landed, energy_j=self._energy_j,
            battery_voltage_v=max(MIN_VOLTAGE_V, FULL_VOLTAGE_V - VOLTAGE_DROP_V_PER_J * self._energy_j),
        )

    def current_item(self) -> int:
        """Index of the mission item being flown, -1 when not flying a mission."""
        return self._index

    def pop_reached(self) -> list[int]:
        out, self._reached = self._reached, []
        return out

    def pop_status_text(self) -> list[str]:
        out, self._status = self._status, []
        return out

    # ----- commands ---------------------------------------------------------------------------

    def arm(self) -> None:
        """Arm on the floor in an armable mode (AUTO and LAND are not, as in ArduCopter)."""
        if self._armed:
            raise CommandRejected("already armed")
        if not self._landed:
            raise CommandRejected("cannot arm: not landed")
        if self._mode in UNARMABLE_MODES:
            raise CommandRejected(f"cannot arm in {self._mode.name}: switch to STABILIZE, GUIDED or LOITER")
        self._armed = True
        self._status.append("armed")

    def disarm(self, force: bool = False) -> None:
        """Disarm on the floor; in the air only with force, which drops the vehicle to the floor."""
        if not self._armed:
            return
        if not self._landed:
            if not force:
                raise CommandRejected("cannot disarm in flight (use force)")
            self._pos[2] = 0.0
            self._landed = True
            self._status.append("forced disarm in flight: dropped to the floor")
        self._stop()
        self._status.append("disarmed")

    def set_mode(self, mode: FlightMode) -> None:
        """Change mode; AUTO needs a mission and an armed vehicle, RTL is not supported."""
        mode = FlightMode(mode)
        if mode not in SUPPORTED_MODES:
            raise CommandRejected(f"mode {mode.name} is not supported")
        if mode is self._mode:
            return
        if mode is FlightMode.AUTO:
            if not self._mission:
                raise CommandRejected("cannot enter AUTO: no mission loaded")
            if not self._armed:
                raise CommandRejected("cannot enter AUTO: arm first")
        self._leave_mode()
        self._mode = mode
        if mode is FlightMode.AUTO:
            self._begin_item(self._resume_index)
        elif mode is FlightMode.LAND and self._landed and self._armed:
            self._touch_down()

    def takeoff(self, altitude_m: float) -> None:
        """GUIDED take-off: climb vertically to altitude_m above the floor."""
        if self._mode is not FlightMode.GUIDED:
            raise CommandRejected(f"takeoff needs GUIDED mode (mode is {self._mode.name})")
        if not self._armed:
            raise CommandRejected("takeoff needs an armed vehicle")
        if not self._landed:
            raise CommandRejected("takeoff needs a landed vehicle")
        if not (math.isfinite(altitude_m) and altitude_m >= MIN_TAKEOFF_ALT_M):
            raise CommandRejected(f"takeoff altitude {altitude_m} m must be >= {MIN_TAKEOFF_ALT_M} m")
        self._guided_target_down = -float(altitude_m)

    def load_mission(self, items: list[NavItem]) -> None:
        """Replace the mission; refused while flying one in AUTO."""
        if self._mode is FlightMode.AUTO and self._armed:
            raise CommandRejected("cannot replace the mission while flying it in AUTO")
        items = list(items)
        for item in items:
            if not isinstance(item, NavItem):
                raise TypeError(f"mission items must be NavItem, got {type(item).__name__}")
        self._mission = tuple(items)
        self._resume_index = 0
        self._reached.clear()

    def start_mission(self) -> None:
        """Fly the mission from item 0 in AUTO (armed, on the floor or in the air)."""
        if not self._mission:
            raise CommandRejected("cannot start mission: no mission loaded")
        if not self._armed:
            raise CommandRejected("cannot start mission: arm first")
        self._leave_mode()
        self._mode = FlightMode.AUTO
        self._begin_item(0)

    # ----- simulation -------------------------------------------------------------------------

    def step(self) -> None:
        """Advance one step of dt_s."""
        self._vel = (0.0, 0.0, 0.0)
        self._yawspeed = 0.0
        if self._armed:
            if self._mode is FlightMode.AUTO and self._index >= 0:
                self._fly_item()
            elif self._mode is FlightMode.GUIDED and self._guided_target_down is not None:
                self._guided_climb()
            elif self._mode is FlightMode.LAND:
                self._land_here()
        if self._armed and not self._landed:
            speed = math.sqrt(sum(v * v for v in self._vel))
            self._energy_j += (HOVER_POWER_W + POWER_PER_SPEED_W_PER_M_S * speed) * self.dt_s
        self._steps += 1

    def _guided_climb(self) -> None:
        target = (self._pos[0], self._pos[1], self._guided_target_down)
        if self._move_towards(target) <= 0.0:
            self._guided_target_down = None
            self._status.append(f"takeoff complete at {-target[2]:g} m")

    def _land_here(self) -> None:
        if self._move_towards((self._pos[0], self._pos[1], 0.0)) <= 0.0:
            self._touch_down()

    def _fly_item(self) -> None:
        item = self._mission[self._index]
        assert self._target is not None
        if item.kind is NavKind.LAND:
            if self._move_towards(self._target) <= 0.0:
                self._complete_item()
            return
        if item.kind is NavKind.WAYPOINT and not self._turn_to_target():
            return
        if self._move_towards(self._target) <= ACCEPT_RADIUS_M:
            self._complete_item()

    def _turn_to_target(self) -> bool:
        """Yaw towards the waypoint; True once the heading is good enough to fly (and while flying)."""
        assert self._target is not None
        dn, de = self._target[0] - self._pos[0], self._target[1] - self._pos[1]
        if math.hypot(dn, de) < ACCEPT_RADIUS_M:
            self._aligned = True  # no meaningful bearing: a vertical move
            return True
        err = wrap_pi(math.atan2(de, dn) - self._yaw)
        max_turn = self.yaw_rate_max_rad_s * self.dt_s
        turn = max(-max_turn, min(max_turn, err))
        self._yaw = wrap_pi(self._yaw + turn)
        self._yawspeed = turn / self.dt_s
        if not self._aligned and abs(err - turn) < HEADING_TOLERANCE_RAD:
            self._aligned = True
            return False  # start flying on the next step
        return self._aligned

    def _move_towards(self, target: tuple[float, float, float]) -> float:
        """One step along the straight line to target; returns the 3D distance left."""
        d = [target[i] - self._pos[i] for i in range(3)]
        dist = math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        if dist == 0.0:
            return 0.0
        t_go = max(math.hypot(d[0], d[1]) / self.speed_m_s, abs(d[2]) / self.climb_rate_m_s)
        frac = 1.0 if t_go <= self.dt_s else self.dt_s / t_go
        self._vel = (d[0] * frac / self.dt_s, d[1] * frac / self.dt_s, d[2] * frac / self.dt_s)
        if frac >= 1.0 or dist * (1.0 - frac) < 1e-9:
            frac = 1.0
            self._pos = list(target)
        else:
            self._pos = [self._pos[i] + d[i] * frac for i in range(3)]
        if self._pos[2] < 0.0:
            self._landed = False
        return dist * (1.0 - frac)

    # ----- mission bookkeeping ----------------------------------------------------------------

    def _begin_item(self, index: int) -> None:
        item = self._mission[index]
        self._index = index
        self._aligned = False
        n, e, d = self._pos
        if item.kind is NavKind.TAKEOFF:
            alt = -item.down_m if -item.down_m >= MIN_TAKEOFF_ALT_M else self.altitude_m
            self._target = (n, e, min(-alt, d))
        elif item.kind is NavKind.LAND:
            self._target = (n, e, 0.0)
        else:
            self._target = (item.north_m, item.east_m, min(item.down_m, 0.0))

    def _complete_item(self) -> None:
        index, item = self._index, self._mission[self._index]
        self._reached.append(index)
        if item.kind is NavKind.LAND:
            self._end_mission()
            self._touch_down()
            if index == len(self._mission) - 1:
                self._status.append("mission complete")
            else:
                self._status.append(f"landed at item {index}: mission stopped")
        elif index == len(self._mission) - 1:
            self._end_mission()
            self._mode = FlightMode.LOITER
            self._status.append("mission complete")
        else:
            self._begin_item(index + 1)

    def _end_mission(self) -> None:
        self._index = -1
        self._resume_index = 0
        self._target = None

    def _touch_down(self) -> None:
        self._pos[2] = 0.0
        self._landed = True
        self._status.append("landed")
        self._stop()
        self._status.append("disarmed")

    def _leave_mode(self) -> None:
        """Pause a mission (to resume later) and cancel a GUIDED take-off."""
        if self._index >= 0:
            self._resume_index = self._index
        self._index = -1
        self._target = None
        self._guided_target_down = None

    def _stop(self) -> None:
        self._armed = False
        self._vel = (0.0, 0.0, 0.0)
        self._yawspeed = 0.0
        self._leave_mode()
