"""`pilescan-sitl serve`: the simulated vehicle as a networked MAVLink autopilot, paced to the wall clock.

The vehicle waits on the floor below W0 of the survey (the plan's home), disarmed. The plan is
written next to the telemetry log so a ground station can load it; the local NED origin (the
storage frame's corner) is the EKF origin both use for global positions.

With `signing` (`--signing-key FILE`) the autopilot signs everything it sends and refuses unsigned,
forged and replayed frames; a UDP client is only sent to once it has sent a signed frame
(MAVProxy: `signing setup PASSPHRASE`, or `signing key FILE` with the same key, before connecting;
pymavlink: `conn.setup_signing(key)`). The emulated device bridge (--devices) is not covered.
"""

from __future__ import annotations

import json
import math
import signal
import sys
import threading
from pathlib import Path

import firmware_py
from firmware_py.frames import StorageFrame
from firmware_py.hal.signing import SigningConfig
from sitl import stockpile as piles
from sitl.devices.bridge_server import parse_bridge_url
from sitl.flight import start_pose
from sitl.jsbsim_plant import PlantConfig
from sitl.jsbsim_vehicle import JsbsimVehicle, VehicleConfig
from sitl.kinematic_vehicle import KinematicVehicle
from sitl.mavlink_vehicle import MavlinkVehicleServer, make_transport, run_realtime
from sitl.mission import Mission
from sitl.mission_plan import DEFAULT_ORIGIN, write_qgc_wpl
from sitl.networked import NetworkedDevices
from sitl.raycast import World
from sitl.run import PILE_FILE, PLAN_FILE, TLOG_FILE, TRUTH_FILE, FlyConfig, check_clearance


def make_vehicle(kind: str, mission: Mission, frame: StorageFrame):
    (n, e, _), yaw = start_pose(mission, frame)  # on the floor below W0, facing along the closing leg
    if kind == "kinematic":
        return KinematicVehicle(speed_m_s=mission.speed_m_s, yaw_rate_max_rad_s=mission.yaw_rate_max_rad_s,
                                altitude_m=mission.altitude_m, home_ned_m=(n, e, 0.0))
    return JsbsimVehicle(VehicleConfig(plant=PlantConfig(start_ned_m=(n, e, 0.0), start_yaw_rad=yaw),
                                       speed_m_s=mission.speed_m_s,
                                       yaw_rate_max_rad_s=mission.yaw_rate_max_rad_s, altitude_m=mission.altitude_m))


def serve(mission: Mission, url: str, speedup: float, duration_s: float | None, kind: str, out: Path,
          devices_url: str | None = None, stockpile: str = "1", signing: SigningConfig | None = None) -> int:
    if not (math.isfinite(speedup) and 0 < speedup <= 1000):
        raise ValueError(f"--speedup must be in (0, 1000], got {speedup:g}")
    if duration_s is not None and not duration_s > 0:
        raise ValueError(f"--duration must be > 0 s, got {duration_s:g}")
    if devices_url is not None and speedup != 1.0:
        raise ValueError("--devices needs --speedup 1: the payload on the other end runs on the wall clock")
    frame = StorageFrame()
    defaults = FlyConfig(mission=mission, stockpile=stockpile)  # the lever arm and LiDAR the lockstep SITL uses
    world = None
    if devices_url is not None:
        parse_bridge_url(devices_url)  # a bad URL fails before any work
        pile = piles.resolve(stockpile, mission.storage)
        check_clearance(mission, pile)
        world = World(mission.storage, pile, max_range_m=defaults.lidar.max_range_m)
    transport = make_transport(url)  # a bad --mavlink fails before anything is written
    try:
        return _serve(mission, url, speedup, duration_s, kind, out, devices_url, stockpile, signing, frame,
                      defaults, world, transport)
    finally:
        transport.close()


def _serve(mission, url, speedup, duration_s, kind, out, devices_url, stockpile, signing, frame, defaults, world,
           transport) -> int:
    pile = world.pile if world is not None else None
    out.mkdir(parents=True, exist_ok=True)
    plan = write_qgc_wpl(out / PLAN_FILE, mission, frame)
    if world is not None:
        pile.mesh.export(out / PILE_FILE)
        truth = {"true_volume_m3": pile.volume_m3, "stockpile": stockpile, "stockpile_source": pile.source,
                 "storage": mission.storage.to_dict(), "storage_frame": frame.to_dict(),
                 "mission": mission.to_dict(), "mission_id": mission.mission_id, "plant": kind,
                 "payload": "networked", "software": f"pilescan {firmware_py.__version__}"}
        (out / TRUTH_FILE).write_text(json.dumps(truth, indent=2) + "\n")
    vehicle = make_vehicle(kind, mission, frame)
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    lat0, lon0, alt0 = DEFAULT_ORIGIN
    devices = None
    try:
        if world is not None:
            devices = NetworkedDevices(vehicle, world, devices_url, frame=frame,
                                       lever_arm_body_m=defaults.lever_arm_body_m).start()
        signed = ""
        if signing is not None:
            signed = "; MAVLink signing on" + (" (unsigned frames accepted)" if signing.allow_unsigned else "")
        print(f"pilescan-sitl: serving a {kind} quadcopter on {url} ({speedup:g}x real time); plan: {plan}"
              + (f"; LiDAR and servo on {devices.url} (pile {stockpile}, {pile.volume_m3:.1f} m^3)" if devices else "")
              + signed, file=sys.stderr, flush=True)
        with MavlinkVehicleServer(vehicle, transport, tlog_path=out / TLOG_FILE, home_lat_deg=lat0,
                                  home_lon_deg=lon0, home_alt_m=alt0, signing=signing) as server:
            sim_s = run_realtime(server, vehicle, speedup=speedup, duration_s=duration_s, stop_event=stop,
                                 on_step=devices.record if devices else None)
    finally:
        if devices is not None:
            devices.close()
        transport.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    refused = ""
    if signing is not None:
        st = server.stats
        refused = (f"; refused {st['rx_unsigned']} unsigned, {st['rx_bad_signature']} badly signed and "
                   f"{st['rx_replayed']} replayed frames")
    print(f"pilescan-sitl: stopped after {sim_s:.1f} simulated seconds; telemetry in {out / TLOG_FILE}{refused}",
          file=sys.stderr)
    return 0
