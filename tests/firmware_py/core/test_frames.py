import math

import numpy as np
import pytest

from firmware_py.core.frames import (
    SQUARE,
    Boresight,
    StorageFrame,
    beam_dir_body,
    beam_dot_body,
    beam_dot_body_partials,
    beam_ray_w,
    beam_rays_w,
    points_w,
    premultiply,
    rot_body_to_ned,
)


def test_that_body_to_ned_matches_scipy_zyx_euler():
    pytest.importorskip("scipy", reason="scipy is the reference here; not in the payload-only install")
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(1)
    rpy = rng.uniform(-math.pi, math.pi, (50, 3))
    ours = rot_body_to_ned(rpy[:, 0], rpy[:, 1], rpy[:, 2])
    ref = Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix()
    assert np.allclose(ours, ref, atol=1e-12)


def test_that_premultiply_is_the_matrix_product_of_each_matrix_of_the_stack():
    rng = np.random.default_rng(2)
    r = rng.normal(size=(3, 3))
    stack = rng.normal(size=(1000, 3, 3))
    got = premultiply(r, stack)
    assert got.shape == (1000, 3, 3)
    assert np.allclose(got, np.stack([r @ m for m in stack]), rtol=0, atol=1e-14)
    assert premultiply(r, stack[:0]).shape == (0, 3, 3)


def test_that_yaw_90_points_the_nose_east():
    r = rot_body_to_ned(0.0, 0.0, math.pi / 2)
    assert np.allclose(r @ [1, 0, 0], [0, 1, 0])


def test_that_beam_sweeps_down_and_to_starboard():
    assert np.allclose(beam_dir_body(0.0), [0, 0, 1])
    assert np.allclose(beam_dir_body(math.pi / 2), [0, 1, 0])


@pytest.mark.parametrize("boresight", [Boresight(), Boresight(0.05, 0.0), Boresight(-0.03, 0.08)])
def test_that_the_beams_dot_product_is_the_directions(boresight):
    rng = np.random.default_rng(3)
    g = rng.uniform(-1.2, 1.2, 200)
    m = rng.normal(size=(200, 3)) * 15
    want = np.einsum("ij,ij->i", m, beam_dir_body(g, boresight))
    assert np.allclose(beam_dot_body(m.T, g, boresight), want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("boresight", [Boresight(), Boresight(0.05, -0.08), Boresight(-0.3, 0.2)])
def test_that_the_beams_dot_product_has_the_partials_a_central_difference_gives(boresight):
    rng = np.random.default_rng(4)
    g = rng.uniform(-1.2, 1.2, 200)
    m = rng.normal(size=(3, 200)) * 15
    h = 1e-6
    d_servo, d_tilt, d_yaw = beam_dot_body_partials(m, g, boresight)
    tilted = [Boresight(boresight.tilt_rad + s * h, boresight.sweep_yaw_rad) for s in (1, -1)]
    yawed = [Boresight(boresight.tilt_rad, boresight.sweep_yaw_rad + s * h) for s in (1, -1)]
    want = [(beam_dot_body(m, g + h, boresight) - beam_dot_body(m, g - h, boresight)) / (2 * h),
            (beam_dot_body(m, g, tilted[0]) - beam_dot_body(m, g, tilted[1])) / (2 * h),
            (beam_dot_body(m, g, yawed[0]) - beam_dot_body(m, g, yawed[1])) / (2 * h)]
    for got, ref in zip((d_servo, d_tilt, d_yaw), want, strict=True):
        assert np.allclose(got, ref, rtol=0, atol=1e-6)


@pytest.mark.parametrize("heading", [0.0, 0.7, math.pi / 2, -2.0])
def test_that_storage_frame_is_right_handed_and_round_trips(heading):
    f = StorageFrame((3.0, -4.0, 1.5), heading)
    r = f.rot_w_from_ned
    assert np.linalg.det(r) == pytest.approx(1.0)
    p = np.random.default_rng(0).normal(size=(10, 3)) * 20
    assert np.allclose(f.w_to_ned(f.ned_to_w(p)), p)
    # The W origin maps to the NED origin given, and W up is NED minus down.
    assert np.allclose(f.w_to_ned([0, 0, 0]), [3.0, -4.0, 1.5])
    assert np.allclose(f.ned_to_w([3.0, -4.0, 0.5]), [0, 0, 1.0])


def test_that_heading_90_puts_the_building_length_east_and_width_north():
    f = StorageFrame((0, 0, 0), math.pi / 2)
    assert np.allclose(f.ned_to_w([0, 1, 0]), [1, 0, 0])
    assert np.allclose(f.ned_to_w([1, 0, 0]), [0, 1, 0])
    # A vehicle flying along +x_W has NED yaw pi/2 (east).
    assert f.yaw_from_w_heading(0.0) == pytest.approx(math.pi / 2)


def test_that_points_follow_eqs_3_to_6_sample_by_sample():
    pytest.importorskip("scipy", reason="scipy is the reference here; not in the payload-only install")
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    n = 40
    pos = rng.normal(size=(n, 3)) * 10
    roll, pitch, yaw = rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-3, 3, n)
    gamma, rng_m = rng.uniform(-1.5, 1.5, n), rng.uniform(1, 30, n)
    lever = np.array([0.05, -0.02, 0.1])
    frame = StorageFrame((1.0, 2.0, 0.0), 0.4)
    got = points_w(pos, roll, pitch, yaw, gamma, rng_m, lever, frame)
    for i in range(n):
        r_nb = Rotation.from_euler("ZYX", [yaw[i], pitch[i], roll[i]]).as_matrix()
        d_b = np.array([0.0, math.sin(gamma[i]), math.cos(gamma[i])])
        p_ned = pos[i] + r_nb @ (lever + rng_m[i] * d_b)
        assert np.allclose(got[i], frame.ned_to_w(p_ned), atol=1e-9)


@pytest.mark.parametrize("boresight", [SQUARE, Boresight(math.radians(2.0), math.radians(-3.0))])
@pytest.mark.parametrize("heading", [0.0, 0.4, -2.5])
def test_that_the_one_ray_path_equals_the_vectorised_one(heading, boresight):
    rng = np.random.default_rng(11)
    n = 30
    pos = rng.normal(size=(n, 3)) * 10
    roll, pitch, yaw = rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-3, 3, n)
    gamma = rng.uniform(-1.5, 1.5, n)
    lever, frame = (0.05, -0.02, 0.1), StorageFrame((1.0, 2.0, -0.5), heading)
    o, d = beam_rays_w(pos, roll, pitch, yaw, gamma, lever, frame, boresight)
    for i in range(n):
        oi, di = beam_ray_w(pos[i], roll[i], pitch[i], yaw[i], gamma[i], lever, frame, boresight)
        assert np.allclose(oi, o[i], atol=1e-12) and np.allclose(di, d[i], atol=1e-12)


def test_that_a_bad_frame_is_refused():
    with pytest.raises(ValueError):
        StorageFrame((0, 0, math.nan), 0.0)
