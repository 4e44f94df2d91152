import math
import random

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.samplelog import SampleFlags
from firmware_py.pose import (
    PoseBuffer,
    euler_from_quat,
    quat_from_euler,
    set_gps_global_origin_msg,
    slerp,
)

MS = 1_000_000
T0 = 1_000_000 * MS


def filled(n: int = 10, period_ns: int = 20 * MS, **kw) -> PoseBuffer:
    """A buffer with both streams at `period_ns`: position moving 1 m/s north, yaw turning 0.5 rad/s."""
    buf = PoseBuffer(**kw)
    for k in range(n):
        t = T0 + k * period_ns
        buf.add_position(t, (k * period_ns / 1e9, 2.0, -5.0))
        buf.add_attitude(t, 0.0, 0.0, 0.5 * k * period_ns / 1e9)
    return buf


def to_scipy(q):
    from scipy.spatial.transform import Rotation

    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w])


# ----- quaternion math --------------------------------------------------------------------------------

def test_euler_to_quaternion_and_back_matches_scipy_zyx_for_random_angles():
    pytest.importorskip("scipy", reason="scipy is the reference here; not in the payload-only install")
    from scipy.spatial.transform import Rotation

    rng = random.Random(3)
    for _ in range(200):
        roll, pitch, yaw = rng.uniform(-3.1, 3.1), rng.uniform(-1.5, 1.5), rng.uniform(-3.1, 3.1)
        q = quat_from_euler(roll, pitch, yaw)
        ref = Rotation.from_euler("ZYX", [yaw, pitch, roll])
        assert np.allclose(to_scipy(q).as_matrix(), ref.as_matrix(), atol=1e-12)
        assert euler_from_quat(q) == pytest.approx((roll, pitch, yaw), abs=1e-9)


def test_slerp_matches_scipy_for_seeded_random_rotations():
    pytest.importorskip("scipy", reason="scipy is the reference here; not in the payload-only install")
    from scipy.spatial.transform import Rotation, Slerp

    rng = np.random.default_rng(11)
    for _ in range(200):
        r = Rotation.random(2, random_state=rng)
        x, y, z, w = r.as_quat()[0]
        q0 = (w, x, y, z)
        small = Rotation.from_rotvec(rng.normal(size=3) * rng.choice([1e-4, 0.1, 1.0]))
        x, y, z, w = (small * r[0]).as_quat()
        q1 = (w, x, y, z)
        u = float(rng.uniform(0, 1))
        ref = Slerp([0.0, 1.0], Rotation.concatenate([to_scipy(q0), to_scipy(q1)]))([u])[0]
        assert (to_scipy(slerp(q0, q1, u)).inv() * ref).magnitude() < 1e-6


def test_slerp_takes_the_short_way_across_yaw_plus_minus_pi():
    q0 = quat_from_euler(0.0, 0.0, math.radians(179))
    q1 = quat_from_euler(0.0, 0.0, math.radians(-179))
    _, _, yaw = euler_from_quat(slerp(q0, q1, 0.5))
    assert abs(abs(yaw) - math.pi) < 1e-9  # through 180 deg, not through 0


# ----- interpolation ----------------------------------------------------------------------------------

def test_position_is_linear_and_attitude_is_slerped_between_each_streams_own_brackets():
    buf = PoseBuffer()
    buf.add_position(T0, (0.0, 0.0, 0.0))
    buf.add_position(T0 + 20 * MS, (2.0, 0.0, -1.0))
    buf.add_attitude(T0 + 5 * MS, 0.0, 0.0, 0.0)  # its own stamps, not the position's
    buf.add_attitude(T0 + 25 * MS, 0.0, 0.0, 1.0)
    pose = buf.pose_at(T0 + 15 * MS)
    assert pose.usable and pose.flags == SampleFlags.NONE
    assert pose.pos_ned_m == pytest.approx((1.5, 0.0, -0.75))
    assert pose.yaw_rad == pytest.approx(0.5, abs=1e-12)
    assert pose.age_s == pytest.approx(0.015)  # farthest bracket sample: the position at +0 ms


def test_an_exact_stamp_returns_that_sample():
    buf = filled()
    pose = buf.pose_at(T0 + 60 * MS)
    assert pose.pos_ned_m == pytest.approx((0.06, 2.0, -5.0))
    assert pose.yaw_rad == pytest.approx(0.03)


def test_samples_arriving_out_of_order_are_used_in_time_order():
    buf = PoseBuffer()
    for k in (0, 3, 1, 4, 2):  # receive order is not time order (UDP, retries)
        buf.add_position(T0 + k * 20 * MS, (float(k), 0.0, 0.0))
        buf.add_attitude(T0 + k * 20 * MS, 0.0, 0.0, 0.1 * k)
    pose = buf.pose_at(T0 + 30 * MS)
    assert pose.pos_ned_m[0] == pytest.approx(1.5)
    assert pose.yaw_rad == pytest.approx(0.15)
    assert buf.stats["out_of_order"] == 4


def test_a_repeated_stamp_keeps_the_newer_copy():
    buf = filled(3)
    buf.add_position(T0 + 20 * MS, (9.0, 9.0, 9.0))
    assert buf.pose_at(T0 + 20 * MS).pos_ned_m == (9.0, 9.0, 9.0)
    assert buf.stats["duplicates"] == 1


def test_within_the_allowance_past_the_newest_sample_motion_is_extrapolated():
    buf = filled(10)
    newest = T0 + 9 * 20 * MS
    pose = buf.pose_at(newest + 25 * MS)
    assert pose.usable
    assert pose.pos_ned_m[0] == pytest.approx(0.18 + 0.025)
    assert pose.yaw_rad == pytest.approx(0.5 * 0.205, abs=1e-12)


def test_beyond_the_extrapolation_allowance_the_pose_is_stale_and_carries_no_values():
    buf = filled(10)
    pose = buf.pose_at(T0 + 9 * 20 * MS + 26 * MS)
    assert pose.stale and not pose.missing and not pose.usable
    assert pose.flags == SampleFlags.STALE_POSE
    assert all(math.isnan(v) for v in (*pose.pos_ned_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad))


def test_a_gap_longer_than_max_age_makes_the_poses_inside_it_stale():
    buf = PoseBuffer(max_age_ns=100 * MS)
    for t in (0, 20, 40, 300, 320):  # position lost between 40 and 300 ms
        buf.add_position(T0 + t * MS, (t / 1000, 0.0, 0.0))
    for t in range(0, 340, 20):
        buf.add_attitude(T0 + t * MS, 0.0, 0.0, 0.0)
    assert buf.pose_at(T0 + 130 * MS).stale  # 90 ms to one bracket, 170 ms to the other
    assert buf.pose_at(T0 + 30 * MS).usable
    assert buf.pose_at(T0 + 310 * MS).usable
    assert buf.pose_at(T0 + 130 * MS).age_s == pytest.approx(0.170)


def test_before_the_oldest_sample_the_pose_is_stale_never_extrapolated_backwards():
    buf = filled(5)
    assert buf.pose_at(T0 - 1).stale


def test_a_single_sample_serves_only_its_own_time_and_the_allowance_after_it():
    buf = PoseBuffer()
    buf.add_position(T0, (1.0, 2.0, 3.0))
    buf.add_attitude(T0, 0.1, 0.2, 0.3)
    assert buf.pose_at(T0 + 10 * MS).pos_ned_m == (1.0, 2.0, 3.0)
    assert buf.pose_at(T0 + 26 * MS).stale


def test_without_local_position_the_pose_is_missing_and_the_status_explains_the_ekf_origin():
    buf = PoseBuffer()
    buf.add_attitude(T0, 0.0, 0.0, 0.0)
    pose = buf.pose_at(T0)
    assert pose.missing and pose.flags == SampleFlags.NO_POSE and pose.age_s == math.inf
    assert "SET_GPS_GLOBAL_ORIGIN" in buf.status() and "EKF" in buf.status()


def test_without_attitude_the_pose_is_missing_and_the_status_says_so():
    buf = PoseBuffer()
    buf.add_position(T0, (0.0, 0.0, 0.0))
    assert buf.pose_at(T0).missing
    assert "ATTITUDE" in buf.status()


def test_cleared_buffer_is_missing_and_says_why():
    buf = filled(5)
    buf.clear()
    assert buf.pose_at(T0 + 40 * MS).missing
    assert "cleared" in buf.status()


def test_non_finite_samples_are_refused_and_counted():
    buf = filled(3)
    assert not buf.add_position(T0 + 70 * MS, (math.nan, 0.0, 0.0))
    assert not buf.add_attitude(T0 + 70 * MS, 0.0, math.inf, 0.0)
    assert buf.stats["rejected_nonfinite"] == 2
    assert buf.pose_at(T0 + 40 * MS).usable


def test_capacity_keeps_the_newest_samples():
    buf = filled(20, capacity=8)
    assert len(buf) == 8
    assert buf.pose_at(T0 + 11 * 20 * MS).stale  # dropped
    assert buf.pose_at(T0 + 13 * 20 * MS).usable


def test_newest_is_the_older_of_the_two_streams_newest_samples():
    buf = filled(3)
    buf.add_attitude(T0 + 100 * MS, 0.0, 0.0, 0.0)
    assert buf.newest_ns == T0 + 40 * MS


@pytest.mark.parametrize("kw,name", [
    ({"capacity": 1}, "capacity"), ({"max_age_ns": 0}, "max_age_ns"),
    ({"max_age_ns": 10 * MS, "extrapolate_ns": 20 * MS}, "extrapolate_ns"), ({"extrapolate_ns": -1}, "extrapolate_ns"),
])
def test_bad_buffer_configuration_is_refused_naming_the_value(kw, name):
    with pytest.raises(ValueError, match=name):
        PoseBuffer(**kw)


# ----- SET_GPS_GLOBAL_ORIGIN --------------------------------------------------------------------------

def test_set_gps_global_origin_msg_scales_to_mavlink_units_and_packs():
    msg = set_gps_global_origin_msg(53.4668, -2.2339, 50.25)
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    back = mavlink.MAVLink(None).decode(bytearray(msg.pack(mav)))
    assert back.get_type() == "SET_GPS_GLOBAL_ORIGIN"
    assert (back.target_system, back.latitude, back.longitude, back.altitude) == (1, 534668000, -22339000, 50250)


@pytest.mark.parametrize("args,name", [
    ((91.0, 0.0, 0.0), "latitude"), ((math.nan, 0.0, 0.0), "latitude"), ((0.0, 181.0, 0.0), "longitude"),
    ((0.0, 0.0, math.inf), "altitude"),
])
def test_set_gps_global_origin_refuses_impossible_coordinates(args, name):
    with pytest.raises(ValueError, match=name):
        set_gps_global_origin_msg(*args)
