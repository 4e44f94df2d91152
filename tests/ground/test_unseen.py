"""The unseen ground: the free-space ceiling the beams give, and the bounded fill held under it."""

import math
from pathlib import Path

import numpy as np
import pytest

from firmware_py.core.rundir import SAMPLES_FILE
from firmware_py.core.samplelog import read_samplelog
from firmware_py.core.storage import Storage
from ground.pointcloud import Cloud, SensorErrorModel, structure_n_sigma
from ground.report import ReportOptions, header_geometry, make_report, survey_from_samples
from ground.surface import Grid, fill_empty, grid_volume
from ground.unseen import (
    MAX_SLOPE,
    Extension,
    beam_angle_sigma_rad,
    bounded_fill,
    free_space_ceiling_m,
    spread_down_slope,
    unseen_bounds,
)
from sitl.world.raycast import World
from sitl.world.stockpile import Stockpile, heightfield_mesh, volume_under_mesh

STORAGE = Storage(20.0, 12.0, 8.0)
GRID = Grid(STORAGE.length_m, STORAGE.width_m, 0.25)
IDEAL = SensorErrorModel(resolution_m=0.01)


def mound_m(x, y):
    """A smooth mound (slopes below 45 deg) in the middle of the small building."""
    return 3.0 * np.exp(-((x - 10.0) ** 2 + (y - 6.0) ** 2) / (2 * 2.5**2))


def scene_cloud(height_fn, origins, n_per_origin=4000, seed=0, range_sigma_m=0.0) -> Cloud:
    """Beams cast at a height-field pile by the SITL's ray tracer from a few sensor positions, every
    direction of the lower hemisphere: a synthetic survey whose truth is known everywhere."""
    xs, ys = np.linspace(0, STORAGE.length_m, 161), np.linspace(0, STORAGE.width_m, 97)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    mesh = heightfield_mesh(xs, ys, height_fn(gx, gy))
    world = World(STORAGE, Stockpile(mesh, volume_under_mesh(mesh), "test"), 40.0)
    rng = np.random.default_rng(seed)
    o_all, d_all = [], []
    for o in origins:
        d = rng.normal(size=(n_per_origin, 3))
        d[:, 2] = -np.abs(d[:, 2])
        o_all.append(np.repeat(np.asarray(o, dtype=float)[None], n_per_origin, axis=0))
        d_all.append(d / np.linalg.norm(d, axis=1)[:, None])
    o, d = np.concatenate(o_all), np.concatenate(d_all)
    r = world.cast(o, d).range_m
    ok = np.isfinite(r) & (r > 0)
    o, d, r = o[ok], d[ok], r[ok]
    r = r + rng.normal(0.0, range_sigma_m, len(r)) if range_sigma_m else r
    return Cloud(o + d * r[:, None], d, r, o, len(r), 0)


def test_that_the_ceiling_is_at_or_above_the_true_surface_everywhere():
    cloud = scene_cloud(mound_m, [(4.0, 3.0, 6.0), (15.0, 9.0, 6.0), (10.0, 6.0, 7.0)])
    ceiling = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL)
    cx, cy = GRID.centres()
    assert np.all(ceiling >= mound_m(cx, cy) - 1e-9)
    assert (ceiling < STORAGE.height_m).mean() > 0.9  # and it is a bound almost everywhere, not the roof


def test_that_the_ceiling_is_below_every_beam_it_crossed():
    """Where a beam passes within a quarter cell of a cell centre (so its track surely crosses the cell),
    the ceiling there is no higher than the beam, up to the beam's rise across the cell and the slope
    allowance."""
    cloud = scene_cloud(mound_m, [(4.0, 3.0, 6.0), (15.0, 9.0, 6.0)], n_per_origin=1500)
    ceiling = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL)
    c = GRID.cell_m
    origins = cloud.points_w - cloud.dirs_w * cloud.range_m[:, None]
    checked = 0
    for o, d, r in zip(origins, cloud.dirs_w, cloud.range_m, strict=True):
        s = np.arange(0.0, r - 0.02, 0.02)
        p = o + s[:, None] * d
        ix, iy = np.floor(p[:, 0] / c).astype(int), np.floor(p[:, 1] / c).astype(int)
        near = np.hypot(p[:, 0] - (ix + 0.5) * c, p[:, 1] - (iy + 0.5) * c) < c / 4
        horiz = math.hypot(d[0], d[1])
        rise = abs(d[2]) / horiz * c * math.sqrt(2) if horiz > 1e-6 else math.inf
        allowance = rise + MAX_SLOPE * c * math.sqrt(2) / 2 + 0.01
        assert np.all(ceiling[ix[near], iy[near]] <= p[near, 2] + allowance)
        checked += int(near.sum())
    assert checked > 10_000


def test_that_range_noise_does_not_push_the_ceiling_into_the_pile():
    """Ranges with 5 cm noise: the ceiling, raised by the error model's margin, stays above the mound;
    the same beams taken as exact cut into it (which is what the margin is for)."""
    noisy = scene_cloud(mound_m, [(4.0, 3.0, 6.0), (15.0, 9.0, 6.0), (10.0, 6.0, 7.0)], range_sigma_m=0.05, seed=3)
    cx, cy = GRID.centres()
    truth = mound_m(cx, cy)
    ceiling = free_space_ceiling_m(noisy, GRID, STORAGE, SensorErrorModel(range_sigma_m=0.05, resolution_m=0.01))
    assert np.all(ceiling >= truth - 1e-9)
    blind = free_space_ceiling_m(noisy, GRID, STORAGE, IDEAL, n_sigma=0.0)
    assert np.any(blind < truth - 0.01)


def test_that_a_stated_pose_and_angle_error_loosen_the_ceiling():
    cloud = scene_cloud(mound_m, [(4.0, 3.0, 6.0)], n_per_origin=1000)
    tight = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL)
    loose = free_space_ceiling_m(cloud, GRID, STORAGE, SensorErrorModel(position_sigma_m=0.1), math.radians(1.0))
    crossed = tight < STORAGE.height_m
    assert np.all(loose >= tight)
    k = structure_n_sigma(len(cloud.range_m))
    assert np.median((loose - tight)[crossed & (loose < STORAGE.height_m)]) > 0.1 * k


def test_that_computing_only_the_cells_asked_for_gives_the_same_beam_bounds_there_and_no_tighter_spread():
    """The beams' own bounds in the cells asked for are those of the whole floor; carried at the slope, the cells
    left out give nothing, so the bound there can only be looser, never below what all the beams say."""
    cloud = scene_cloud(mound_m, [(4.0, 3.0, 6.0), (15.0, 9.0, 6.0)], n_per_origin=2000)
    where = np.zeros(GRID.shape, dtype=bool)
    where[:12, :10] = where[60:, 30:] = True
    full = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL, spread=False)
    part = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL, where=where, spread=False)
    assert np.array_equal(part[where], full[where])
    assert np.isnan(part[~where]).all()
    spread_full = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL)
    spread_part = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL, where=where)
    assert np.all(spread_part[where] >= spread_full[where])
    assert np.all(spread_part[where] <= part[where])


def test_that_the_spread_carries_a_bound_at_the_slope_and_never_below_the_straight_cone():
    """One low cell in a roof-high ceiling: every cell is bounded by its height plus MAX_SLOPE times the distance,
    exactly along the neighbourhood's steps and within 3 % of the distance between them, never less."""
    roof = np.full(GRID.shape, STORAGE.height_m)
    roof[40, 24] = 1.0
    out = spread_down_slope(roof, GRID.cell_m, GRID.cell_m)
    ix, iy = np.meshgrid(np.arange(GRID.shape[0]), np.arange(GRID.shape[1]), indexing="ij")
    cone = np.minimum(1.0 + MAX_SLOPE * GRID.cell_m * np.hypot(ix - 40, iy - 24), STORAGE.height_m)
    assert np.all(out >= cone - 1e-9)
    assert np.all(out <= 1.0 + 1.03 * (cone - 1.0) + 1e-9)
    assert out[40, 24 + 8] == pytest.approx(1.0 + 8 * GRID.cell_m)
    assert out[40 + 6, 24 + 6] == pytest.approx(1.0 + 6 * math.sqrt(2) * GRID.cell_m)


def test_that_the_spread_ceiling_stays_above_the_true_surface_between_the_beams():
    """A few hundred beams only: most cells are crossed by none, and the ceiling carried to them from the crossed
    ones still lies above the mound (slopes below MAX_SLOPE) and below the roof in most of them."""
    cloud = scene_cloud(mound_m, [(4.0, 3.0, 6.0), (15.0, 9.0, 6.0)], n_per_origin=30, seed=2)
    own = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL, spread=False)
    ceiling = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL)
    cx, cy = GRID.centres()
    assert (own < STORAGE.height_m).mean() < 0.5  # the beams alone bound under half the cells
    assert np.all(ceiling >= mound_m(cx, cy) - 1e-9)
    assert np.all(ceiling <= own)
    assert (ceiling < STORAGE.height_m).mean() > 0.9


def test_that_a_bare_corner_under_low_beams_stays_near_the_floor_where_nearest_paints_material():
    """A pile's flank runs down towards the corner (0, 0) and ends 3 m short of it; the survey saw the flank
    to 2.1 m, not its toe or the bare corner, but beams from a sensor low in the corner ran over them to
    the walls and the floor. Nearest copies the flank's 2.1 m into the corner; bounded stays under the beams."""

    def flank(x, y):
        return np.clip(0.7 * (x + y - 3.0), 0.0, 4.0)

    cloud = scene_cloud(flank, [(1.0, 1.0, 0.8)], n_per_origin=4000, seed=1)
    cx, cy = GRID.centres()
    unseen, bare = cx + cy < 6.0, cx + cy < 3.0
    truth = flank(cx, cy)
    fit = np.where(unseen, np.nan, truth)
    ceiling = free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL, where=unseen)
    bounded = fill_empty(fit, "bounded", ceiling)
    nearest = fill_empty(fit, "nearest")
    assert np.mean(nearest[bare]) > 1.5
    assert np.mean(bounded[bare]) < 0.3
    assert np.abs(bounded[unseen] - truth[unseen]).sum() < 0.25 * np.abs(nearest[unseen] - truth[unseen]).sum()
    assert np.all((bounded[unseen] >= 0.0) & (bounded[unseen] <= ceiling[unseen] + 1e-12))


@pytest.mark.parametrize("extension", list(Extension))
def test_that_on_a_fully_covered_pile_the_bounded_policy_changes_nothing(extension):
    cx, cy = GRID.centres()
    fit = mound_m(cx, cy)
    assert np.array_equal(bounded_fill(fit, np.zeros(GRID.shape), extension), fit)
    assert np.array_equal(fill_empty(fit, "bounded", np.zeros(GRID.shape)), fit)


@pytest.mark.parametrize("extension", list(Extension))
def test_that_the_bounded_fill_keeps_the_seen_cells_and_stays_within_its_bounds(extension):
    cx, cy = GRID.centres()
    fit = np.where(cx + cy < 6.0, np.nan, 0.5 * cx)  # a ramp rising away from an unseen corner
    ceiling = np.full(GRID.shape, 1.0)
    out = bounded_fill(fit, ceiling, extension)
    seen = np.isfinite(fit)
    assert np.array_equal(out[seen], fit[seen])
    assert np.all((out[~seen] >= 0.0) & (out[~seen] <= 1.0))
    assert np.any(out[~seen] == 1.0) or np.any(out[~seen] == 0.0)  # the bounds were met: the plain fill leaves them


def test_that_the_thin_plate_continues_a_slope_the_harmonic_fill_flattens():
    """A plane rising towards an unseen corner: the biharmonic fill carries the slope on, the harmonic one
    stays below the edge's highest heights."""
    cx, cy = GRID.centres()
    plane = 6.0 - 0.3 * (cx + cy)
    fit = np.where(cx + cy < 8.0, np.nan, plane)
    unseen = ~np.isfinite(fit)
    thin = bounded_fill(fit, None, Extension.BIHARMONIC)
    flat = bounded_fill(fit, None, Extension.HARMONIC)
    assert np.max(np.abs(thin[unseen] - plane[unseen])) < 0.05
    assert np.max(flat[unseen]) <= np.nanmax(fit[np.isfinite(fit) & (cx + cy < 9.0)]) + 1e-9


def test_that_without_a_ceiling_only_the_floor_bounds_the_fill():
    cx, _ = GRID.centres()
    fit = np.where(cx < 3.0, np.nan, cx - 3.0)  # a ramp going down into the unseen strip: floor-bound
    out = fill_empty(fit, "bounded")
    assert np.all(out[cx < 3.0] >= 0.0)
    assert np.all(np.isfinite(out))


def test_that_the_unseen_bounds_are_floor_and_ceiling_where_unseen_and_the_fit_where_seen():
    cx, _ = GRID.centres()
    fit = np.where(cx < 2.0, np.nan, 1.5)
    ceiling = np.full(GRID.shape, 2.5)
    lo, hi = unseen_bounds(fit, ceiling)
    unseen = ~np.isfinite(fit)
    assert np.all(lo[unseen] == 0.0) and np.all(hi[unseen] == 2.5)
    assert np.array_equal(lo[~unseen], fit[~unseen]) and np.array_equal(hi[~unseen], fit[~unseen])
    v = grid_volume(fill_empty(fit, "bounded", ceiling), GRID)
    assert grid_volume(lo, GRID) <= v <= grid_volume(hi, GRID)


def test_that_the_angle_error_is_read_from_the_headers_noise_record_and_a_bad_one_voids_the_ceiling():
    rec = {"sensor_noise": {"servo_sigma_rad": 0.03, "attitude_sigma_rad": 0.04}}
    assert beam_angle_sigma_rad(rec) == pytest.approx(0.05)
    assert beam_angle_sigma_rad({}) == 0.0
    bad = beam_angle_sigma_rad({"sensor_noise": {"servo_sigma_rad": "lots"}})
    assert bad == math.inf
    cloud = scene_cloud(mound_m, [(4.0, 3.0, 6.0)], n_per_origin=500)
    assert np.all(free_space_ceiling_m(cloud, GRID, STORAGE, IDEAL, bad) == STORAGE.height_m)


def test_that_a_cloud_without_beams_bounds_nothing():
    empty = Cloud(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), 0, 0)
    assert np.all(free_space_ceiling_m(empty, GRID, STORAGE, IDEAL) == STORAGE.height_m)


@pytest.mark.parametrize("policy", ["bounded", "wall-contact"])
def test_that_the_report_fills_the_unseen_cells_within_the_floor_and_the_flights_ceiling(tmp_path, monkeypatch, policy):
    """The golden flight (pile 1, JSBSim) through the report with --empty-cells bounded and with the default
    wall-contact: fitted cells as fitted, the others between the floor and the ceiling its own beams give (the
    survey the report made, watched as it passed); the report says the policy."""
    import ground.report

    log = read_samplelog(Path("tests/golden") / SAMPLES_FILE)
    storage, _, _ = header_geometry(log, Path("tests/golden"))
    surveys = []

    def surveyed(*args, **kwargs):
        surveys.append(survey_from_samples(*args, **kwargs))
        return surveys[-1]
    monkeypatch.setattr(ground.report, "survey_from_samples", surveyed)
    rep = make_report("tests/golden", tmp_path / "b", ReportOptions(plots=False, empty_cells=policy))
    monkeypatch.undo()
    (sv,) = surveys
    unseen = ~np.isfinite(sv.heights_fit)
    assert unseen.any()
    ceiling = free_space_ceiling_m(sv.cloud, sv.grid, storage, SensorErrorModel.from_header(log.header),
                                   beam_angle_sigma_rad(log.header), where=unseen)
    assert np.array_equal(sv.heights[~unseen], sv.heights_fit[~unseen])
    assert np.all(sv.heights[unseen] <= ceiling[unseen] + 1e-12)
    if policy == "bounded":  # the default copies a fitted height as fitted, a few mm below the floor included
        assert np.all(sv.heights[unseen] >= 0.0)
    assert rep["empty_cell_policy"] == policy
    assert rep["volume_error_pct"] < 1.0


def test_that_the_wall_contact_fill_is_held_under_the_ceiling_where_one_was_computed():
    """A flank copied into an unseen strip: the default fill keeps the seen cells, lowers the copied heights to
    the ceiling where it is below them, and leaves the cells it has no ceiling for (NaN) as copied."""
    cx, _ = GRID.centres()
    fit = np.where(cx < 3.0, np.nan, 2.0)
    ceiling = np.where(cx < 3.0, 0.5 + 0.5 * cx, np.nan)
    ceiling[:2, :4] = np.nan  # not computed there
    out = fill_empty(fit, "wall-contact", ceiling)
    seen, unseen = np.isfinite(fit), ~np.isfinite(fit)
    assert np.array_equal(out[seen], fit[seen])
    bounded = unseen & np.isfinite(ceiling)
    assert np.allclose(out[bounded], np.minimum(2.0, ceiling[bounded]))
    assert np.any(out[bounded] < 2.0)
    assert np.all(out[:2, :4] == 2.0)
    assert np.array_equal(fill_empty(fit, "wall-contact"), fill_empty(fit, "nearest"))
