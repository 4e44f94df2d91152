"""Mission plans for standard tools: QGC WPL 110 (`.waypoints`), as MAVProxy, QGroundControl and
Mission Planner load them, so the same survey can be flown by a real ArduPilot.

The plan is: home (item 0, ArduPilot's convention), set speed, take off on W0 to the survey
altitude, the loop's waypoints W1..Wn (Wn = W0), land; from a take-off spot away from W0 (material below
it), back over that spot at the survey altitude before the landing there. Positions are global, converted from the
local NED frame by the same flat-earth mapping the SITL's MAVLink server uses (about the EKF
origin: the local NED origin, whose lat/lon the plan takes as arguments; `pilescan-sitl plan --origin`
puts it on the site's floor corner, `--heading` turns the building). Altitudes are relative
to home (MAV_FRAME_GLOBAL_RELATIVE_ALT), which indoors is the floor. The yaw-rate limit is not a
mission item in ArduPilot: set the parameter ATC_RATE_Y_MAX (deg/s) on the vehicle.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import ned_to_global
from firmware_py.core.site import DEFAULT_SITE
from sitl.missions.rectangle import Mission

MAV_FRAME_GLOBAL, MAV_FRAME_MISSION, MAV_FRAME_GLOBAL_RELATIVE_ALT = 0, 2, 3
MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_LAND, MAV_CMD_NAV_TAKEOFF, MAV_CMD_DO_CHANGE_SPEED = 16, 21, 22, 178
DEFAULT_ORIGIN = DEFAULT_SITE.corner.as_tuple()
"""lat, lon (deg), altitude AMSL (m) of the local NED origin when no site is given; the SITL server's too."""


def plan_rows(mission: Mission, frame: StorageFrame, origin=DEFAULT_ORIGIN,
              takeoff_w: tuple[float, float] | None = None) -> list[list[float]]:
    """Rows of (frame, command, p1..p4, x/lat, y/lon, z/alt) for the survey: home and the take-off on W0, or at
    takeoff_w (W, m: clear floor away from it), then W0 as the first waypoint and the loop, and the landing at home.
    A copter takes off where it stands (ArduPilot ignores the take-off's position): with W0 first, the survey starts at
    its start wherever the operator put the drone down (reached at once when that is below W0). With takeoff_w the loop
    ends over the material below W0, so the plan flies back over the take-off spot at the survey altitude and lands
    there: a landing at W0 would set the copter down on the pile's slope (the simulator's plant, which knows only the
    floor, descended through 5 m of pile 1)."""
    lat0, lon0, alt0 = origin
    wp = mission.waypoints_w()
    ned = frame.w_to_ned(np.column_stack([wp, np.zeros(len(wp))]))
    floor_d = float(ned[0, 2])
    ll = [ned_to_global(float(n), float(e), lat0, lon0) for n, e, _ in ned]
    home = ll[0]
    if takeoff_w is not None:
        t = frame.w_to_ned([takeoff_w[0], takeoff_w[1], 0.0])
        home = ned_to_global(float(t[0]), float(t[1]), lat0, lon0)
    rows = [[MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT, 0, 0, 0, 0, home[0], home[1], alt0 - floor_d]]
    rows.append([MAV_FRAME_MISSION, MAV_CMD_DO_CHANGE_SPEED, 1, mission.speed_m_s, -1, 0, 0, 0, 0])
    rows.append([MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, home[0], home[1],
                 mission.altitude_m])
    rows += [[MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_CMD_NAV_WAYPOINT, 0, 0, 0, 0, la, lo, mission.altitude_m]
             for la, lo in ll]
    if takeoff_w is not None:  # W0 stands over material: back over the clear floor it left, at the survey altitude
        rows.append([MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_CMD_NAV_WAYPOINT, 0, 0, 0, 0, home[0], home[1],
                     mission.altitude_m])
    rows.append([MAV_FRAME_GLOBAL_RELATIVE_ALT, MAV_CMD_NAV_LAND, 0, 0, 0, 0, home[0], home[1], 0.0])
    return rows


def write_qgc_wpl(path: str | Path, mission: Mission, frame: StorageFrame, origin=DEFAULT_ORIGIN,
                  takeoff_w: tuple[float, float] | None = None) -> Path:
    """Write the survey as a QGC WPL 110 file (tab separated, 12 columns); takeoff_w: see `plan_rows`."""
    lines = ["QGC WPL 110"]
    for i, r in enumerate(plan_rows(mission, frame, origin, takeoff_w)):
        fr, cmd, *p = r
        cells = [str(i), "1" if i == 0 else "0", str(int(fr)), str(int(cmd))]
        cells += [f"{v:.8f}" for v in p[:4]] + [f"{p[4]:.8f}", f"{p[5]:.8f}", f"{p[6]:.6f}", "1"]
        lines.append("\t".join(cells))
    path = Path(path)
    path.write_text("\n".join(lines) + "\n")
    return path


def read_qgc_wpl(path: str | Path) -> list[list[float]]:
    """Rows of a QGC WPL 110 file, for checks; ValueError naming the line on a malformed file."""
    try:
        text = Path(path).read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a QGC WPL 110 file (not UTF-8 text)") from None
    if not text or not text[0].startswith("QGC WPL 110"):
        raise ValueError(f"{path}: not a QGC WPL 110 file")
    rows = []
    for n, line in enumerate(text[1:], start=2):
        if not line.strip():
            continue
        cells = line.split("\t") if "\t" in line else line.split()
        if len(cells) != 12:
            raise ValueError(f"{path}:{n}: expected 12 columns, got {len(cells)}")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise ValueError(f"{path}:{n}: non-numeric value") from None
        if not np.all(np.isfinite(rows[-1])):
            raise ValueError(f"{path}:{n}: non-finite value")
    return rows
