import math

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from sitl.missions.rectangle import Mission


def test_that_corners_follow_eqs_17_and_18():
    m = Mission(p_traj=0.2)
    assert np.allclose(m.corners_w(), [[12, 8], [48, 8], [48, 32], [12, 32]])
    wp = m.waypoints_w()
    assert np.allclose(wp[0], wp[-1]) and len(wp) == 5
    assert m.path_length_m() == pytest.approx(2 * (36 + 24))


def test_that_two_step_corners_cut_10_percent_of_w_before_and_after_each_turn():
    m = Mission(p_traj=0.2, turn="two-step")
    wp = m.waypoints_w()
    assert len(wp) == 2 * 4 + 1 and np.allclose(wp[0], wp[-1])
    assert np.allclose(wp[0], [12, 12]) and np.allclose(wp[1], [16, 8]) and np.allclose(wp[2], [44, 8])
    headings = np.degrees(np.arctan2(*np.diff(wp, axis=0)[:, ::-1].T))
    assert np.allclose(np.diff(np.r_[headings[-1], headings]) % 360, 45)
    # Each corner is cut by a 4 m x 4 m triangle: 4 x (8 - 4 sqrt 2) shorter.
    assert m.path_length_m() == pytest.approx(120 - 4 * (8 - 4 * math.sqrt(2)))


@pytest.mark.parametrize("kwargs,match", [
    (dict(p_traj=0.0), "P_traj"), (dict(p_traj=0.5), "P_traj"), (dict(p_traj=-0.1), "P_traj"),
    (dict(p_traj=math.nan), "P_traj"), (dict(turn="three-step"), "turn"), (dict(speed_m_s=0), "speed"),
    (dict(altitude_m=15.0), "altitude"), (dict(altitude_m=math.nan), "altitude"),
    (dict(yaw_rate_max_rad_s=0.0), "yaw"), (dict(storage=Storage(60, 40, 10)), "altitude"),
    (dict(storage=Storage(6, 4, 15), p_traj=0.05), "wall"),
    (dict(storage=Storage(60, 40, 15), p_traj=0.45, turn="two-step"), "cut"),
    (dict(p_traj=0.4999999), "legs are 0.00 m"), (dict(p_traj=0.49), "at most 48.8 %"),
])
def test_that_missions_that_do_not_fit_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        Mission(**kwargs)


def test_that_the_largest_p_traj_the_refusal_names_is_flown():
    from sitl.missions.rectangle import MIN_LEG_M
    most = 0.5 * (1 - MIN_LEG_M / 40.0)
    assert min(np.ptp(Mission(p_traj=most).corners_w(), axis=0)) == pytest.approx(MIN_LEG_M)


def test_that_mission_ids_are_stable_and_distinct():
    assert Mission(p_traj=0.1).mission_id == Mission(p_traj=0.1).mission_id
    assert Mission(p_traj=0.1).mission_id != Mission(p_traj=0.15).mission_id
    m = Mission(p_traj=0.1, turn="two-step")
    assert Mission.from_dict(m.to_dict()) == Mission(p_traj=0.1, turn="two-step", two_step_cut_m=4.0)
