"""An earlier survey's surface for the coverage planner: read without the ground station, beams stop at it."""

import math

import numpy as np
import pytest

from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from ground.render import write_ply
from ground.surface_file import SavedSurface, save_surface
from sitl.cli import main
from sitl.missions.coverage import LoopPlan, predict_coverage
from sitl.missions.range_check import RangeLimit
from sitl.missions.surveyed_surface import HeightField, first_hits_w, load_height_field
from tests.firmware_py.core.test_surface_file import BUILDING_OR_CELL_CASES, edit_meta

SMALL = Storage(30.0, 20.0, 10.0)
WF = named_waveform("semi-triangular", 5.0, 0)
LIDAR = RangeLimit(LIDARLITE_V3.max_range_m)


def _report(tmp_path, heights: np.ndarray, storage: Storage = SMALL, cloud_xy: np.ndarray | None = None):
    """A report directory as `pilescan-ground report` writes it: surface.npz (by the ground's own writer) and
    cloud.ply (the pile points)."""
    d = tmp_path / "report"
    d.mkdir(exist_ok=True)
    save_surface(SavedSurface(heights, storage.length_m, storage.width_m, storage.height_m,
                              storage.length_m / heights.shape[0], 0.0, 0.0, 0.0, 0.0), d / "surface.npz")
    if cloud_xy is not None:
        write_ply(np.column_stack([cloud_xy, np.zeros(len(cloud_xy))]), d / "cloud.ply")
    return d


def _block(height_m: float, x0: float, x1: float) -> np.ndarray:
    """Heights on SMALL's 0.5 m grid: a wall of material across the building from x0 to x1."""
    h = np.zeros((60, 40))
    h[int(x0 / 0.5):int(x1 / 0.5), :] = height_m
    return h


def test_that_the_ground_stations_surface_file_is_read_as_it_was_written(tmp_path):
    h = _block(4.0, 10.0, 12.0)
    field = load_height_field(_report(tmp_path, h), SMALL)
    assert np.array_equal(field.heights_m, h)
    assert field.height_at(np.array([11.0, 5.0]), np.array([3.0, 3.0])).tolist() == [4.0, 0.0]


def test_that_cells_outside_the_reports_points_count_as_floor_not_as_the_fill(tmp_path):
    h = np.full((60, 40), 2.0)  # the empty-cell policy's fill reaches the walls
    cloud = np.array([[5.0, 5.0], [25.0, 5.0], [25.0, 15.0], [5.0, 15.0]])
    field = load_height_field(_report(tmp_path, h, cloud_xy=cloud), SMALL)
    assert field.height_at(np.array([15.0]), np.array([10.0]))[0] == 2.0  # measured
    assert field.height_at(np.array([1.0]), np.array([10.0]))[0] == 0.0  # outside the points: floor


def test_that_a_beam_stops_at_the_first_surface_and_a_beam_into_a_wall_meets_nothing():
    field = HeightField(_block(6.0, 10.0, 12.0), 30.0, 20.0)
    o = np.array([[5.0, 10.0, 8.0], [5.0, 10.0, 8.0], [2.0, 10.0, 8.0]])
    d = np.array([[math.sin(math.radians(60)), 0.0, -math.cos(math.radians(60))], [0.0, 0.0, -1.0],
                  [-math.sin(math.radians(60)), 0.0, -math.cos(math.radians(60))]])
    hits, r = first_hits_w(o, d, field, 0.05)
    assert hits[0, 0] == pytest.approx(10.0, abs=0.06) and hits[0, 2] == pytest.approx(5.1, abs=0.1)  # the block's face
    assert hits[1] == pytest.approx([5.0, 10.0, 0.0])  # straight down: the floor
    assert np.isnan(r[2])  # leaves the floor through the west wall before meeting anything


def _marched(o, d, field, step_m):
    """Every beam marched alone in steps of step_m from where it comes below the highest surface (the definition)."""
    hits, rng = np.full((len(o), 3), np.nan), np.full(len(o), np.nan)
    for i in range(len(o)):
        down = -d[i, 2]
        r0, r_floor, k = max(0.0, (o[i, 2] - field.max_height_m) / down), o[i, 2] / down, 0
        while True:
            r = min(r0 + k * step_m, r_floor)
            p = o[i] + r * d[i]
            if not (0 <= p[0] <= field.length_m and 0 <= p[1] <= field.width_m):
                break
            if p[2] <= field.height_at(p[:1], p[1:2])[0] + 1e-9:
                hits[i], rng[i] = p, r
                break
            if r >= r_floor:
                break
            k += 1
    return hits, rng


def test_that_beams_over_bare_floor_land_where_marching_them_lands_without_being_marched():
    rng = np.random.default_rng(1)
    h = np.zeros((120, 80))
    h[10:40, 20:50] = rng.uniform(0, 5, (30, 30))  # a rough heap
    h[70:75, :] = 3.0  # a bank wall to wall
    field = HeightField(h, 30.0, 20.0)
    n = 3000
    o = np.column_stack([rng.uniform(-1, 31, n), rng.uniform(-1, 21, n), rng.uniform(5, 9, n)])
    g, az = rng.uniform(-1.2, 1.2, n), rng.uniform(0, 2 * np.pi, n)
    d = np.column_stack([np.sin(g) * np.cos(az), np.sin(g) * np.sin(az), -np.cos(g)])
    hits, r = first_hits_w(o, d, field, 0.125)
    ref_hits, ref_r = _marched(o, d, field, 0.125)
    assert np.array_equal(r, ref_r, equal_nan=True) and np.array_equal(hits, ref_hits, equal_nan=True)
    assert 0.2 * n < np.isfinite(r).sum() < n and np.isnan(r).sum() > 0.1 * n  # floor, heap, bank and walls all met


def test_that_material_on_the_surface_shadows_floor_the_empty_floor_model_counts():
    m = LoopPlan((4.0, 6.0, 4.0, 6.0), speed_m_s=2.0).mission(SMALL, 8.0, math.radians(30))
    flat = predict_coverage(m, WF, LIDAR, LIDARLITE_V3.rate_hz)
    banked = predict_coverage(m, WF, LIDAR, LIDARLITE_V3.rate_hz,
                              surface=HeightField(_block(7.0, 1.0, 3.0), 30.0, 20.0))
    # the floor strip between the west wall and a 7 m bank 1 m from it is seen by no leg
    assert banked.predicted_ra_pct < flat.predicted_ra_pct - 100 * 0.5 / 30


@pytest.mark.parametrize("make, message", [
    (lambda d: None, "cannot read surface file"),
    (lambda d: (d / "surface.npz").write_bytes(b"not a zip"), "is not a pilescan surface file"),
    (lambda d: np.savez(d / "surface.npz", heights_m=np.zeros(3), meta=np.array('{"format": "x"}')),
     "is not a pilescan surface file"),
])
def test_that_an_unusable_surface_is_one_line(tmp_path, make, message):
    d = tmp_path / "r"
    d.mkdir()
    make(d)
    with pytest.raises(ValueError, match=message) as e:
        load_height_field(d, SMALL)
    assert "\n" not in str(e.value)


def test_that_a_surface_file_with_cells_finer_than_a_grid_can_hold_is_one_line(tmp_path):
    d = tmp_path / "r"
    d.mkdir()
    save_surface(SavedSurface(np.zeros((1, 1)), 30.0, 20.0, 10.0, 1e-320, 0.0, 0.0, 0.0, 0.0), d / "surface.npz")
    with pytest.raises(ValueError, match=r"cell_m must be a finite number >= 0\.01"):  # OverflowError before
        load_height_field(d, SMALL)


@pytest.mark.parametrize("key, value, message", BUILDING_OR_CELL_CASES)
def test_that_a_surface_file_whose_building_or_cell_is_no_usable_number_is_one_line(tmp_path, key, value, message):
    d = _report(tmp_path, np.zeros((60, 40)))
    edit_meta(d / "surface.npz", key, value)
    with pytest.raises(ValueError, match=message) as e:
        load_height_field(d, SMALL)
    assert "\n" not in str(e.value) and str(e.value).startswith(f"{d / 'surface.npz'}: surface file field {key} ")


def test_that_a_survey_of_another_building_is_refused(tmp_path):
    d = _report(tmp_path, np.zeros((60, 40)))
    with pytest.raises(ValueError, match="not the 60x40x15"):
        load_height_field(d, Storage())


def test_that_plan_refuses_a_bad_surface_with_one_line(tmp_path, capsys):
    assert main(["plan", "--coverage", "95", "--surface", str(tmp_path / "none"), "--storage", "30x20x10",
                 "--altitude", "6", "--out", str(tmp_path / "p.waypoints")]) != 0
    err = capsys.readouterr().err
    assert "cannot read surface file" in err and len(err.strip().splitlines()) == 1


def test_that_plan_refuses_a_surface_whose_cell_is_no_number_with_one_line(tmp_path, capsys):
    d = _report(tmp_path, np.zeros((60, 40)))
    edit_meta(d / "surface.npz", "cell_m", "half a metre")
    assert main(["plan", "--coverage", "95", "--surface", str(d), "--storage", "30x20x10", "--altitude", "6",
                 "--out", str(tmp_path / "p.waypoints")]) != 0
    err = capsys.readouterr().err
    assert "cell_m must be a finite number >= 0.01, got 'half a metre'" in err and len(err.strip().splitlines()) == 1
    assert "Traceback" not in err and not (tmp_path / "p.waypoints").exists()


def test_that_plan_plans_on_a_surface_and_says_so(tmp_path, capsys, one_speed):
    from sitl.missions.qgc_wpl import read_qgc_wpl
    seen = one_speed  # the real planner at one speed: four are slow on a surface
    d = _report(tmp_path, _block(5.0, 1.0, 3.0))
    out = tmp_path / "p.waypoints"
    assert main(["plan", "--coverage", "90", "--surface", str(d), "--storage", "30x20x10", "--altitude", "6",
                 "--out", str(out)]) == 0
    assert f"on the surface of {d}" in capsys.readouterr().out
    assert seen[0].surface is not None and seen[0].surface.max_height_m == 5.0
    assert len(read_qgc_wpl(out)) >= 8
