"""sitl.world.clearance: a true path that reaches a wall or the roof is a crash."""

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from sitl.world.clearance import closest_approach, collision, f450_reach_m

STORAGE = Storage(60.0, 40.0, 15.0)


def test_that_the_f450_reaches_its_propeller_tips_from_the_model_jsbsim_ships():
    # hubs at (+-0.1651, +-0.1651) m, 9.4-inch propellers: 0.2335 + 0.1194 m
    assert f450_reach_m() == pytest.approx(0.3529, abs=1e-3)


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
