"""Modes and commands of the flight-dynamics vehicle."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sitl.vehicle.api import CommandRejected, FlightMode, NavItem, NavKind
from sitl.vehicle.jsbsim_vehicle import JsbsimVehicle


def run(v, seconds):
    for _ in range(int(seconds / v.dt_s)):
        v.step()


def test_that_jsbsim_loads_quietly(capfd):
    JsbsimVehicle()
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_that_a_full_flight_takes_off_flies_its_mission_and_lands():
    v = JsbsimVehicle()
    assert v.state().landed and not v.state().armed
    v.load_mission([NavItem(NavKind.TAKEOFF, 0, 0, -3), NavItem(NavKind.WAYPOINT, 4, 0, -3),
                    NavItem(NavKind.WAYPOINT, 4, 3, -3), NavItem(NavKind.LAND, 4, 3, 0)])
    v.arm()
    v.start_mission()
    reached = []
    for _ in range(90):
        run(v, 1.0)
        reached += v.pop_reached()
        if not v.state().armed:
            break
    assert reached == [0, 1, 2, 3]
    s = v.state()
    assert s.landed and not s.armed
    assert math.hypot(s.pos_ned_m[0] - 4, s.pos_ned_m[1] - 3) < 0.5
    assert "landed and disarmed" in v.pop_status_text()


def test_that_guided_takeoff_climbs_to_the_asked_height():
    v = JsbsimVehicle()
    v.arm()
    v.set_mode(FlightMode.GUIDED)
    v.takeoff(4.0)
    run(v, 15.0)
    assert -v.state().pos_ned_m[2] == pytest.approx(4.0, abs=0.2)
    with pytest.raises(CommandRejected):
        v.arm()
    with pytest.raises(CommandRejected):
        v.disarm()
    v.disarm(force=True)
    assert not v.state().armed


def test_that_commands_in_the_wrong_state_are_rejected():
    v = JsbsimVehicle()
    with pytest.raises(CommandRejected):
        v.set_mode(FlightMode.AUTO)  # no mission
    with pytest.raises(CommandRejected):
        v.takeoff(5.0)  # disarmed
    with pytest.raises(CommandRejected):
        v.start_mission()
    with pytest.raises(ValueError):
        v.takeoff(math.nan)
    with pytest.raises(KeyError):
        v.set_param("NOPE", 1.0)
    with pytest.raises(ValueError):
        v.set_param("PS_SPEED_MS", -1.0)
    v.set_param("PS_YAW_RATE_DPS", 6.0)
    assert v.ap.yaw_rate_max_rad_s == pytest.approx(math.radians(6))


def test_that_a_take_off_climbs_at_the_climb_rate_and_stops_at_its_height():
    """The climb followed a carrot a second above the vehicle and sped up to 2.3 m/s for the 1 m/s then asked; a
    9 m take-off in a 10 m building went to 10.8 m, through the roof (a served flight, `serve --altitude 9`). Now a
    reference moves at PS_CLIMB_MS (ArduPilot's 2.5 m/s), brakes before the goal, and is fed forward."""
    v = JsbsimVehicle()
    v.arm()
    v.set_mode(FlightMode.GUIDED)
    v.takeoff(9.0)
    heights = []
    for _ in range(round(20.0 / v.dt_s)):
        v.step()
        heights.append(-v.state().pos_ned_m[2])
    h = np.array(heights)
    assert h.max() < 9.0 + 0.4 and h[-1] == pytest.approx(9.0, abs=0.05)  # 0.25 m; it was 1.8 m
    mid = np.flatnonzero((h > 3.0) & (h < 6.0))  # the steady part of the climb
    rate = (h[mid[-1]] - h[mid[0]]) / ((mid[-1] - mid[0]) * v.dt_s)
    assert rate == pytest.approx(v.params["PS_CLIMB_MS"], rel=0.15)


def test_that_the_aircraft_copy_is_removed_when_the_process_exits():
    """Every `fly` and `serve` copies the F450 to add the payload's mass: the copy must not outlive the process, nor
    the copy a process pool's worker made (workers end with os._exit, which skips atexit)."""
    code = ("from concurrent.futures import ProcessPoolExecutor\n"
            "from sitl.vehicle.jsbsim_plant import _aircraft_dir\n"
            "if __name__ == '__main__':\n"
            "    with ProcessPoolExecutor(1) as pool:  # before the parent's own: a forked worker shares that one\n"
            "        print(pool.submit(_aircraft_dir).result())\n"
            "    print(_aircraft_dir())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).parents[3]).stdout.split()
    assert len(out) == 2 and out[0] != out[1]
    assert all(Path(d).name.startswith("pilescan-jsbsim-") and not Path(d).exists() for d in out)
