"""The indoor pose-estimate profiles: deterministic per seed, zero for none, smooth, and drifting at their
documented rates (statistics over fixed seeds: they cannot flake)."""

import math

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.storage import Storage
from sitl.sensing.pose_drift import (
    PROFILES,
    DriftParams,
    PoseDrift,
    PoseErrorProfile,
    error_stats,
    make_drift,
    pose_error_series,
    record,
    world_ground_below,
)
from sitl.world import stockpile as piles
from sitl.world.raycast import World

DT = 0.02
STATS_DT = 0.5
"""The step of the statistics tests' legs (hundreds of seeds each). Their errors do not depend on the step:
the random draws sit on the model's 0.1 s knot grid whatever the step (tested below, at 20 and 100 ms), the
scale and drift terms integrate a straight leg exactly, and the bent leg's sum is off its integral by
step / duration (0.5 %, inside the 2 % asked of it)."""


def _leg(duration_s: float, speed_m_s: float = 1.0, dt_s: float = DT) -> tuple[np.ndarray, np.ndarray]:
    """A straight leg north at 12 m: times and NED positions."""
    t = np.arange(0.0, duration_s + dt_s / 2, dt_s)
    return t, np.column_stack([speed_m_s * t, np.zeros_like(t), np.full_like(t, -12.0)])


def _only(**kw) -> DriftParams:
    """A profile with every error zero but those given."""
    base = dict(scale_sigma_rel=0.0, drift_rel=0.0, drift_tau_s=60.0, hover_rw_m_per_sqrt_s=0.0,
                yaw_bias_sigma_rad_s=0.0, yaw_rw_rad_per_sqrt_s=0.0, baro_rw_m_per_sqrt_s=0.0)
    return DriftParams(**{**base, **kw})


def _final(params: DriftParams, seeds, t, pos, ground=None) -> np.ndarray:
    out = []
    for s in seeds:
        d = PoseDrift(params, [s, 1], ground)
        for i in range(len(t)):
            e = d.update(float(t[i]), tuple(pos[i]))
        out.append(e)
    return np.array(out)


def test_that_none_is_no_error_at_all():
    t, pos = _leg(20.0)
    assert make_drift(PoseErrorProfile.NONE, 3) is None
    assert not pose_error_series(PoseErrorProfile.NONE, 3, t, pos).any()
    assert record(PoseErrorProfile.NONE, 3) is None


@pytest.mark.parametrize("profile", [PoseErrorProfile.FLOW, PoseErrorProfile.VIO])
def test_that_each_profile_repeats_with_its_seed_and_differs_with_another(profile):
    t, pos = _leg(60.0)
    a = pose_error_series(profile, 7, t, pos)
    assert np.array_equal(a, pose_error_series(profile, 7, t, pos))
    assert not np.array_equal(a, pose_error_series(profile, 8, t, pos))
    assert np.abs(a).max() > 0


@pytest.mark.parametrize("profile", [PoseErrorProfile.FLOW, PoseErrorProfile.VIO])
def test_that_the_error_at_a_time_does_not_depend_on_how_often_it_is_asked(profile):
    t, pos = _leg(30.0)
    fine = pose_error_series(profile, 2, t, pos)
    coarse = pose_error_series(profile, 2, t[::5], pos[::5])
    # the walks in time are the same draws; the motion-driven part integrates the same path in larger steps
    assert np.array_equal(fine[::5, 2:], coarse[:, 2:])
    assert np.abs(fine[::5, :2] - coarse[:, :2]).max() < 0.01


@pytest.mark.parametrize("profile", [PoseErrorProfile.FLOW, PoseErrorProfile.VIO])
def test_that_the_error_is_smooth_no_white_jumps(profile):
    t, pos = _leg(300.0)
    e = pose_error_series(profile, 11, t, pos)
    step = np.abs(np.diff(e, axis=0))
    assert step[:, :3].max() < 0.01  # m per 20 ms, at 1 m/s: far below a white-noise draw of the same sizes
    assert step[:, 3].max() < math.radians(0.01)


def test_that_the_distance_drift_grows_as_its_documented_fraction_of_the_distance():
    t, pos = _leg(100.0, dt_s=STATS_DT)
    params = _only(drift_rel=0.02, drift_tau_s=1e9)  # a direction that does not turn within the leg
    e = _final(params, range(300), t, pos)
    rms = math.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))
    assert rms == pytest.approx(0.02 * 100.0, rel=0.1)
    t, pos = _leg(50.0, dt_s=STATS_DT)
    half = _final(params, range(300), t, pos)
    assert math.sqrt(np.mean(half[:, 0] ** 2 + half[:, 1] ** 2)) == pytest.approx(rms / 2, rel=0.02)


def test_that_the_hover_walk_grows_with_the_square_root_of_time():
    t, pos = _leg(100.0, speed_m_s=0.0, dt_s=STATS_DT)
    e = _final(_only(hover_rw_m_per_sqrt_s=0.01), range(300), t, pos)
    assert np.sqrt(np.mean(e[:, 0] ** 2)) == pytest.approx(0.01 * math.sqrt(100.0), rel=0.15)


def test_that_the_heading_drifts_by_its_gyro_bias_and_bends_a_leg():
    t, pos = _leg(100.0, dt_s=STATS_DT)
    e = _final(_only(yaw_bias_sigma_rad_s=math.radians(0.01)), range(300), t, pos)
    assert np.degrees(np.sqrt(np.mean(e[:, 3] ** 2))) == pytest.approx(0.01 * 100.0, rel=0.15)
    # a heading error growing linearly to dpsi bends a 100 m leg sideways by dpsi * 100 / 2, along its sign
    assert np.allclose(e[:, 1], e[:, 3] * 100.0 / 2, rtol=0.02, atol=1e-3)
    assert np.allclose(e[:, 0], 0.0, atol=1e-9)


def test_that_the_scale_error_stretches_the_distance_flown():
    t, pos = _leg(50.0, dt_s=STATS_DT)
    e = _final(_only(scale_sigma_rel=0.02), range(300), t, pos)
    assert np.sqrt(np.mean(e[:, 0] ** 2)) == pytest.approx(0.02 * 50.0, rel=0.15)


@pytest.mark.parametrize("profile", [PoseErrorProfile.FLOW, PoseErrorProfile.VIO])
def test_that_a_profile_drifts_about_its_documented_rate_over_a_leg(profile):
    t, pos = _leg(100.0, dt_s=STATS_DT)
    p = PROFILES[profile]
    e = _final(p, range(200), t, pos)
    rms = math.sqrt(np.mean(e[:, 0] ** 2 + e[:, 1] ** 2))
    # drift, scale and the bent leg together: sqrt(drift^2 + scale^2 + (bias T / 2)^2 ...) of the 100 m
    expected = 100.0 * math.sqrt(p.drift_rel ** 2 + p.scale_sigma_rel ** 2 + (p.yaw_bias_sigma_rad_s * 100 / 2) ** 2)
    assert rms == pytest.approx(expected, rel=0.2)
    assert 0.005 * 100 < rms < 0.04 * 100  # the 1-3 % of the distance the sources report


def test_that_the_flow_altitude_jumps_over_a_pile_and_not_over_the_floor():
    t, pos = _leg(60.0)
    step_at_m = 30.0
    ground = lambda n, e, d: 5.0 if n >= step_at_m else 0.0  # noqa: E731
    e = pose_error_series(PoseErrorProfile.FLOW, 4, t, pos, ground)
    bare = pose_error_series(PoseErrorProfile.FLOW, 4, t, pos, lambda n, e, d: 0.0)
    w, tau = PROFILES[PoseErrorProfile.FLOW].rangefinder_weight, PROFILES[PoseErrorProfile.FLOW].rangefinder_tau_s
    before = t < step_at_m
    assert np.array_equal(e[before, 2], bare[before, 2])  # over the floor: the barometer's walk alone
    settled = t > step_at_m + 5 * tau
    assert np.allclose(e[settled, 2] - bare[settled, 2], w * 5.0, rtol=0.01)  # thinks it is w x 5 m lower
    k = np.searchsorted(t, step_at_m)
    assert e[k + 1, 2] - bare[k + 1, 2] < w * 5.0 * 0.1  # low-passed: no white jump
    assert np.allclose(e[:, :2], bare[:, :2]) and np.allclose(e[:, 3], bare[:, 3])
    assert not PROFILES[PoseErrorProfile.VIO].rangefinder_weight  # VIO's height is the barometer's


def test_that_the_rangefinder_sees_the_pile_below_and_the_floor_beside_it():
    storage = Storage(30, 20, 12)
    world = World(storage, piles.resolve("1", storage))
    frame = StorageFrame((0.0, 0.0, 0.0), 0.0)
    below = world_ground_below(world, frame)
    top = world.pile.max_height_m
    centre = frame.w_to_ned([15.0, 10.0, 9.0])
    corner = frame.w_to_ned([0.5, 0.5, 9.0])
    assert below(*centre) > 0.5 * top
    assert below(*corner) == pytest.approx(0.0, abs=0.05)


def test_that_error_stats_summarise_the_horizontal_vertical_and_heading_error():
    e = np.array([[3.0, 4.0, 1.0, math.radians(2.0)], [0.0, 0.0, -1.0, 0.0]])
    s = error_stats(e)
    assert s["horizontal_max_m"] == 5.0 and s["horizontal_rms_m"] == pytest.approx(math.sqrt(12.5))
    assert s["vertical_rms_m"] == 1.0 and s["heading_rms_deg"] == pytest.approx(math.sqrt(2.0))


def test_that_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="drift_rel"):
        _only(drift_rel=-0.1)
    with pytest.raises(ValueError, match="rangefinder_weight"):
        _only(rangefinder_weight=2.0)
