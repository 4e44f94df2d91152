"""tools.base_compare_campaign's meshes: the sloped floor adds exactly its slab, the scoop removes what the
two meshes' volumes say, and the simulator loads them as the truths the page uses."""

import pytest

from firmware_py.core.storage import Storage
from sitl.world.stockpile import load_mesh
from tools.base_compare_campaign import FALL_PCT, floor_rise, make_meshes, plane_integral_m3


def test_that_the_campaign_meshes_hold_the_truths_it_reports(tmp_path):
    storage = Storage()
    v = make_meshes(tmp_path, storage)
    assert v["sloped_above_floor_m3"] == pytest.approx(v["pile1_m3"], rel=1e-9)
    assert v["cones_sloped_above_floor_m3"] == pytest.approx(v["cones_m3"], rel=1e-9)
    assert 0 < v["removed_m3"] < 0.1 * v["pile1_m3"]
    assert plane_integral_m3(storage) == pytest.approx(storage.floor_area_m2 * float(floor_rise(30.0, 20.0)))
    assert float(floor_rise(60.0, 0.0)) < FALL_PCT / 100 * 60.0  # rises along 30 deg, not along x
    loaded = load_mesh(tmp_path / "pile1_sloped.stl", storage)  # the simulator accepts the sloped slab
    assert loaded.volume_m3 == pytest.approx(v["sloped_over_z0_m3"], rel=1e-6)
