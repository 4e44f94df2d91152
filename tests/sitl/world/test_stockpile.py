import math

import numpy as np
import pytest
import trimesh

from firmware_py.core.storage import Storage
from sitl.world.stockpile import (
    PAPER_PILES,
    PileSpec,
    generate,
    heightfield_mesh,
    load_mesh,
    paper_pile,
    resolve,
    volume_under_mesh,
)
from tests.sitl.conftest import frustum_mesh, polygonal_frustum_volume


@pytest.mark.parametrize("name", ["1", "2"])
def test_that_paper_piles_are_within_2_percent_of_table_1(name):
    pile = paper_pile(name)
    target = PAPER_PILES[name]["table1_volume_m3"]
    assert abs(pile.volume_m3 - target) / target < 0.02


def test_that_pile_1_is_zero_on_the_walls_and_pile_2_is_not():
    v1 = paper_pile("1").mesh.vertices
    v2 = paper_pile("2").mesh.vertices
    on_wall = lambda v: (v[:, 0] == 0) | (v[:, 0] == 60) | (v[:, 1] == 0) | (v[:, 1] == 40)  # noqa: E731
    assert np.all(v1[on_wall(v1), 2] == 0)
    assert np.mean(v2[on_wall(v2), 2]) > 1.0


def test_that_generated_heights_stay_in_range_and_are_seeded():
    a = generate(PileSpec(seed=3), Storage())
    b = generate(PileSpec(seed=3), Storage())
    c = generate(PileSpec(seed=4), Storage())
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert not np.array_equal(a.mesh.vertices, c.mesh.vertices)
    assert a.mesh.vertices[:, 2].min() >= 0


def test_that_volume_under_a_planar_height_field_is_exact():
    xs, ys = np.linspace(0, 10, 11), np.linspace(0, 4, 9)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    z = 2.0 + 0.3 * gx - 0.1 * gy
    # integral over [0,10]x[0,4] of 2 + 0.3x - 0.1y = 80 + 60 - 8
    assert volume_under_mesh(heightfield_mesh(xs, ys, z)) == pytest.approx(132.0, rel=1e-12)


def test_that_a_closed_cone_stl_loads_with_its_exact_volume(cone_stl):
    pile = load_mesh(cone_stl, Storage())
    expected = polygonal_frustum_volume(12, 2, 6, 512)
    assert pile.volume_m3 == pytest.approx(expected, rel=1e-6)  # STL stores float32
    assert pile.volume_m3 == pytest.approx(math.pi * 6 / 3 * (144 + 24 + 4), rel=1e-3)


def test_that_an_open_height_field_loads_either_way_up(tmp_path):
    xs, ys = np.linspace(5, 15, 6), np.linspace(5, 10, 4)
    z = np.ones((6, 4)) * 2.0
    mesh = heightfield_mesh(xs, ys, z)
    for flip in (False, True):
        m = mesh.copy()
        if flip:
            m.faces = m.faces[:, ::-1]
        path = tmp_path / f"hf{flip}.obj"
        m.export(path)
        assert load_mesh(path, Storage()).volume_m3 == pytest.approx(2.0 * 10 * 5)


def test_that_a_mesh_outside_the_building_is_refused(tmp_path):
    path = tmp_path / "big.stl"
    frustum_mesh(30.0, 2.0, 6.0, (30.0, 20.0), 64).export(path)
    with pytest.raises(ValueError, match="must lie inside"):
        load_mesh(path, Storage())


def test_that_an_open_mesh_that_is_not_a_height_field_is_refused(tmp_path):
    box = trimesh.creation.box(extents=[4, 4, 4])
    box.apply_translation([10, 10, 2])
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    path = tmp_path / "open.stl"
    open_box.export(path)
    with pytest.raises(ValueError, match="neither closed nor a height field"):
        load_mesh(path, Storage())


def test_that_missing_unknown_and_garbage_piles_are_refused(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        load_mesh(tmp_path / "nope.stl", Storage())
    with pytest.raises(ValueError, match="unknown stockpile"):
        resolve("3", Storage())
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"solid x\n garbage \n")
    with pytest.raises(ValueError):
        load_mesh(bad, Storage())
