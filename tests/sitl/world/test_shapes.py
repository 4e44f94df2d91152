"""sitl.world.shapes: every procedural pile has the volume its formula says, fits its building and is what its
name promises (leaning on walls, bare corners, separate heaps, a closed undercut body)."""

import math

import numpy as np
import pytest
from scipy import ndimage

from firmware_py.core.storage import Storage
from sitl.world.raycast import GEOM_PILE, World
from sitl.world.shapes import Family, Mesa, make_shape, outside
from sitl.world.stockpile import Stockpile, heightfield_mesh, volume_under_mesh

BUILDINGS = [(Storage(60, 40, 15), 10.0), (Storage(40, 25, 12), 5.0), (Storage(80, 30, 15), 8.0)]
SEEDS = (0, 1, 2, 3)


def _all():
    for storage, top in BUILDINGS:
        for fam in Family:
            for seed in SEEDS:
                yield storage, top, fam, seed


@pytest.mark.parametrize("family", list(Family))
def test_that_every_shape_has_the_volume_of_its_mesh_and_of_its_formula(family):
    for storage, top in BUILDINGS:
        for seed in SEEDS:
            s = make_shape(family, storage, top, seed)
            assert s.volume_m3 == pytest.approx(volume_under_mesh(s.pile.mesh), rel=1e-12)
            if s.analytic_volume_m3 is None:
                assert family is Family.IRREGULAR  # only the paper's generator has no closed formula
                assert s.volume_m3 > 0
            elif s.analytic_volume_m3 == 0:
                assert s.volume_m3 == 0
            else:  # a 0.25 m height field cuts the kinks; the icosphere is 0.22 % inside its sphere
                assert s.volume_m3 == pytest.approx(s.analytic_volume_m3, rel=3e-3), s.pile.source


@pytest.mark.parametrize("family", [f for f in Family if f is not Family.EMPTY])
def test_that_every_shape_lies_inside_its_building_on_the_floor_and_under_its_top(family):
    for storage, top in BUILDINGS:
        for seed in SEEDS:
            s = make_shape(family, storage, top, seed)
            lo, hi = s.pile.mesh.bounds
            assert lo[0] >= -1e-9 and lo[1] >= -1e-9 and lo[2] >= -1e-9  # a height field may cover all the floor
            if s.pile.mesh.is_watertight:  # a closed body rests on the floor
                assert abs(lo[2]) < 1e-9
            assert hi[0] <= storage.length_m + 1e-9 and hi[1] <= storage.width_m + 1e-9
            assert 0 < hi[2] <= top + 1e-9
            assert outside(s.pile, storage, top) is None


def test_that_shapes_are_seeded():
    a, b = make_shape("corner", Storage(), 8.0, 5), make_shape("corner", Storage(), 8.0, 5)
    c = make_shape("corner", Storage(), 8.0, 6)
    assert np.array_equal(a.pile.mesh.vertices, b.pile.mesh.vertices)
    assert not np.array_equal(a.pile.mesh.vertices, c.pile.mesh.vertices)


def test_that_the_mesa_formula_matches_a_fine_height_field_against_walls():
    storage = Storage(30, 20, 10)
    xs, ys = np.linspace(0, 30, 1201), np.linspace(0, 20, 801)
    px, py = np.meshgrid(xs, ys, indexing="ij")
    for m in (Mesa(0, 4, 0, 3, 3.0, 35.0), Mesa(10, 18, 0, 0, 3.0, 33.0), Mesa(12, 14, 8, 9, 2.0, 30.0)):
        mesh = heightfield_mesh(xs, ys, m.heights(px, py))
        assert volume_under_mesh(mesh) == pytest.approx(m.volume_m3(storage), rel=5e-4)


def test_that_a_free_slope_crossing_a_wall_is_refused_by_the_formula():
    with pytest.raises(ValueError, match="crosses a wall"):
        Mesa(2, 3, 5, 5, 5.0, 30.0).volume_m3(Storage(30, 20, 10))


def _grid_heights(shape, storage):
    v = shape.pile.mesh.vertices
    nx = len(np.unique(v[:, 0]))
    return v[:, 2].reshape(nx, -1)


def test_that_a_corner_pile_is_highest_in_a_building_corner_and_leans_on_two_walls():
    storage = Storage()
    for seed in SEEDS:
        s = make_shape("corner", storage, 8.0, seed)
        z = _grid_heights(s, storage)
        corners = [z[0, 0], z[-1, 0], z[-1, -1], z[0, -1]]
        assert max(corners) == pytest.approx(s.params["height_m"])
        assert sorted(corners)[:3] == [0.0, 0.0, 0.0]  # one corner only


def test_that_a_wall_pile_touches_one_wall_and_no_corner():
    storage = Storage()
    for seed in SEEDS:
        z = _grid_heights(make_shape("wall", storage, 8.0, seed), storage)
        touched = [z[0, :].max() > 0, z[-1, :].max() > 0, z[:, 0].max() > 0, z[:, -1].max() > 0]
        assert sum(touched) == 1
        assert z[0, 0] == z[-1, 0] == z[-1, -1] == z[0, -1] == 0.0


def test_that_a_bay_pile_stands_against_one_wall_with_vertical_ends_and_bare_building_corners():
    storage = Storage()
    for seed in SEEDS:
        s = make_shape("bay", storage, 8.0, seed)
        lo, hi = s.pile.mesh.bounds
        assert lo[0] > 0 and hi[0] < storage.length_m  # bare floor at both ends: the corners
        assert lo[1] == 0 or hi[1] == storage.width_m  # against a long wall
        ends = np.isclose(s.pile.mesh.vertices[:, 0], lo[0])
        assert s.pile.mesh.vertices[ends, 2].max() == pytest.approx(s.params["height_m"])  # a vertical end face


def test_that_separate_piles_have_bare_floor_between_them():
    storage = Storage()
    for seed in SEEDS:
        s = make_shape("separate", storage, 8.0, seed)
        _, n = ndimage.label(_grid_heights(s, storage) > 0)
        assert n == s.params["n_piles"] >= 2


def test_that_flat_piles_are_low_and_steep_piles_tall_at_the_angle_of_repose():
    for seed in SEEDS:
        f = make_shape("flat", Storage(), 10.0, seed)
        assert 0.5 <= f.pile.max_height_m <= 1.5
        s = make_shape("steep", Storage(), 10.0, seed)
        assert 38.0 <= s.params["repose_deg"] <= 40.0
        assert s.pile.max_height_m >= 0.8 * 10.0


def test_that_the_sphere_is_a_closed_body_touching_the_floor_and_the_ray_tracer_sees_its_top():
    s = make_shape("sphere", Storage(), 10.0, 0)
    mesh, r = s.pile.mesh, s.params["radius_m"]
    assert mesh.is_watertight and not s.height_field
    assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
    centre = mesh.bounds.mean(axis=0)
    world = World(Storage(), s.pile)
    down = world.cast(np.array([[centre[0], centre[1], 12.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert down.geom_id[0] == GEOM_PILE and down.points_w[0, 2] == pytest.approx(2 * r, abs=0.02)
    # beside the contact point, under the bulge: a horizontal ray at 0.1 r hits the sphere, not the wall behind
    side = world.cast(np.array([[0.5, centre[1], 0.1 * r]]), np.array([[1.0, 0.0, 0.0]]))
    assert side.geom_id[0] == GEOM_PILE and side.points_w[0, 0] > centre[0] - r


def test_that_the_empty_building_has_no_pile_and_no_volume():
    s = make_shape("empty", Storage(), 10.0, 0)
    assert s.volume_m3 == 0 and len(s.pile.mesh.faces) == 0
    world = World(Storage(), s.pile)
    hit = world.cast(np.array([[30.0, 20.0, 12.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert hit.range_m[0] == pytest.approx(12.0, abs=1e-4)


@pytest.mark.parametrize("args,match", [(("dune", Storage(), 5.0, 0), "unknown pile shape"),
                                        (("cone", Storage(), 15.0, 0), "below the"),
                                        (("cone", Storage(), math.nan, 0), "must be > 0"),
                                        (("cone", Storage(), 5.0, -1), "seed")])
def test_that_bad_shape_requests_are_one_line_errors(args, match):
    with pytest.raises(ValueError, match=match):
        make_shape(*args)


def test_that_outside_names_a_pile_that_leaves_the_building_or_tops_its_limit():
    xs, ys = np.array([0.0, 61.0]), np.array([0.0, 40.0])
    mesh = heightfield_mesh(xs, ys, np.ones((2, 2)))
    assert "outside the floor" in outside(Stockpile(mesh, 0.0, "t"), Storage(), 5.0)
    mesh = heightfield_mesh(np.array([0.0, 60.0]), ys, np.full((2, 2), 6.0))
    assert "above the 5.00 m allowed" in outside(Stockpile(mesh, 0.0, "t"), Storage(), 5.0)
