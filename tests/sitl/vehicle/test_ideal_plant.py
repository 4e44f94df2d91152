import math

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from sitl.missions.rectangle import Mission
from sitl.vehicle.ideal_plant import IdealPlant, wrap_pi

FRAMES = [StorageFrame(), StorageFrame((5.0, -3.0, 0.2), math.radians(37))]


@pytest.mark.parametrize("frame", FRAMES)
@pytest.mark.parametrize("turn", ["one-step", "two-step"])
def test_that_the_ideal_vehicle_flies_the_waypoints_at_speed_and_within_the_yaw_limit(frame, turn):
    m = Mission(p_traj=0.15, turn=turn, speed_m_s=1.3, yaw_rate_max_rad_s=math.radians(20))
    plant = IdealPlant(m, frame)
    t = plant.sample_times(100.0)
    s = plant.states(t)
    p_w = frame.ned_to_w(s.pos_ned_m)
    wp = m.waypoints_w()
    assert np.allclose(p_w[0, :2], wp[0]) and np.allclose(p_w[-1, :2], wp[-1], atol=0.02)
    assert np.allclose(p_w[:, 2], m.altitude_m)
    # every waypoint is visited
    for w in wp:
        assert np.min(np.linalg.norm(p_w[:, :2] - w, axis=1)) < 1e-6 + 1.3 / 100
    dt = np.diff(t)
    speed = np.linalg.norm(np.diff(p_w, axis=0), axis=1) / dt
    assert np.max(speed) <= 1.3 + 1e-9
    assert np.median(speed[speed > 0.01]) == pytest.approx(1.3, rel=1e-6)
    yaw_rate = np.abs(wrap_pi(np.diff(s.yaw_rad))) / dt
    assert np.max(yaw_rate) <= math.radians(20) * (1 + 1e-9)
    # One turn on every waypoint of the closed loop: 360 deg of turning in all.
    expected = m.path_length_m() / 1.3 + 2 * math.pi / math.radians(20)
    assert plant.duration_s == pytest.approx(expected)


@pytest.mark.parametrize("frame", FRAMES)
def test_that_the_nose_points_along_the_leg(frame):
    m = Mission(p_traj=0.1)
    plant = IdealPlant(m, frame)
    s = plant.states(np.array([plant.duration_s / 10]))  # on the first leg: +x in W
    assert s.yaw_rad[0] == pytest.approx(wrap_pi(frame.heading_rad))
    r = frame.rot_w_from_ned
    nose_ned = np.array([math.cos(s.yaw_rad[0]), math.sin(s.yaw_rad[0]), 0.0])
    assert np.allclose(r @ nose_ned, [1, 0, 0], atol=1e-12)


def test_that_the_flight_starts_with_the_turn_onto_the_first_leg():
    m = Mission(p_traj=0.1, yaw_rate_max_rad_s=math.radians(30))
    plant = IdealPlant(m, StorageFrame())
    s = plant.states(np.array([0.0, 1.5, 3.0]))
    # Arrives along the closing leg (heading -y_W, NED yaw +90 deg) and turns to +x_W (yaw 0) in 3 s.
    assert np.allclose(s.yaw_rad, [math.pi / 2, math.pi / 4, 0.0])
    assert np.allclose(s.pos_ned_m[:, :2], s.pos_ned_m[0, :2])
