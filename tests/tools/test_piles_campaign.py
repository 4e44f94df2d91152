"""The three-pile scene: separate piles whose mesh truths add up to the scene's, match their closed forms, and
a configuration the report reads that names each pile by a point inside it."""

from __future__ import annotations

import json

import pytest

from firmware_py.core.config_file import load_config
from tools.piles_campaign import BUILDING, SCENE, write_scene


def test_that_the_scene_is_three_piles_whose_truths_add_up(tmp_path):
    doc = write_scene(tmp_path)
    assert json.loads((tmp_path / "truths.json").read_text()) == doc
    assert sum(doc["piles_m3"].values()) == pytest.approx(doc["total_m3"], rel=1e-9)
    for name, v in doc["piles_m3"].items():
        assert v == pytest.approx(doc["analytic_m3"][name], rel=1e-3)  # the mesh against the closed form
    assert len({p.mesa.height_m for p in SCENE}) == 3  # different heights
    assert any(p.mesa.x1 >= BUILDING.length_m for p in SCENE)  # one against a wall


def test_that_the_scene_configuration_names_every_pile_inside_it(tmp_path):
    write_scene(tmp_path)
    cfg = load_config(tmp_path / "scene.toml")
    assert [e.name for e in cfg.piles] == [p.name for p in SCENE]
    for e, p in zip(cfg.piles, SCENE, strict=True):
        assert p.mesa.heights(e.x_m, e.y_m) == pytest.approx(p.mesa.height_m)  # the point is on the pile's top
        assert e.density_kg_m3 == p.density_kg_m3
    assert cfg.site.timezone == "Europe/London" and cfg.survey.aircraft
