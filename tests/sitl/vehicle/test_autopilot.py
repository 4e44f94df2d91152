"""The autopilot on JSBSim's F450: the tuning targets of the vehicle issue, as checks that can fail."""

import math

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from sitl.missions.rectangle import Mission
from sitl.runners.flight import fly_mission
from sitl.vehicle.api import FlightMode
from sitl.vehicle.autopilot import mix
from sitl.vehicle.jsbsim_plant import PlantConfig
from sitl.vehicle.jsbsim_vehicle import JsbsimVehicle, VehicleConfig


@pytest.fixture(scope="module")
def baseline():
    mission = Mission(p_traj=0.2)
    return mission, fly_mission(mission, StorageFrame((3.0, -2.0, 0.0), math.radians(25)))


def test_that_hover_holds_altitude():
    v = JsbsimVehicle(VehicleConfig(plant=PlantConfig(start_ned_m=(0, 0, -5), airborne=True)), armed=True,
                      mode=FlightMode.GUIDED)
    heights = []
    for _ in range(int(30 / v.dt_s)):
        v.step()
        heights.append(-v.state().pos_ned_m[2])
    settled = np.array(heights[int(10 / v.dt_s):])
    assert np.all(np.abs(settled - 5.0) < 0.05)
    n, e, _ = v.state().pos_ned_m
    assert math.hypot(n, e) < 0.1


def test_that_the_baseline_mission_reaches_every_waypoint(baseline):
    mission, flown = baseline
    assert flown.completed
    assert flown.reached == list(range(len(mission.waypoints_w()) - 1))


def test_that_altitude_stays_within_20_cm(baseline):
    _, flown = baseline
    assert np.all(np.abs(-flown.states["down_m"] - 12.0) < 0.2)


def test_that_straight_legs_are_flown_at_1_m_s(baseline):
    _, flown = baseline
    speed = np.hypot(flown.states["vn_m_s"], flown.states["ve_m_s"])
    yaw_rate = np.abs(flown.states["yawspeed_rad_s"])
    cruising = (yaw_rate < math.radians(0.5)) & (speed > 0.5)
    assert cruising.mean() > 0.5
    assert np.median(speed[cruising]) == pytest.approx(1.0, abs=0.05)
    assert np.percentile(speed[cruising], 95) < 1.05


@pytest.mark.parametrize("limit_dps", [30.0, 6.0])
def test_that_the_yaw_rate_limit_is_never_exceeded_by_more_than_10_percent(limit_dps):
    mission = Mission(p_traj=0.3, yaw_rate_max_rad_s=math.radians(limit_dps))
    flown = fly_mission(mission, StorageFrame())
    assert flown.completed
    peak = np.degrees(np.abs(flown.states["yawspeed_rad_s"]).max())
    assert peak <= 1.10 * limit_dps
    assert peak >= 0.8 * limit_dps  # the limit is actually used in the turns


@pytest.mark.parametrize("limit_dps", [30.0, 6.0, 1.0])
def test_that_corners_are_turned_without_flying_past_the_waypoint(limit_dps):
    """P_traj 5 % puts the loop 2-3 m from the walls: a vehicle that keeps moving along its old heading
    while turning slowly would leave the building."""
    mission = Mission(p_traj=0.05, yaw_rate_max_rad_s=math.radians(limit_dps))
    flown = fly_mission(mission, StorageFrame())
    assert flown.completed
    wp = mission.waypoints_w()
    x, y = flown.states["north_m"], -flown.states["east_m"]  # W from NED with the default frame
    margin = 0.5
    assert x.min() > wp[:, 0].min() - margin and x.max() < wp[:, 0].max() + margin
    assert y.min() > wp[:, 1].min() - margin and y.max() < wp[:, 1].max() + margin


def test_that_energy_grows_when_flying_slower_and_carrying_more():
    base = fly_mission(Mission(p_traj=0.3), StorageFrame())
    slow = fly_mission(Mission(p_traj=0.3, speed_m_s=0.5), StorageFrame())
    heavy = fly_mission(Mission(p_traj=0.3), StorageFrame(), payload_kg=0.830)
    assert slow.energy_j > 1.3 * base.energy_j
    assert heavy.energy_j > 1.1 * base.energy_j


def test_that_the_mixer_maps_commands_to_the_right_motors():
    fr, al, fl, ar = mix(0.5, 0.1, 0.0, 0.0)  # roll right: left motors up
    assert fl > fr and al > ar
    fr, al, fl, ar = mix(0.5, 0.0, 0.1, 0.0)  # nose up: front motors up
    assert fr > ar and fl > al
    assert all(0 <= m <= 1 for m in mix(0.99, 0.5, 0.5, 0.5))
