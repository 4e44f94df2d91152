"""sitl.world.clearance: a true path that reaches a wall, the roof or the pile is a crash."""

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from sitl.world import clearance
from sitl.world.clearance import closest_approach, collision, pile_approach, pile_collision

STORAGE = Storage(60.0, 40.0, 15.0)


def test_that_the_f450_reaches_its_propeller_tips_from_the_model_jsbsim_ships():
    # hubs at (+-0.1651, +-0.1651) m, 9.4-inch propellers: 0.2335 + 0.1194 m
    assert clearance.f450_reach_m() == pytest.approx(0.3529, abs=1e-3)


@pytest.mark.parametrize(("point", "surface", "distance"), [
    ((0.8, 20.0, 12.0), "the wall x = 0", 0.8), ((59.5, 20.0, 12.0), "the wall x = L", 0.5),
    ((30.0, 0.3, 12.0), "the wall y = 0", 0.3), ((30.0, 40.2, 12.0), "the wall y = W", -0.2),
    ((30.0, 20.0, 14.9), "the roof", 0.1)])
def test_that_the_nearest_approach_names_the_surface_and_is_negative_outside(point, surface, distance):
    t = np.arange(3.0)
    path = np.array([[30.0, 20.0, 12.0], point, [30.0, 20.0, 12.0]])
    a = closest_approach(t, path, STORAGE)
    assert a.surface == surface and a.distance_m == pytest.approx(distance) and a.t_s == 1.0


def test_that_the_floor_is_no_collision_and_only_a_reach_within_the_propellers_is():
    t = np.arange(3.0)
    takeoff = np.array([[30.0, 20.0, 0.0], [30.0, 20.0, 6.0], [30.0, 20.0, 12.0]])  # from the floor
    assert collision(closest_approach(t, takeoff, STORAGE), 0.35) is None
    near = np.array([[30.0, 20.0, 12.0], [30.0, 0.36, 12.0], [30.0, 20.0, 12.0]])
    assert collision(closest_approach(t, near, STORAGE), 0.35) is None
    touching = near.copy()
    touching[1, 1] = 0.34
    why = collision(closest_approach(t, touching, STORAGE), 0.35)
    assert why is not None and "the wall y = 0" in why and "t = 1 s" in why
    assert collision(closest_approach(t, np.full((3, 3), np.nan), STORAGE), 0.35) is None


def test_that_the_f450_s_landing_gear_and_propellers_are_read_from_the_model_jsbsim_ships():
    assert clearance.f450_below_m() == pytest.approx(0.1524, abs=1e-4)  # the ground contacts 6 in under the CG
    assert clearance.f450_rotor_height_m() == pytest.approx(0.025, abs=1e-4)  # the thrusters 2.5 cm above it


def _cone(xy: np.ndarray) -> np.ndarray:
    """A cone 5 m tall at (30, 20), its sides at 45 deg (5 m radius), the floor (0) elsewhere."""
    r = np.hypot(xy[:, 0] - 30.0, xy[:, 1] - 20.0)
    return np.clip(5.0 - r, 0.0, None)


def test_that_the_pile_approach_is_the_least_room_under_the_landing_gear_or_the_propellers():
    t = np.arange(3.0)
    path = np.array([[10.0, 20.0, 8.0], [30.0, 20.0, 6.0], [50.0, 20.0, 8.0]])
    a = pile_approach(t, path, _cone, 0.35, 0.15, 0.025)
    assert a.surface == "the pile" and a.t_s == 1.0
    assert a.distance_m == pytest.approx(6.0 - 0.15 - 5.0)  # over the apex: the gear, 0.15 m below the centre
    assert pile_collision(a) is None
    # the apex 0.3 m aside, under the propellers' circle: the gear clears the 4.7 m below the centre (4.9 - 0.15), the
    # propellers (4.925 m) not the 4.95 m under the nearest of the circle's points
    beside = np.array([[30.0, 20.3, 4.9]])
    hit = pile_approach(np.zeros(1), beside, _cone, 0.35, 0.15, 0.025)
    assert hit.distance_m == pytest.approx(4.9 + 0.025 - 4.95) and "hit the pile at t = 0 s" in pile_collision(hit)


def test_that_a_path_over_the_floor_alone_has_no_pile_approach():
    t = np.arange(2.0)
    over_floor = np.array([[2.0, 2.0, 0.0], [3.0, 2.0, 0.5]])  # the take-off, nowhere near the cone
    assert pile_approach(t, over_floor, _cone, 0.35, 0.15, 0.025) is None
    assert pile_approach(t, np.full((2, 3), np.nan), _cone, 0.35, 0.15, 0.025) is None
    # standing on the cone's toe, where it is thinner than the landing gear is tall: ground, as the floor
    at_toe = np.array([[35.2, 20.0, 0.15], [35.2, 20.0, 0.15]])  # its propellers over 0-0.15 m of it
    assert pile_approach(t, at_toe, _cone, 0.35, 0.15, 0.025) is None
    assert pile_collision(None) is None


def test_that_a_dense_path_is_looked_at_every_quarter_reach_and_loses_little_room():
    """The physics' states come hundreds a second; a position every quarter reach along the path finds the least room
    within the slope times half that step (the cone's 45 deg crest: 4 cm)."""
    n = 20_000
    path = np.column_stack([np.linspace(20.0, 40.0, n), np.full(n, 20.0), np.full(n, 6.0)])
    t = np.arange(n) * 0.001
    dense = pile_approach(t, path, _cone, 0.35, 0.15, 0.025)
    every = pile_approach(t[::40], path[::40], _cone, 0.35, 0.15, 0.025)  # 2 cm apart
    assert dense.distance_m == pytest.approx(every.distance_m, abs=0.045)
    assert 6.0 - 0.15 - 5.0 <= dense.distance_m <= 6.0 - 0.15 - 5.0 + 0.045
