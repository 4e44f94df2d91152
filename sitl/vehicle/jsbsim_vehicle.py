"""The flight-dynamics vehicle: JSBSim F450 plant + our autopilot + modes and mission sequencing.

Implements `sitl.vehicle.api.Vehicle`, so the MAVLink server and the lockstep runner can drive it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from firmware_py.core.pose_source import EKF_SOURCE_PARAMS
from sitl.sensing.pose_drift import PoseErrorProfile, ekf_source_params
from sitl.vehicle.api import CommandRejected, FlightMode, NavItem, NavKind, PlantState, VehicleState
from sitl.vehicle.autopilot import Autopilot, Gains, Target, wrap_pi
from sitl.vehicle.jsbsim_plant import GEAR_HEIGHT_M, JsbsimPlant, PlantConfig

PARAM_LIMITS = {
    "PS_SPEED_MS": (0.05, 15.0),
    "PS_YAW_RATE_DPS": (0.1, 360.0),
    "PS_ALT_M": (0.5, 100.0),
    "PS_WP_RADIUS_M": (0.05, 10.0),
    "PS_CLIMB_MS": (0.1, 5.0),
}
LANDED_HEIGHT_M = GEAR_HEIGHT_M + 0.03
TAKEOFF_TOLERANCE_M = 0.2
LAND_CARROT_M = 0.5
"""A landing descends after a target this far below the vehicle (a slow, steady descent to the ground)."""
BRAKE_Z_M_S2 = 1.0
"""The vertical deceleration a climb's reference height brakes with before its goal: ArduPilot's default for the
waypoint navigator's vertical acceleration (WPNAV_ACCEL_Z, 100 cm/s/s)."""


@dataclass
class VehicleConfig:
    plant: PlantConfig = field(default_factory=PlantConfig)
    gains: Gains = field(default_factory=Gains)
    speed_m_s: float = 1.0
    yaw_rate_max_rad_s: float = math.radians(30)
    altitude_m: float = 12.0
    wp_radius_m: float = 0.25
    climb_rate_m_s: float = 2.5
    """Take-off climb rate (PS_CLIMB_MS): ArduPilot's default for auto climbs (WPNAV_SPEED_UP, 250 cm/s)."""


class JsbsimVehicle:
    """A quadcopter you can arm, take off, send on a mission and land, in simulated time."""

    def __init__(self, cfg: VehicleConfig | None = None, armed: bool = False,
                 mode: FlightMode = FlightMode.STABILIZE) -> None:
        self.cfg = cfg or VehicleConfig()
        self.plant = JsbsimPlant(self.cfg.plant)
        self.dt_s = self.cfg.plant.dt_s
        self.params: dict[str, float] = {
            "PS_SPEED_MS": self.cfg.speed_m_s,
            "PS_YAW_RATE_DPS": math.degrees(self.cfg.yaw_rate_max_rad_s),
            "PS_ALT_M": self.cfg.altitude_m,
            "PS_WP_RADIUS_M": self.cfg.wp_radius_m,
            "PS_CLIMB_MS": self.cfg.climb_rate_m_s,
            **ekf_source_params(PoseErrorProfile.NONE),
        }
        self.ap = Autopilot(self.cfg.gains, self.cfg.yaw_rate_max_rad_s)
        self.armed = armed
        self.mode = mode
        self.mission: list[NavItem] = []
        self._item = -1
        self._reached: list[int] = []
        self._texts: list[str] = []
        self._s = self.plant.read()
        self.drift = None
        """A `sitl.sensing.pose_drift.PoseDrift`: the estimator's error, which guidance flies on (None: the truth)."""
        self.pose_error: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        """The estimate minus the truth now (north, east, down m; yaw rad): what the autopilot reports."""
        self._e = self._s  # the estimated state guidance flies on (the truth without a drift)
        n, e, d = self._e[:3]
        self._hold = Target(n, e, d, yaw_rad=self._e[8])
        self._climb_to: float | None = None
        self._ref_d: float | None = None  # a climb's moving reference height (down, m); None: not climbing
        self._landing = False

    # ----------------------------------------------------------------- protocol: state and stepping
    def state(self) -> VehicleState:
        n, e, d, vn, ve, vd, roll, pitch, yaw, p, q, r = self._s
        return VehicleState(self.plant.t_s, (n, e, d), (vn, ve, vd), roll, pitch, wrap_pi(yaw), p, q, r,
                            self.armed, self.mode, self.landed, self.plant.energy_j,
                            16.8 - 1.5e-5 * self.plant.energy_j)

    def time_s(self) -> float:
        """The vehicle's clock (state().t_s without building a VehicleState: read every physics step)."""
        return self.plant.t_s

    @property
    def plant_state(self) -> PlantState:
        """The rigid body as the plant last reported it (yaw not wrapped, unlike `state()`)."""
        return self._s

    @property
    def landed(self) -> bool:
        return -self._s[2] < LANDED_HEIGHT_M and abs(self._s[5]) < 0.2

    def step(self) -> None:
        if self.armed:
            target = self._target()
            self.plant.set_escs(*self.ap.update(self.dt_s, self._e, target))
        else:
            self.plant.set_escs(0.0, 0.0, 0.0, 0.0)
            self.ap.reset()
        self.plant.step()
        self._s = self.plant.read()
        if self.drift is None:
            self._e = self._s
        else:
            self._estimate()

    def attach_drift(self, drift) -> None:
        """Fly on an estimate with this error (`sitl.sensing.pose_drift.PoseDrift`) from now on; the physics
        stays true. The hold point is taken over into the estimate's frame."""
        self.drift = drift
        self.params.update(drift.ekf_params)
        self._estimate()
        n, e, d = self._e[:3]
        self._hold = Target(n, e, d, yaw_rad=self._e[8])

    def _estimate(self) -> None:
        s = self._s
        err = self.drift.update(self.plant.t_s, (s[0], s[1], s[2]))
        self.pose_error = (err[0], err[1], err[2], err[3])
        self._e = PlantState(s[0] + err[0], s[1] + err[1], s[2] + err[2], *s[3:8], s[8] + err[3], *s[9:])

    @property
    def estimated_state(self) -> PlantState:
        """What the autopilot believes (the plant state plus `pose_error`)."""
        return self._e

    # ----------------------------------------------------------------- guidance
    def _target(self) -> Target:
        if self._landing:
            return self._land_target()
        if self._climb_to is not None:
            return self._climb_target(self._climb_to)
        if self.mode == FlightMode.AUTO and 0 <= self._item < len(self.mission):
            return self._mission_target()
        return self._hold

    def _ramp(self, d_goal: float) -> tuple[float, float]:
        """A reference height (down, m) and how fast it rises (m/s): it moves towards the goal at the climb rate and
        slows before it as fast as BRAKE_Z_M_S2 allows (the square-root profile of ArduPilot's position controller),
        so climbs are steady and stop at the goal. It used to be a carrot a second of climb above the vehicle's own
        height: the vehicle chased it ever faster (2.3 m/s for 1 m/s asked) and overshot a 9 m take-off by 1.8 m,
        through a 10 m roof."""
        if self._ref_d is None:
            self._ref_d = self._e[2]
        left = d_goal - self._ref_d
        speed = min(self.params["PS_CLIMB_MS"], math.sqrt(2.0 * BRAKE_Z_M_S2 * abs(left)))
        step = speed * self.dt_s
        moved = max(-step, min(step, left))
        self._ref_d += moved
        return self._ref_d, -moved / self.dt_s

    def _climb_target(self, d_goal: float) -> Target:
        ref_d, climb_m_s = self._ramp(d_goal)
        t = Target(self._hold.north_m, self._hold.east_m, ref_d, yaw_rad=self._hold.yaw_rad, climb_m_s=climb_m_s)
        if abs(self._e[2] - d_goal) < TAKEOFF_TOLERANCE_M:
            self._climb_to = None
            self._ref_d = None
            self._hold = Target(self._hold.north_m, self._hold.east_m, d_goal, yaw_rad=self._hold.yaw_rad)
            self._advance_if_item(NavKind.TAKEOFF)
        return t

    def _land_target(self) -> Target:
        t = Target(self._hold.north_m, self._hold.east_m, self._e[2] + LAND_CARROT_M,
                   yaw_rad=self._hold.yaw_rad)
        if self.landed:
            self._landing = False
            self.armed = False  # before advancing: a mission that ends landed stays in its mode
            self._texts.append("landed and disarmed")
            self._advance_if_item(NavKind.LAND)
        return t

    def _mission_target(self) -> Target:
        item = self.mission[self._item]
        n, e, d = self._e[:3]
        if item.kind == NavKind.TAKEOFF:
            self._hold = Target(n, e, item.down_m, yaw_rad=self._e[8])
            self._climb_to, self._ref_d = item.down_m, None
            return self._climb_target(item.down_m)
        if item.kind == NavKind.LAND:
            self._hold = Target(n, e, d, yaw_rad=self._e[8])
            self._landing = True
            return self._land_target()
        dist = math.dist((n, e, d), (item.north_m, item.east_m, item.down_m))
        if dist < self.params["PS_WP_RADIUS_M"]:
            self._reach()
            if self.mode == FlightMode.AUTO and 0 <= self._item < len(self.mission):
                return self._mission_target()
            return self._hold
        return Target(item.north_m, item.east_m, item.down_m, speed_m_s=self.params["PS_SPEED_MS"])

    def _advance_if_item(self, kind: NavKind) -> None:
        if self.mode == FlightMode.AUTO and 0 <= self._item < len(self.mission) \
                and self.mission[self._item].kind == kind:
            self._reach()

    def _reach(self) -> None:
        self._reached.append(self._item)
        self._item += 1
        if self._item >= len(self.mission):
            self._item = -1
            n, e, d = self._e[:3]
            self._hold = Target(n, e, d, yaw_rad=self._e[8])
            if self.armed and not self._landing:
                self.mode = FlightMode.LOITER
            self._texts.append("mission complete")

    # ----------------------------------------------------------------- protocol: commands
    def arm(self) -> None:
        if self.armed:
            raise CommandRejected("already armed")
        if not self.landed:
            raise CommandRejected("cannot arm: not on the ground")
        self.armed = True
        n, e, d = self._e[:3]
        self._hold = Target(n, e, d, yaw_rad=self._e[8])
        if self.mode == FlightMode.AUTO and self.mission:
            self.start_mission()

    def disarm(self, force: bool = False) -> None:
        if not self.armed:
            return
        if not self.landed and not force:
            raise CommandRejected("cannot disarm in flight (use force)")
        self.armed = False

    def set_mode(self, mode: FlightMode) -> None:
        mode = FlightMode(mode)
        if mode == FlightMode.AUTO:
            if not self.mission:
                raise CommandRejected("AUTO needs a mission")
            self.mode = mode
            if self.armed:
                self._item = 0 if self._item < 0 else self._item
            return
        if mode == FlightMode.LAND:
            self.mode = mode
            n, e, d = self._e[:3]
            self._hold = Target(n, e, d, yaw_rad=self._e[8])
            self._landing = self.armed and not self.landed
            return
        if mode not in (FlightMode.GUIDED, FlightMode.LOITER, FlightMode.STABILIZE):
            raise CommandRejected(f"mode {mode.name} is not supported")
        self.mode = mode
        n, e, d = self._e[:3]
        self._hold = Target(n, e, d, yaw_rad=self._e[8])

    def takeoff(self, altitude_m: float) -> None:
        if not (math.isfinite(altitude_m) and 0.5 <= altitude_m <= 100):
            raise ValueError(f"take-off altitude must be 0.5-100 m, got {altitude_m}")
        if not self.armed or not self.landed:
            raise CommandRejected("take-off needs the vehicle armed and on the ground")
        if self.mode != FlightMode.GUIDED:
            raise CommandRejected("take-off needs GUIDED mode")
        n, e, _ = self._e[:3]
        self._hold = Target(n, e, -altitude_m, yaw_rad=self._e[8])
        self._climb_to, self._ref_d = -altitude_m, None

    def load_mission(self, items: list[NavItem]) -> None:
        if self.mode == FlightMode.AUTO and self._item >= 0 and self.armed:
            raise CommandRejected("cannot replace the mission while flying it")
        self.mission = list(items)
        self._item = -1

    def start_mission(self) -> None:
        if not self.mission:
            raise CommandRejected("no mission loaded")
        if not self.armed:
            raise CommandRejected("arm first")
        self.mode = FlightMode.AUTO
        self._item = 0

    def set_param(self, name: str, value: float) -> None:
        if name in EKF_SOURCE_PARAMS:
            raise ValueError(f"{name} is read-only in the SITL: the pose-error profile (--pose-error) sets it")
        if name not in PARAM_LIMITS:
            raise KeyError(name)
        lo, hi = PARAM_LIMITS[name]
        if not (math.isfinite(value) and lo <= value <= hi):
            raise ValueError(f"{name} must be {lo:g}-{hi:g}, got {value}")
        self.params[name] = float(value)
        if name == "PS_YAW_RATE_DPS":
            self.ap.yaw_rate_max_rad_s = math.radians(value)

    def pop_reached(self) -> list[int]:
        out, self._reached = self._reached, []
        return out

    def current_item(self) -> int:
        return self._item

    def pop_status_text(self) -> list[str]:
        out, self._texts = self._texts, []
        return out
