"""`pilescan-sitl serve`: the simulated vehicle as a networked MAVLink autopilot, paced to the wall clock.

The vehicle waits on the floor below W0 of the survey (the plan's home), disarmed. The plan is
written next to the telemetry log so a ground station can load it; the local NED origin (the
storage frame's corner) is the EKF origin both use for global positions.
"""

from __future__ import annotations

import math
import signal
import sys
import threading
from pathlib import Path

from firmware_py.frames import StorageFrame
from sitl.flight import start_pose
from sitl.jsbsim_plant import PlantConfig
from sitl.jsbsim_vehicle import JsbsimVehicle, VehicleConfig
from sitl.kinematic_vehicle import KinematicVehicle
from sitl.mavlink_vehicle import MavlinkVehicleServer, make_transport, run_realtime
from sitl.mission import Mission
from sitl.mission_plan import DEFAULT_ORIGIN, write_qgc_wpl
from sitl.run import PLAN_FILE, TLOG_FILE


def make_vehicle(kind: str, mission: Mission, frame: StorageFrame):
    (n, e, _), _yaw = start_pose(mission, frame)
    if kind == "kinematic":
        return KinematicVehicle(speed_m_s=mission.speed_m_s, yaw_rate_max_rad_s=mission.yaw_rate_max_rad_s,
                                altitude_m=mission.altitude_m, home_ned_m=(n, e, 0.0))
    return JsbsimVehicle(VehicleConfig(plant=PlantConfig(start_ned_m=(n, e, 0.0)), speed_m_s=mission.speed_m_s,
                                       yaw_rate_max_rad_s=mission.yaw_rate_max_rad_s, altitude_m=mission.altitude_m))


def serve(mission: Mission, url: str, speedup: float, duration_s: float | None, kind: str, out: Path) -> int:
    if not (math.isfinite(speedup) and 0 < speedup <= 1000):
        raise ValueError(f"--speedup must be in (0, 1000], got {speedup:g}")
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"--duration must be > 0 s, got {duration_s:g}")
    frame = StorageFrame()
    out.mkdir(parents=True, exist_ok=True)
    plan = write_qgc_wpl(out / PLAN_FILE, mission, frame)
    vehicle = make_vehicle(kind, mission, frame)
    transport = make_transport(url)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    lat0, lon0, alt0 = DEFAULT_ORIGIN
    print(f"pilescan-sitl: serving a {kind} quadcopter on {url} ({speedup:g}x real time); plan: {plan}",
          file=sys.stderr, flush=True)
    try:
        with MavlinkVehicleServer(vehicle, transport, tlog_path=out / TLOG_FILE, home_lat_deg=lat0,
                                  home_lon_deg=lon0, home_alt_m=alt0) as server:
            sim_s = run_realtime(server, vehicle, speedup=speedup, duration_s=duration_s, stop_event=stop)
    finally:
        transport.close()
    print(f"pilescan-sitl: stopped after {sim_s:.1f} simulated seconds; telemetry in {out / TLOG_FILE}",
          file=sys.stderr)
    return 0
