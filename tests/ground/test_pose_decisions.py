"""Whether a fitted pose correction is applied (`ground.pose_decisions`): the structure explained, a wall or the floor
brought on, the pile seen at different times brought together, a registration still a drift."""


import numpy as np
import pytest

from ground.pose_decisions import (
    chi2_quantile,
    crossings_brought_together,
    draw_sd_m,
    explains_more,
    floor_brought_on,
    floor_is_level,
    is_drift,
    level_clear,
    plane_brought_on,
)
from ground.pose_knots import PLANE_NAMES, Component, PoseCorrectionOptions, prior_sigmas


def test_that_a_registration_whose_steps_the_drift_model_does_not_allow_is_no_drift():
    step = prior_sigmas(3.0, 1.0, PoseCorrectionOptions())
    xy = (Component.X.value, Component.Y.value)
    walls = np.zeros((30, 4))
    smooth = walls.copy()
    smooth[:, 1] = 0.5 * step[1] * np.arange(30)  # half a sigma a knot: a drift
    assert is_drift(smooth, walls, step, xy)
    runaway = smooth.copy()
    runaway[27:, 1] += 25 * step[1]  # the end runs away along the track (as measured on a flown ridge)
    assert not is_drift(runaway, walls, step, xy)
    assert is_drift(runaway, runaway, step, xy)  # no worse than the walls' fit: not the registration's doing
    rough = walls.copy()
    rough[::2, 0] = 2 * step[0]  # a walls' fit with two-sigma steps of its own noise at every knot
    assert is_drift(rough + smooth, rough, step, xy)  # a drift on top of it is allowed
    assert not is_drift(rough + runaway, rough, step, xy)
    few = smooth.copy()
    few[10, 0] += 4 * step[0]  # one knot off by four sigmas among 58 steps: still a drift at the 99 % level
    assert is_drift(few, walls, step, xy)


def test_that_a_plane_counts_when_its_points_are_brought_onto_it_not_when_they_stay_off_it():
    rng = np.random.default_rng(0)
    noise = 0.01
    floor, x0 = PLANE_NAMES.index("floor"), PLANE_NAMES.index("x0")
    on_floor = rng.normal(0.0, noise, 900)
    # a wall's points 0.3 m off before and on it after: brought onto it
    plane = np.r_[np.full(900, floor), np.full(100, x0)]
    before = np.r_[on_floor, 0.3 + rng.normal(0.0, noise, 100)]
    after = np.r_[on_floor, rng.normal(0.0, noise, 100)]
    assert plane_brought_on(before, after, plane, noise) == "x0"
    # a pile's toe on the floor's plane, 22 cm off before and 11 cm after: closer, but not onto it
    toe = np.r_[on_floor, 0.22 + rng.normal(0.0, noise, 100)]
    toe_after = np.r_[on_floor, 0.11 + rng.normal(0.0, noise, 100)]
    assert plane_brought_on(toe, toe_after, np.r_[np.full(900, floor), np.full(100, x0)], noise) is None
    # a far wall scattering more than the data's noise says, 16 -> 13.5 cm against 6 cm (within MAX_MISFIT noise
    # levels after, and closer by more than the noise): the correction explains less of its mean square than is
    # left, so it has not brought the wall onto its plane
    far = np.r_[on_floor, rng.normal(0.0, 0.16, 100)]
    far_after = np.r_[on_floor, 0.135 / 0.16 * far[900:]]
    assert plane_brought_on(far, far_after, plane, 0.06) is None
    assert plane_brought_on(far, np.r_[on_floor, 0.07 / 0.16 * far[900:]], plane, 0.06) == "x0"  # most of it: yes
    # the floor's own points do not count: they may be a pile's flat top that a height correction pulled down
    # onto the floor's plane (the height has its own tests, and the floor sees no horizontal drift)
    assert plane_brought_on(before, after, np.r_[np.full(900, x0), np.full(100, floor)], noise) is None
    # unchanged: nothing
    assert plane_brought_on(after, after, plane, noise) is None
    # too few points on a plane to say
    assert plane_brought_on(before[:905], after[:905], plane[:905], noise) is None


def _floor_sightings(level_m: float, sd_m: float, seed: int, n: int = 50,
                     each: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """A floor's points at level_m with sd_m of noise a point, n sightings (a knot interval's cell) of `each`."""
    return np.random.default_rng(seed).normal(level_m, sd_m, n * each), np.repeat(np.arange(n), each)


def test_that_the_floor_counts_when_a_height_brings_it_up_onto_z0_and_down_only_when_level_and_within_the_drift():
    noise = 0.003
    low, key = _floor_sightings(-0.2, noise, seed=0)
    on, _ = _floor_sightings(0.0, 0.013, seed=1)
    spread = np.random.default_rng(4).uniform(0.0, 6.0, 50)[key]  # each sighting's distance from the nearest wall
    assert floor_brought_on(low, on, key, noise)  # 0.2 m below, brought to within 1.3 cm: up onto it, always
    # above z = 0 it may be material covering the floor: down only within the logged reference's drift, and level
    assert not floor_brought_on(-low, on, key, noise)
    assert not floor_brought_on(-low, on, key, noise, most_down_m=0.5)  # nothing says it is level
    assert not floor_brought_on(-low, on, key, noise, most_down_m=0.1, wall_distance_m=spread)
    assert floor_brought_on(-low, on, key, noise, most_down_m=0.5, wall_distance_m=spread)
    # a pile's flank rising from the walls, 0.2 m up on average: not a floor to take down
    ramp = 0.2 + 0.1 * (spread - 3.0) + np.random.default_rng(5).normal(0.0, noise, len(key))
    assert not floor_brought_on(ramp, ramp - 0.2, key, noise, most_down_m=0.5, wall_distance_m=spread)
    assert not floor_brought_on(low, low + 0.1, key, noise)  # half way: more is left than was explained
    assert not floor_brought_on(low, low, key, noise)  # unchanged
    assert not floor_brought_on(low[:5], on[:5], key[:5], noise)  # too few points to say
    assert not floor_brought_on(low[:90], on[:90], key[:90], noise)  # ... or too few sightings of them
    # within the noise: a floor 1 cm low under 20 cm of pointing noise is not brought up by anything that matters
    wide, _ = _floor_sightings(-0.01, 0.2, seed=2)
    assert not floor_brought_on(wide, wide + 0.01, key, 0.2)


# The 41 sightings of the floor an error-free flight took down onto z = 0 (the paper's pile 1, P_traj 30 %, Appendix A's
# noise, servo phase 0; the volume then read 1.3 pp low): their heights (m), what the height correction moved each by,
# and their distances (m) from the material beside the floor and from the nearest wall, nearest the material first.
TOE_FLOOR_M = [0.56, 0.47, 0.11, 0.14, 0.26, 0.28, 0.22, 0.25, 0.09, 0.15, -0.05, 0.14, 0.24, 0.02, -0.15, 0.13, 0.13,
               0.36, 0.33, 0.11, 0.02, 0.0, -0.0, -0.0, 0.18, 0.28, 0.01, -0.17, -0.09, 0.03, -0.08, 0.14, 0.13, 0.07,
               0.05, -0.12, -0.15, 0.06, 0.13, -0.0, -0.06]


TOE_MOVED_M = [-0.033, -0.07, -0.064, -0.068, -0.111, -0.091, -0.112, -0.065, -0.069, -0.088, -0.087, -0.055, -0.068,
               -0.051, -0.075, -0.069, -0.091, -0.06, -0.068, -0.087, -0.087, -0.079, -0.061, -0.112, -0.065, -0.104,
               -0.051, -0.075, -0.112, -0.065, -0.056, -0.114, -0.061, -0.052, -0.079, -0.056, -0.084, -0.056, -0.115,
               -0.063, -0.079]


TOE_MATERIAL_M = [0.0, 0.2, 0.3, 0.5, 0.5, 0.6, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.7, 0.8, 0.9, 0.9, 0.9, 0.9,
                  0.9, 0.9, 1.0, 1.0, 1.0, 1.0, 1.1, 1.1, 1.1, 1.1, 1.1, 1.2, 1.2, 1.2, 1.3, 1.4, 1.4, 1.4, 1.5, 1.7,
                  1.8]


TOE_WALL_M = [3.3, 2.1, 2.5, 3.0, 2.6, 2.8, 4.6, 3.1, 3.5, 3.5, 2.4, 2.2, 4.1, 3.6, 5.0, 4.9, 1.9, 1.6, 5.0, 4.5, 3.4,
              5.6, 3.0, 3.3, 2.3, 3.0, 5.0, 4.0, 2.5, 6.0, 3.3, 4.5, 5.1, 6.0, 3.4, 5.7, 3.1, 4.6, 3.3, 4.2, 4.5]


def test_that_a_floor_above_z0_is_taken_down_only_when_its_sightings_far_from_the_material_are_up_too():
    """Under a degree of pointing a floor patch beside a pile's toe reads high nearest the toe (its hits placed on the
    floor beside it: 0.16 m up in the nearer half of these sightings, 0.02 m in the farther); a height offset lifts
    the far sightings as much as the near."""
    each = 8
    key = np.repeat(np.arange(len(TOE_FLOOR_M)), each)
    z = np.repeat(TOE_FLOOR_M, each)
    moved = np.repeat(TOE_MOVED_M, each)
    common = dict(most_down_m=0.47, wall_distance_m=np.repeat(TOE_WALL_M, each))
    material = np.repeat(TOE_MATERIAL_M, each)
    noise = 0.127
    assert floor_brought_on(z, z + moved, key, noise, **common)  # as it was: taken down
    assert not floor_brought_on(z, z + moved, key, noise, material_distance_m=material, **common)
    # the same floor, its near half's toe taken out, lifted 0.2 m as a whole: the far half is up as much, and it comes
    # down (a lever arm's z 0.2 m too short)
    lifted = z - np.where(material < np.median(TOE_MATERIAL_M), 0.14, 0.0) + 0.2
    assert floor_brought_on(lifted, lifted - 0.2, key, noise, material_distance_m=material, **common)


def test_that_a_floor_seen_in_one_moment_is_not_taken_down_on_the_pose_draws_it_shares():
    """A pose message's position error moves the points it places alike: a floor seen within a few messages is off
    by their draws, which its sightings' own scatter does not show; an offset of the flight shows early and late."""
    from ground.uncertainty import SharedDraws
    noise = 0.03
    rng = np.random.default_rng(8)
    key = np.repeat(np.arange(20), 10)
    spread = rng.uniform(0.0, 6.0, 20)[key]
    z = 0.1 + rng.normal(0.0, noise, len(key))
    common = dict(most_down_m=0.5, wall_distance_m=spread)
    one_moment = SharedDraws(0.113, np.repeat(np.arange(4), 50))  # 200 points in 4 messages
    all_flight = SharedDraws(0.113, np.arange(len(key)) * 37)  # each point its own message, spread over the flight
    assert floor_brought_on(z, z - 0.1, key, noise, **common)  # without pose draws
    assert not floor_brought_on(z, z - 0.1, key, noise, draws=one_moment, **common)
    assert floor_brought_on(z, z - 0.1, key, noise, draws=all_flight, **common)
    # below z = 0, where nothing but a height error puts a floor, it is brought up as before (asked of the level, the
    # same test refused four real drifts of 2-3 cm under noise, and no error-free flight was ever taken up)
    assert floor_brought_on(-z, -z + 0.1, key, noise, draws=one_moment)


def test_that_a_floor_within_half_the_range_quantum_of_z0_is_not_brought_onto_it():
    """Ranges rounded to 1 cm: a floor seen by a few sweeps at nearly one range shares its rounding error, 2.8 mm
    below z = 0 on a noise-free error-free flight of the paper's pile 1, which no count of sightings averages out."""
    low, key = _floor_sightings(-0.0028, 0.0005, seed=10)
    on, _ = _floor_sightings(0.0, 0.0005, seed=11)
    assert floor_brought_on(low, on, key, 0.0005)  # a millimetre-true sensor: 2.8 mm is an offset
    assert not floor_brought_on(low, on, key, 0.0005, quantum_m=0.01)
    assert floor_brought_on(low - 0.01, on, key, 0.0005, quantum_m=0.01)  # 1.3 cm below: beyond what rounding does


def test_that_a_level_is_clear_of_z0_by_its_own_scatter_and_the_pose_draws_it_shares():
    from ground.uncertainty import SharedDraws
    h = np.random.default_rng(9).normal(0.1, 0.05, 100)
    assert level_clear(h, 0.0, 3.0)
    assert not level_clear(h, 0.04, 3.0)  # 0.1 m against 3 x 0.04 m of shared draws
    assert not level_clear(np.zeros(0), 0.0, 3.0)
    draws = SharedDraws(0.12, np.array([0, 0, 1, 1, 2, 3]))
    assert draw_sd_m(draws, np.ones(6, dtype=bool)) == pytest.approx(0.06)  # four messages
    assert draw_sd_m(draws, np.array([True, True, False, False, False, False])) == pytest.approx(0.12)
    assert draw_sd_m(None, np.ones(6, dtype=bool)) == 0.0


@pytest.mark.parametrize("trend_m_per_m", [0.1, -0.1])
def test_that_a_floor_is_level_when_its_sightings_do_not_trend_with_the_distance_from_the_walls(trend_m_per_m):
    """A pile's flank rises away from a wall it meets at zero height, or towards one it is heaped against; a floor is
    level whatever its sightings' noise."""
    rng = np.random.default_rng(6)
    distance = rng.uniform(0.0, 6.0, 60)
    noise = 0.05
    assert floor_is_level(rng.normal(0.0, noise, 60), distance, noise)
    assert not floor_is_level(trend_m_per_m * distance + rng.normal(0.0, noise, 60), distance, noise)
    # a trend as sure but within a few of a point's noise over the distances seen is not a pile's flank (0.1 mm/m on
    # a noise-free floor, where the drift model's misfit leaves millimetres)
    assert floor_is_level(1e-4 * distance + rng.normal(0.0, 1e-5, 60), distance, 0.003)
    assert not floor_is_level(np.zeros(5), distance[:5], noise)  # too few to say


def test_that_the_floor_is_judged_on_its_sightings_so_a_points_noise_does_not_hide_its_offset():
    """5 cm below z = 0 under 0.12 m of noise a point (a degree of pointing at 7 m): the points' RMS comes down by
    less than a point's noise (0.13 -> 0.12 m, which a test on the points refused), yet each of 50 sightings of 16
    points knows the level to 4 cm."""
    below, key = _floor_sightings(-0.05, 0.12, seed=3, each=16)
    assert floor_brought_on(below, below + 0.05, key, 0.12)
    # the same points, their sightings' medians on z = 0 already: nothing to bring
    on, _ = _floor_sightings(0.0, 0.12, seed=3, each=16)
    assert not floor_brought_on(on, on + 0.05, key, 0.12)


def test_that_a_height_matters_to_the_pile_seen_at_different_times_when_it_brings_the_sightings_together():
    assert crossings_brought_together(0.073, 0.010, 0.003)  # a walk of decimetres taken out to a centimetre
    assert not crossings_brought_together(0.073, 0.060, 0.003)  # more is left than was explained
    assert not crossings_brought_together(0.004, 0.003, 0.003)  # within the noise
    assert not crossings_brought_together(0.010, 0.010, 0.003)  # unchanged: a height off by a constant is the floor's


def test_that_the_chi_square_quantile_is_scipy_stats_own():
    from scipy.stats import chi2  # here only: the ground station does not import scipy.stats
    for level, dof in [(0.99, 1), (0.99, 60), (0.95, 132), (0.5, 7)]:
        assert chi2_quantile(level, dof) == float(chi2.ppf(level, dof))


def test_that_a_mount_explains_more_when_its_two_misfits_in_their_own_noise_add_to_less():
    # a sweep yawed off square: the walls see nothing of it, the pile seen on opposite passes disagrees by 7 cm, and
    # the mount takes that to 5 mm for 0.3 mm more on the walls (noise 2.9 mm and 3 mm): explained
    assert explains_more((0.0048, 0.0051), 0.0029, (0.070, 0.0046), 0.003)
    # a mount that buys a millimetre on the crossings with two on the walls explains nothing more
    assert not explains_more((0.0102, 0.0119), 0.0029, (0.0068, 0.0059), 0.0029)
    # the same figures both ways: not more
    assert not explains_more((0.005, 0.005), 0.003, (0.005, 0.005), 0.003)
    # no noise to weigh them in: not more (rather than a division by zero)
    assert not explains_more((0.01, 0.001), 0.0, (0.01, 0.001), 0.003)
