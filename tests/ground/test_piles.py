"""Piles: found on the height grid (separate, touching, grown together, specks, an empty floor), named and
weighed from the configuration, in the units asked for, with intervals that add up, and written as a CSV."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from firmware_py.core.config_file import ConfigError, PileEntry, parse_config
from ground.piles import (
    KG_PER_SHORT_TON,
    M3_PER_YD3,
    MIN_THRESHOLD_M,
    THRESHOLD_SIGMAS,
    MassUnit,
    PileOptions,
    VolumeUnit,
    pile_table,
    segment,
    threshold_m,
    write_piles_csv,
)
from ground.surface import Grid
from ground.uncertainty import DEFAULT_INTERVAL_MODEL, survey_errors

GRID = Grid(40.0, 20.0, 0.25)
SIGMA_M = 0.03  # a typical point sigma: threshold 0.09 m


def centres(grid: Grid = GRID) -> tuple[np.ndarray, np.ndarray]:
    xs = (np.arange(grid.shape[0]) + 0.5) * grid.length_m / grid.shape[0]
    ys = (np.arange(grid.shape[1]) + 0.5) * grid.width_m / grid.shape[1]
    return np.meshgrid(xs, ys, indexing="ij")


def cone(cx: float, cy: float, h: float, r: float, grid: Grid = GRID) -> np.ndarray:
    px, py = centres(grid)
    return np.clip(h * (1.0 - np.hypot(px - cx, py - cy) / r), 0.0, None)


def grid_volume(z: np.ndarray, grid: Grid = GRID) -> float:
    return float(z.sum() * grid.cell_area_m2)


def table(heights: np.ndarray, opts: PileOptions | None = None, errors_in=None) -> dict:
    return pile_table(heights, GRID, SIGMA_M, opts or PileOptions(), errors_in)


def test_that_two_separate_cones_are_two_piles_with_their_volumes():
    a, b = cone(10, 10, 4.0, 6.0), cone(30, 10, 2.0, 3.0)
    t = table(np.maximum(a, b))
    assert t["n_piles"] == 2
    big, small = t["piles"]  # in decreasing volume
    assert big["volume_m3"] == pytest.approx(grid_volume(a), rel=1e-9)
    assert small["volume_m3"] == pytest.approx(grid_volume(b), rel=1e-9)
    assert big["volume_m3"] == pytest.approx(math.pi * 36 * 4 / 3, rel=0.01)  # the cone's own volume
    assert big["peak_height_m"] == pytest.approx(a.max())  # the highest cell centre, 0.18 m off the apex
    assert big["centroid_xy_m"] == pytest.approx([10, 10], abs=0.05)
    assert small["centroid_xy_m"] == pytest.approx([30, 10], abs=0.05)
    assert t["volume_outside_piles_m3"] == pytest.approx(0.0, abs=1e-9)


def test_that_cones_whose_toes_touch_are_two_piles_each_with_its_volume():
    a, b = cone(10, 10, 4.0, 6.0), cone(19, 10, 3.0, 3.0)  # centres 9 m apart = r1 + r2
    t = table(np.maximum(a, b))
    assert t["n_piles"] == 2
    got = sorted(p["volume_m3"] for p in t["piles"])
    assert got == pytest.approx(sorted([grid_volume(a), grid_volume(b)]), rel=0.002)


def test_that_heaps_grown_together_are_one_pile_unless_the_configuration_names_both():
    a, b = cone(10, 10, 4.0, 6.0), cone(16, 10, 3.0, 4.5)  # they merge 1.7 m above the floor
    z = np.maximum(a, b)
    one = table(z)
    assert one["n_piles"] == 1 and one["piles"][0]["volume_m3"] == pytest.approx(grid_volume(z))
    named = table(z, PileOptions(entries=(PileEntry("west", 10.0, 10.0), PileEntry("east", 16.0, 10.0))))
    assert [p["label"] for p in named["piles"]] == ["west", "east"]
    west, east = named["piles"]
    assert west["volume_m3"] + east["volume_m3"] == pytest.approx(grid_volume(z))
    # split along the valley, where the two cones meet: each keeps the ground where it is the higher
    assert west["volume_m3"] == pytest.approx(grid_volume(np.where(a >= b, z, 0.0)), rel=0.01)
    assert east["volume_m3"] == pytest.approx(grid_volume(np.where(a < b, z, 0.0)), rel=0.01)
    assert any("split between them" in w for w in named["warnings"])
    assert not any("no summit" in w for w in named["warnings"])  # a real valley


def test_that_two_names_on_one_cone_are_warned_and_two_in_one_cell_report_the_first():
    z = cone(10, 10, 4.0, 6.0)
    flank = table(z, PileOptions(entries=(PileEntry("top", 10.0, 10.0), PileEntry("flank", 13.0, 10.0))))
    assert any("'flank' has no summit of its own" in w for w in flank["warnings"])
    same = table(z, PileOptions(entries=(PileEntry("a", 10.0, 10.0), PileEntry("b", 10.05, 10.05))))
    # "attempt to get argmax of an empty sequence" before: the second name's cell was the first's seed
    assert [p["label"] for p in same["piles"]] == ["a"] and same["piles"][0]["volume_m3"] == pytest.approx(
        grid_volume(z))
    assert any("'a' and 'b' point at the same cell: 'b' not reported" in w for w in same["warnings"])
    assert not any("split between them" in w for w in same["warnings"])


def test_that_a_named_point_whose_part_of_a_split_is_smaller_than_a_pile_is_not_a_pile():
    # a point near a cone's toe took 0.1 m² of it: listed as a pile of 0.5 yd³ under "at least 1 m² and 4 cells"
    z = cone(10, 10, 4.0, 6.0)
    t = table(z, PileOptions(entries=(PileEntry("top", 10.0, 10.0), PileEntry("toe", 15.5, 10.0))))
    assert [p["label"] for p in t["piles"]] == ["top"]
    assert t["piles"][0]["volume_m3"] == pytest.approx(grid_volume(z))  # its cells stay with the pile they are on
    assert any("'toe' would take only 0.1 m²" in w and "not reported" in w for w in t["warnings"])
    assert not any("split between them" in w for w in t["warnings"])
    big = table(z, PileOptions(entries=(PileEntry("top", 10.0, 10.0), PileEntry("toe", 13.0, 10.0))))
    assert [p["label"] for p in big["piles"]] == ["top", "toe"]  # a part of a pile's size is still split off


def test_that_noise_level_specks_are_not_piles():
    rng = np.random.default_rng(3)
    floor = rng.normal(0.0, SIGMA_M, GRID.shape)  # 12,800 cells: ~17 pass 3 sigma, alone
    floor[5, 5] = 2.0  # a single tall cell (a post, a bird): a speck, not a pile
    assert table(floor)["n_piles"] == 0
    with_pile = table(floor + cone(20, 10, 3.0, 4.0))
    assert with_pile["n_piles"] == 1
    assert with_pile["piles"][0]["volume_m3"] == pytest.approx(grid_volume(cone(20, 10, 3.0, 4.0)), rel=0.01)


def test_that_an_empty_floor_has_no_piles_and_a_csv_with_only_its_header(tmp_path):
    t = table(np.zeros(GRID.shape))
    assert t["n_piles"] == 0 and t["piles"] == [] and t["volume_in_piles_m3"] == 0.0
    path = write_piles_csv(t, tmp_path / "piles.csv")
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    assert len(rows) == 1 and rows[0][:3] == ["label", "material", "volume_m3"]


def test_that_the_threshold_is_the_surveys_noise_with_a_floor():
    assert threshold_m(0.05) == pytest.approx(THRESHOLD_SIGMAS * 0.05)
    assert threshold_m(0.001) == MIN_THRESHOLD_M
    assert threshold_m(float("nan")) == MIN_THRESHOLD_M


def test_that_a_region_smaller_than_the_least_area_is_a_speck():
    z = cone(20, 10, 0.5, 0.9)  # above the 0.09 m threshold over ~1.7 m²
    assert segment(z, GRID, threshold_m(SIGMA_M), 1.0).max() == 1
    assert segment(z, GRID, threshold_m(SIGMA_M), 5.0).max() == 0


# ----- units and mass -----------------------------------------------------------------------------------


def test_that_the_unit_conversions_are_the_exact_definitions():
    assert M3_PER_YD3 == 0.9144**3
    assert VolumeUnit.YD3.of_m3(1.0) == pytest.approx(1.307950619, rel=1e-9)
    assert VolumeUnit.M3.of_m3(2.5) == 2.5
    assert KG_PER_SHORT_TON == 2000 * 0.45359237
    assert MassUnit.SHORT_TON.of_kg(1000.0) == pytest.approx(1.10231131, rel=1e-8)
    assert MassUnit.TONNE.of_kg(1500.0) == 1.5


def test_that_mass_is_volume_times_density_in_the_units_asked_for():
    z = cone(10, 10, 4.0, 6.0)
    t = table(z, PileOptions(density_kg_m3=1600.0, volume_unit=VolumeUnit.YD3, mass_unit=MassUnit.SHORT_TON))
    p = t["piles"][0]
    assert p["mass_kg"] == pytest.approx(p["volume_m3"] * 1600.0)
    assert p["display"]["volume"] == pytest.approx(p["volume_m3"] / 0.9144**3)
    assert p["display"]["mass"] == pytest.approx(p["mass_kg"] / 907.18474)
    assert t["volume_unit"] == "yd3" and t["mass_unit"] == "short-ton"


def test_that_a_configured_density_wins_over_the_one_for_all_and_names_come_from_the_configuration():
    z = np.maximum(cone(10, 10, 4.0, 6.0), cone(30, 10, 2.0, 3.0))
    opts = PileOptions(entries=(PileEntry("coal", 30.0, 10.0, 850.0, "coal"),), density_kg_m3=1600.0)
    t = table(z, opts)
    by = {p["label"]: p for p in t["piles"]}
    assert set(by) == {"coal", "P1"}
    assert by["coal"]["density_kg_m3"] == 850.0 and by["coal"]["material"] == "coal"
    assert by["P1"]["density_kg_m3"] == 1600.0


def test_that_a_configured_pile_on_no_pile_is_a_warning():
    t = table(cone(10, 10, 4.0, 6.0), PileOptions(entries=(PileEntry("gone", 35.0, 15.0),)))
    assert t["n_piles"] == 1 and t["piles"][0]["label"] == "P1"
    assert len([w for w in t["warnings"] if "'gone'" in w and "on no pile" in w]) == 1


@pytest.mark.parametrize("bad", [dict(density_kg_m3=0.0), dict(density_kg_m3=float("inf")),
                                 dict(min_area_m2=-1.0)])
def test_that_pile_options_refuse_impossible_values(bad):
    with pytest.raises(ValueError):
        PileOptions(**bad)


# ----- the configuration ------------------------------------------------------------------------------------


@pytest.mark.parametrize(("piles", "line"), [
    ([{"x_m": 1.0, "y_m": 2.0}], "[[piles]] #1 name: missing"),
    ([{"name": "a", "y_m": 2.0}], "[[piles]] #1 x_m: missing"),
    ([{"name": "a", "x_m": 1.0, "y_m": 2.0}, {"name": "a", "x_m": 5.0, "y_m": 2.0}],
     "[[piles]] #2 name: \"a\" is already pile #1's name"),
    ([{"name": "a", "x_m": 41.0, "y_m": 2.0}], "[[piles]] #1 x_m: 41 m is outside the 40 m building"),
    ([{"name": "a", "x_m": 1.0, "y_m": 2.0, "density_kg_m3": -5}], "[[piles]] #1 density_kg_m3: must be in (0, 22600]"),
    ([{"name": "a", "x_m": 1.0, "y_m": 2.0, "colour": "red"}], "[[piles]] #1 colour: unknown key"),
    ({"name": "a"}, "[[piles]]: must be an array of tables"),
])
def test_that_each_bad_pile_entry_is_one_line_naming_it(piles, line):
    with pytest.raises(ConfigError) as exc:
        parse_config({"site": {"length_m": 40, "width_m": 20, "height_m": 10}, "piles": piles}, "c.toml")
    lines = [str(exc.value), *exc.value.details]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"c.toml: {line}"), lines[0]


def test_that_a_bad_time_zone_is_one_line_and_a_good_one_reads():
    with pytest.raises(ConfigError, match=r"c.toml: \[site\] timezone: is not a time zone"):
        parse_config({"site": {"timezone": "Mars/Olympus_Mons"}}, "c.toml")
    cfg = parse_config({"site": {"timezone": "America/Chicago", "name": "Bay 3"},
                        "survey": {"operator": "J. Smith"}, "piles": [{"name": "a", "x_m": 1, "y_m": 2}]})
    assert cfg.site.timezone == "America/Chicago" and cfg.survey.operator == "J. Smith"
    assert cfg.piles == (PileEntry("a", 1.0, 2.0),)


# ----- the CSV ------------------------------------------------------------------------------------------------


def test_that_the_csv_reads_back_with_units_in_its_column_names(tmp_path):
    z = np.maximum(cone(10, 10, 4.0, 6.0), cone(30, 10, 2.0, 3.0))
    t = table(z, PileOptions(entries=(PileEntry("sand, washed", 10.0, 10.0, 1600.0, "sand"),),
                             volume_unit=VolumeUnit.YD3, mass_unit=MassUnit.SHORT_TON))
    with write_piles_csv(t, tmp_path / "piles.csv").open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2
    assert {"volume_m3", "volume_yd3", "mass_kg", "mass_short-ton", "footprint_area_m2"} <= set(rows[0])
    sand = rows[0]
    assert sand["label"] == "sand, washed"  # quoted by the csv module, read back whole
    assert float(sand["volume_m3"]) == pytest.approx(t["piles"][0]["volume_m3"])
    assert float(sand["volume_yd3"]) == pytest.approx(float(sand["volume_m3"]) / M3_PER_YD3)
    assert float(sand["mass_short-ton"]) == pytest.approx(float(sand["volume_m3"]) * 1600 / 907.18474)
    assert rows[1]["mass_kg"] == ""  # no density for the unnamed pile: no mass, not 0


# ----- intervals -------------------------------------------------------------------------------------------


def test_that_per_pile_intervals_add_up_to_the_surveys():
    """The terms are sums over cells (noise: in quadrature), so the piles and the rest of the floor add up to
    the whole survey's (noise: at most); each pile's interval holds its volume and is narrower than the survey's."""
    rng = np.random.default_rng(7)
    z = np.maximum(cone(10, 10, 4.0, 6.0), cone(30, 10, 2.0, 3.0))
    px, py = centres()
    seen = rng.random(GRID.shape) < 0.4  # points in 40 % of the cells, the rest interpolated
    fit = np.where(seen | (rng.random(GRID.shape) < 0.9), z, np.nan)  # some cells never surfaced
    heights = np.where(np.isfinite(fit), fit, 0.0)
    idx = np.flatnonzero(seen)
    pts = np.column_stack([px.ravel()[idx], py.ravel()[idx], z.ravel()[idx] + rng.normal(0, SIGMA_M, idx.size)])
    counts = seen.astype(int)
    sweep = rng.choice([-1, 1], len(pts))

    def errors_in(mask=None):
        return survey_errors(pts, sweep, fit, heights, counts, GRID, SIGMA_M, 3.0, mask=mask)
    t = table(heights, errors_in=errors_in)
    assert t["n_piles"] == 2
    whole = errors_in().terms.as_dict()
    labels = np.zeros(GRID.shape, bool)
    parts = []
    for p in t["piles"]:
        x0, x1 = p["extent_m"]["x"]
        mask = (px > x0) & (px < x1) & np.isfinite(px)
        mask &= (py > p["extent_m"]["y"][0]) & (py < p["extent_m"]["y"][1])
        labels |= mask
        parts.append(errors_in(mask).terms.as_dict())
        lo, hi = p["volume_interval_m3"]
        assert lo <= p["volume_m3"] <= hi
        assert hi - lo < np.subtract(*DEFAULT_INTERVAL_MODEL.interval_m3(grid_volume(heights), errors_in().terms)[::-1])
    parts.append(errors_in(~labels).terms.as_dict())
    for name in ("unseen_low_m3", "unseen_high_m3", "interpolation_m3", "blur_m3", "faces_m3"):
        assert sum(p[name] for p in parts) == pytest.approx(whole[name], rel=1e-6, abs=1e-9), name
    # noise: a cell's points stand for the cells nearest them, and a mask can cut that area in two: in
    # quadrature the parts are then a little less than the whole, never more
    in_quadrature = math.sqrt(sum(p["noise_m3"] ** 2 for p in parts))
    assert 0.9 * whole["noise_m3"] <= in_quadrature <= whole["noise_m3"] * (1 + 1e-9)
    assert sum(p["sweeps_m3"] for p in parts) >= whole["sweeps_m3"] - 1e-12  # |sum| <= sum of |parts|


def test_that_piles_over_a_fitted_floor_add_up_to_the_volume_over_it_and_carry_its_error():
    from ground.base import Base, BaseKind
    px, _ = centres()
    floor = 0.02 * px  # a floor rising 2 cm a metre: 0.8 m at the far wall
    heights = floor + np.maximum(cone(10, 10, 4.0, 6.0), cone(30, 10, 2.0, 3.0))
    base = Base(BaseKind.FITTED_FLOOR, "a plane", floor, 20.0, 20.0, extra_over=lambda mask: 20.0 * mask.mean())
    over = pile_table(base.pile_heights(heights), GRID, SIGMA_M, PileOptions(), None, over=base.piles_over)
    assert over["n_piles"] == 2 and "fitted floor" in over["method"]
    assert over["volume_in_piles_m3"] + over["volume_outside_piles_m3"] == pytest.approx(base.volume_m3(heights, GRID))
    assert over["volume_outside_piles_m3"] == pytest.approx(0.0, abs=1e-6)
    z0 = table(heights)  # over z = 0 the sloped floor itself is a "pile" wall to wall
    assert z0["volume_in_piles_m3"] > over["volume_in_piles_m3"] + 250  # most of the 320 m³ of sloped slab

    def errors_in(mask=None):
        return survey_errors(np.zeros((0, 3)), np.zeros(0), heights, heights, np.ones(GRID.shape, int), GRID,
                             SIGMA_M, 3.0, mask=mask)
    plain = pile_table(base.pile_heights(heights), GRID, SIGMA_M, PileOptions(), errors_in)
    widened = pile_table(base.pile_heights(heights), GRID, SIGMA_M, PileOptions(), errors_in,
                         extra_over=base.extra_over)
    for p, w in zip(plain["piles"], widened["piles"], strict=True):
        (lo, hi), (wlo, whi) = p["volume_interval_m3"], w["volume_interval_m3"]
        assert wlo < lo and whi > hi  # the base's own error, in quadrature


def test_that_over_an_earlier_survey_the_piles_are_this_survey_s_over_the_floor_and_say_so():
    from ground.base import Base, BaseKind
    heights = cone(10, 10, 4.0, 6.0)
    earlier = Base(BaseKind.SURVEY, "an earlier survey", 0.9 * heights, 5.0, 5.0, False)
    assert earlier.pile_heights(heights) is heights
    assert "compare" in earlier.piles_over and "z = 0" in earlier.piles_over
    t = pile_table(earlier.pile_heights(heights), GRID, SIGMA_M, PileOptions(), None, over=earlier.piles_over)
    assert t["piles"][0]["volume_m3"] == pytest.approx(grid_volume(heights), rel=1e-9)
