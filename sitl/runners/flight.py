"""Fly a survey Mission with the flight-dynamics vehicle, lockstep, and record what it flew.

The vehicle starts hovering on waypoint W0 at the survey altitude, facing along the closing leg
(as the ideal plant does, see sitl.missions.rectangle). It first holds that hover for a settling time, so the
altitude loop's integrator has found the hover thrust for this airframe and payload (as after a
real take-off); then, in AUTO with the loop's waypoints W1..Wn as its mission, it flies the survey,
which ends when it reaches Wn = W0. Time and energy count from the start of the survey. States are
recorded at every physics step and interpolated to the LiDAR's sample times.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.frames import StorageFrame
from firmware_py.core.site import DEFAULT_SITE, GeodeticPoint
from sitl.mavlink.server import MavlinkVehicleServer
from sitl.mavlink.transport import PipeTransport
from sitl.missions.rectangle import Mission
from sitl.vehicle.api import PLANT_STATE_DTYPE, FlightMode, NavItem, NavKind
from sitl.vehicle.ideal_plant import Trajectory, wrap_pi
from sitl.vehicle.jsbsim_plant import PlantConfig
from sitl.vehicle.jsbsim_vehicle import JsbsimVehicle, VehicleConfig

PAYLOAD_1D_KG = 0.040
"""LIDAR-Lite v3 + micro servo (paper Sec. 4.5)."""


@dataclass(frozen=True)
class FlownMission:
    """What the vehicle did: states at each physics step, energy, and whether it finished."""

    t_s: np.ndarray
    states: np.ndarray  # (N,) of PLANT_STATE_DTYPE: the PlantState at each physics step
    energy_j: float
    duration_s: float
    completed: bool
    reached: list[int]
    pose_error: np.ndarray | None = None  # (N, 4) estimate minus truth at each step (None: flown on the truth)

    def trajectory_at(self, t_s: np.ndarray) -> Trajectory:
        """States interpolated at times t_s (linear in position, unwrapped-linear in the angles)."""
        t = np.clip(t_s, self.t_s[0], self.t_s[-1])
        interp = lambda col: np.interp(t, self.t_s, col)  # noqa: E731
        s = self.states
        pos = np.column_stack([interp(s["north_m"]), interp(s["east_m"]), interp(s["down_m"])])
        roll, pitch = interp(s["roll_rad"]), interp(s["pitch_rad"])
        yaw = wrap_pi(interp(np.unwrap(s["yaw_rad"])))
        return Trajectory(np.asarray(t_s, dtype=float), pos, roll, pitch, yaw)

    def pose_error_at(self, t_s: np.ndarray) -> np.ndarray | None:
        """The estimator's error (N, 4) [dn, de, dd, dyaw] at times t_s, linear between steps (None: none)."""
        if self.pose_error is None:
            return None
        t = np.clip(t_s, self.t_s[0], self.t_s[-1])
        return np.column_stack([np.interp(t, self.t_s, self.pose_error[:, j]) for j in range(4)])


def mission_nav_items(mission: Mission, frame: StorageFrame) -> list[NavItem]:
    """The loop's waypoints W1..Wn as NED mission items at the survey altitude."""
    wp = mission.waypoints_w()
    pts = frame.w_to_ned(np.column_stack([wp, np.full(len(wp), mission.altitude_m)]))
    return [NavItem(NavKind.WAYPOINT, *map(float, p)) for p in pts[1:]]


def start_pose(mission: Mission, frame: StorageFrame) -> tuple[tuple[float, float, float], float]:
    """W0 in NED and the yaw of the closing leg (the way the vehicle arrives on the loop)."""
    wp = mission.waypoints_w()
    p0 = frame.w_to_ned([wp[0, 0], wp[0, 1], mission.altitude_m])
    d = wp[-1] - wp[-2]
    yaw = float(frame.yaw_from_w_heading(math.atan2(d[1], d[0])))
    return (float(p0[0]), float(p0[1]), float(p0[2])), yaw


SETTLE_S = 10.0


def fly_mission(mission: Mission, frame: StorageFrame, payload_kg: float = PAYLOAD_1D_KG,
                dt_s: float = 1.0 / 200.0, timeout_s: float | None = None,
                tlog_path: str | Path | None = None, origin: GeodeticPoint = DEFAULT_SITE.corner,
                drift=None) -> FlownMission:
    """Fly the survey with JSBSim + autopilot as fast as the CPU allows.

    With tlog_path, the vehicle also runs its MAVLink server (streams at their default rates, on an
    in-memory link nobody answers yet) and everything it sends goes into that telemetry log.
    `origin` is the local NED frame's place on Earth: the plant's reference and the server's home.
    With `drift` (`sitl.sensing.pose_drift.PoseDrift`) the autopilot flies on an estimate with that error
    (what its MAVLink pose reports too); the flight records the error at every step.
    """
    start, yaw0 = start_pose(mission, frame)
    cfg = VehicleConfig(plant=PlantConfig(dt_s=dt_s, payload_kg=payload_kg, start_ned_m=start,
                                          start_yaw_rad=yaw0, airborne=True, origin=origin),
                        speed_m_s=mission.speed_m_s, yaw_rate_max_rad_s=mission.yaw_rate_max_rad_s,
                        altitude_m=mission.altitude_m)
    v = JsbsimVehicle(cfg, armed=True, mode=FlightMode.GUIDED)
    if drift is not None:
        v.attach_drift(drift)
    with contextlib.ExitStack() as stack:
        tick = _telemetry(stack, v, tlog_path, origin)
        return _fly(v, mission, frame, dt_s, timeout_s, tick)


def _telemetry(stack: contextlib.ExitStack, v: JsbsimVehicle, tlog_path: str | Path | None,
               origin: GeodeticPoint) -> Callable[[], None]:
    """A per-step hook that serves MAVLink into a tlog, or does nothing."""
    if tlog_path is None:
        return lambda: None
    server_end, client_end = PipeTransport.pair()
    server = stack.enter_context(MavlinkVehicleServer(v, server_end, tlog_path=tlog_path, home=origin))

    def tick() -> None:
        server.update()
        client_end.recv()  # drain: no peer in a lockstep flight without the payload
    return tick


def _fly(v: JsbsimVehicle, mission: Mission, frame: StorageFrame, dt_s: float, timeout_s: float | None,
         tick: Callable[[], None]) -> FlownMission:
    for _ in range(int(SETTLE_S / dt_s)):
        v.step()
        tick()
    t0, e0 = v.plant.t_s, v.plant.energy_j
    v.load_mission(mission_nav_items(mission, frame))
    v.start_mission()
    if timeout_s is None:  # three times the ideal flight, plus a minute: generous, but bounded
        ideal_s = mission.path_length_m() / mission.speed_m_s + 2 * math.pi / mission.yaw_rate_max_rad_s
        timeout_s = 3 * ideal_s + 60
    n_max = int(timeout_s / dt_s) + 1
    t = np.empty(n_max + 1)
    states = np.empty(n_max + 1, dtype=PLANT_STATE_DTYPE)
    errors = np.zeros((n_max + 1, 4)) if v.drift is not None else None
    t[0], states[0] = 0.0, v.plant_state
    if errors is not None:
        errors[0] = v.pose_error
    k = 0
    while k < n_max and v.mode == FlightMode.AUTO:
        v.step()
        tick()
        k += 1
        t[k], states[k] = v.plant.t_s - t0, v.plant_state
        if errors is not None:
            errors[k] = v.pose_error
    return FlownMission(t[: k + 1], states[: k + 1], v.plant.energy_j - e0, float(t[k]),
                        v.mode != FlightMode.AUTO and v.current_item() == -1, v.pop_reached(),
                        None if errors is None else errors[: k + 1])
