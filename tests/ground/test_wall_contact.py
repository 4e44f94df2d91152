"""The wall contacts: where a sweep's lowest wall hit sits above material, the material meets the wall."""

from dataclasses import replace

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleLog
from firmware_py.core.storage import Storage
from ground.pointcloud import Cloud, SensorErrorModel, structure_mask
from ground.report import ReportOptions, summarise, survey_from_samples
from ground.surface import grid_volume
from ground.wall_contact import WALL_LIKE_SIGMAS, WallContacts, contact_ceiling_m, pin_contacts, wall_contacts
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, log_header
from sitl.sensing.batch_sampler import sample_flight
from sitl.vehicle.ideal_plant import IdealPlant
from sitl.world.raycast import World
from sitl.world.shapes import make_shape
from sitl.world.stockpile import Stockpile, heightfield_mesh, volume_under_mesh

STORAGE = Storage(20.0, 12.0, 8.0)
IDEAL = SensorErrorModel(resolution_m=0.01)
NOISY = SensorErrorModel(range_sigma_m=0.02, resolution_m=0.01)
SLOPE = np.tan(np.radians(35.0))
RATE_HZ = 500.0
CELL_M = 0.25


def wedge_m(top_m: float):
    """Material leaning on the wall x = 0 at its angle of repose, top_m high at the wall."""
    return lambda x, y: np.clip(top_m - SLOPE * x, 0.0, None)


def swept_cloud(height_fn, sensor_x=8.0, sensor_z=6.0, ys=(3.0, 4.5, 6.0, 7.5, 9.0), step_deg=0.5,
                max_deg=85.0, range_sigma_m=0.0, seed=0) -> Cloud:
    """Sweeps of one servo across the wall x = 0, one per y (alternating directions, RATE_HZ samples),
    ray traced by the SITL against the building and a height-field pile: every beam's truth is known."""
    xs, yy = np.linspace(0, STORAGE.length_m, 161), np.linspace(0, STORAGE.width_m, 97)
    gx, gy = np.meshgrid(xs, yy, indexing="ij")
    mesh = heightfield_mesh(xs, yy, height_fn(gx, gy))
    world = World(STORAGE, Stockpile(mesh, max(volume_under_mesh(mesh), 1e-9), "test"), 40.0)
    theta = np.radians(np.arange(0.0, max_deg + 1e-9, step_deg))
    o_all, d_all, sweep, gamma = [], [], [], []
    for i, y in enumerate(ys):
        th = theta if i % 2 == 0 else theta[::-1]
        d = np.column_stack([-np.sin(th), np.zeros_like(th), -np.cos(th)])
        o_all.append(np.tile([sensor_x, y, sensor_z], (len(th), 1)))
        d_all.append(d)
        sweep.append(np.full(len(th), 1 if i % 2 == 0 else -1))
        gamma.append(th)
    o, d = np.concatenate(o_all), np.concatenate(d_all)
    r = world.cast(o, d).range_m
    r = r + np.random.default_rng(seed).normal(0.0, range_sigma_m, len(r)) if range_sigma_m else r
    t = np.arange(len(r)) / RATE_HZ + np.repeat(np.arange(len(ys)) * 0.5, len(theta))  # a pause between sweeps
    return Cloud(o + d * r[:, None], d, r, o, len(r), 0, sweep_dir=np.concatenate(sweep), t_s=t,
                 servo_rad=np.concatenate(gamma))


def contacts_of(cloud: Cloud, err: SensorErrorModel) -> WallContacts:
    return wall_contacts(cloud, structure_mask(cloud, STORAGE, err), STORAGE, err, CELL_M)


def beam_gap_at_wall_m(sensor_x=8.0, sensor_z=6.0, z=3.0, step_deg=0.5) -> float:
    """Vertical distance between two neighbouring beams where they meet the wall near height z."""
    th = np.arctan2(sensor_x, sensor_z - z)
    return float(sensor_x / np.tan(th) - sensor_x / np.tan(th + np.radians(step_deg)))


@pytest.mark.parametrize("top_m", [1.5, 3.0])
def test_that_the_contact_of_a_wedge_against_a_wall_is_recovered(top_m):
    c = contacts_of(swept_cloud(wedge_m(top_m)), IDEAL)
    assert len(c) == 5  # one per sweep: each reaches the wall above the wedge
    assert np.all(c.wall == 0) and np.allclose(c.xy_m[:, 0], 0.0)
    assert np.all((c.low_m <= top_m) & (top_m <= c.high_m))
    assert np.all(np.abs(c.height_m - top_m) <= beam_gap_at_wall_m(z=top_m))


def test_that_the_contact_is_recovered_within_the_range_noise():
    sigma = NOISY.range_sigma_m
    c = contacts_of(swept_cloud(wedge_m(3.0), range_sigma_m=sigma, seed=1), NOISY)
    assert len(c) >= 4
    assert np.all((c.low_m <= 3.0) & (3.0 <= c.high_m))
    assert np.all(np.abs(c.height_m - 3.0) <= beam_gap_at_wall_m() + 3 * sigma)


def test_that_a_bare_wall_foot_is_no_material():
    c = contacts_of(swept_cloud(lambda x, y: np.zeros_like(x)), IDEAL)
    assert len(c) == 5
    assert np.all(c.height_m == 0.0) and np.all(c.low_m == 0.0)


@pytest.mark.parametrize("seed", range(4))
def test_that_range_noise_does_not_create_material_at_a_bare_wall(seed):
    c = contacts_of(swept_cloud(lambda x, y: np.zeros_like(x), range_sigma_m=0.02, seed=seed), NOISY)
    assert np.all(c.height_m == 0.0) and np.all(c.low_m == 0.0)


def test_that_a_sweep_seeing_only_the_wall_makes_no_contact():
    # a sensor close to the wall, beams from 45 deg up: every one reaches the wall above the floor
    cloud = swept_cloud(lambda x, y: np.zeros_like(x), sensor_x=2.0, sensor_z=7.0, max_deg=85.0, range_sigma_m=0.02)
    keep = np.degrees(cloud.servo_rad) >= 45.0
    cloud = Cloud(cloud.points_w[keep], cloud.dirs_w[keep], cloud.range_m[keep], cloud.path_w, int(keep.sum()), 0,
                  sweep_dir=cloud.sweep_dir[keep], t_s=cloud.t_s[keep], servo_rad=cloud.servo_rad[keep])
    assert len(contacts_of(cloud, NOISY)) == 0


def test_that_one_wall_return_off_the_wall_makes_no_contact():
    """An escaped wall return (noise put it beyond the wall tolerance) between wall hits: the material
    must be seen by two beams in a row."""
    cloud = swept_cloud(lambda x, y: np.zeros_like(x), sensor_x=2.0, sensor_z=7.0)
    on_wall = np.nonzero(np.abs(cloud.points_w[:, 0]) < 1e-6)[0]
    i = on_wall[len(on_wall) // 2]
    assert i - 1 in on_wall and i + 1 in on_wall
    points = cloud.points_w.copy()
    points[i, 0] = 0.5  # half a metre into the room
    moved = Cloud(points, cloud.dirs_w, cloud.range_m, cloud.path_w, cloud.n_samples, 0, sweep_dir=cloud.sweep_dir,
                  t_s=cloud.t_s, servo_rad=cloud.servo_rad)
    before, after = contacts_of(cloud, IDEAL), contacts_of(moved, IDEAL)
    assert len(after) == len(before) == 5  # the bare feet only
    assert np.all(after.height_m == 0.0)


def test_that_pinned_contacts_fill_only_unseen_cells():
    h = np.full((4, 3), np.nan)
    h[2:, :] = 1.0
    c = WallContacts(np.array([[0.0, 0.5], [0.0, 0.6], [3.9, 0.5]]), np.array([2.0, 4.0, 9.0]),
                     np.zeros(3), np.full(3, 10.0), np.array([0, 0, 1]))
    out = pin_contacts(h, c, np.linspace(0, 4, 5), np.linspace(0, 3, 4))
    assert out[0, 0] == 3.0  # the mean of the cell's two contacts
    assert out[3, 0] == 1.0  # a seen cell keeps its fit
    assert np.isnan(out[0, 1]) and np.isnan(out[1, 0])


FLOWN = Storage(30.0, 20.0, 10.0)


def ideal_flight(family: str, top_m: float, seed: int, p_traj: float, initial_position: int):
    """A pile of the family flown at 8 m in FLOWN by the ideal plant, one servo phase: (shape, cfg, world, samples,
    header)."""
    shape = make_shape(family, FLOWN, top_m, seed)
    cfg = replace(FlyConfig(mission=Mission(storage=FLOWN, altitude_m=8.0, p_traj=p_traj)),
                  initial_position=initial_position)
    plant = IdealPlant(cfg.mission, StorageFrame())
    t = np.arange(int(plant.duration_s * cfg.lidar.rate_hz) + 1) / cfg.lidar.rate_hz
    wf = cfg.servo_waveform()
    world = World(FLOWN, shape.pile, cfg.lidar.max_range_m)
    samples = sample_flight(plant.states(t), wf, world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame, seed=[0])
    return shape, cfg, world, samples, log_header(cfg, wf)


def true_heights(world: World, grid) -> np.ndarray:
    """The pile's true height at every cell centre of grid (a beam cast down from under FLOWN's roof)."""
    cx, cy = grid.centres()
    top = FLOWN.height_m - 1e-3
    r = world.cast(np.column_stack([cx.ravel(), cy.ravel(), np.full(cx.size, top)]),
                   np.tile([0.0, 0.0, -1.0], (cx.size, 1)), max_range_m=2 * FLOWN.height_m).range_m
    return np.clip(top - np.nan_to_num(r, nan=top), 0.0, None).reshape(cx.shape)


@pytest.fixture(scope="module")
def corner_flight():
    """A corner pile (seed 0, top 6 m) flown at 8 m, P_traj 40 %, by the ideal plant, one servo phase."""
    return ideal_flight("corner", 6.0, 0, 0.40, 5)


@pytest.fixture(scope="module")
def wall_contact_survey(corner_flight):
    """corner_flight surveyed with the unseen cells filled through the wall contacts (two tests read it: one survey,
    not two)."""
    _, cfg, _, samples, header = corner_flight
    return survey_from_samples(samples, header, FLOWN, cfg.frame, np.array(cfg.lever_arm_body_m),
                               ReportOptions(plots=False, empty_cells="wall-contact"))


def test_that_the_wall_contact_fill_of_a_flown_corner_pile_beats_nearest(corner_flight, wall_contact_survey):
    """The surface through the wall contacts puts more of the unseen corner's material back than the
    nearest copy, and the volume is closer (one servo phase; over four phases at P_traj 30 and 40 %:
    Ve 1.84 -> 1.57 % mean, all eight closer)."""
    shape, cfg, world, samples, header = corner_flight
    lever = np.array(cfg.lever_arm_body_m)
    near = survey_from_samples(samples, header, FLOWN, cfg.frame, lever,
                               ReportOptions(plots=False, empty_cells="nearest"))
    wall = wall_contact_survey
    assert np.array_equal(near.heights_fit, wall.heights_fit, equal_nan=True)  # the same fit: only the fill differs
    truth = true_heights(world, near.grid)
    unseen = ~np.isfinite(near.heights_fit)
    missing_near = float((truth - near.heights)[unseen].sum())
    missing_wall = float((truth - wall.heights)[unseen].sum())
    assert 0.0 < missing_wall < 0.5 * missing_near  # measured: 0.11 against 0.80 % of the volume
    v = shape.pile.volume_m3
    assert abs(grid_volume(wall.heights, wall.grid) - v) < abs(grid_volume(near.heights, near.grid) - v)
    log = SampleLog(header=header, samples=samples, blocks_ok=1, blocks_corrupt=0, blocks_truncated=0, bytes_skipped=0)
    lo, hi = summarise(wall, log, ReportOptions(plots=False, empty_cells="wall-contact"), v)["volume_interval_m3"]
    assert lo <= v <= hi  # the interval, its unseen term bounded by the contacts' tops too, still holds the truth


def test_that_the_wall_contact_fit_from_the_points_near_the_unseen_cells_is_the_whole_clouds(corner_flight,
                                                                                             wall_contact_survey,
                                                                                             monkeypatch):
    """The report fits the surface through the contacts from the nodes near the unseen cells only (its
    speed): the filled heights are those of the fit through every node."""
    import ground.surface

    _, cfg, _, samples, header = corner_flight
    lever = np.array(cfg.lever_arm_body_m)
    opts = ReportOptions(plots=False, empty_cells="wall-contact")
    part = wall_contact_survey  # surveyed as the report does, before the monkeypatch below
    monkeypatch.setattr(ground.surface, "shaping_points", lambda xy, wanted, grid: np.ones(len(xy), dtype=bool))
    whole = survey_from_samples(samples, header, FLOWN, cfg.frame, lever, opts)
    assert (~np.isfinite(whole.heights_fit)).sum() > 100  # a real unseen corner
    np.testing.assert_allclose(part.heights, whole.heights, atol=1e-4)


def test_that_a_wide_wall_tolerance_does_not_pull_the_contact_down():
    """A sensor model stating 2 % of range puts the wedge's last half metre within the wall's tolerance
    (structure); the estimate walks up the sweep to the first hit on the wall plane, within its own two
    sigmas along the normal (times the wedge's slope) of the contact."""
    wide = SensorErrorModel(range_sigma_rel=0.02, resolution_m=0.01)
    cloud = swept_cloud(wedge_m(3.0))
    structure = structure_mask(cloud, STORAGE, wide)
    taken = structure & (cloud.points_w[:, 0] > 0.3) & (cloud.points_w[:, 2] < STORAGE.height_m - 1)
    assert taken.any()  # the mask took wedge points 0.3 m or more from the wall for wall
    c = wall_contacts(cloud, structure, STORAGE, wide, CELL_M)
    assert len(c) == 5
    assert np.all((c.low_m <= 3.0) & (3.0 <= c.high_m))
    sigma_n = 0.02 * np.hypot(8.0, 3.0) * np.sin(np.arctan2(8.0, 3.0))  # range sigma along the wall normal
    assert np.all(np.abs(c.height_m - 3.0) <= beam_gap_at_wall_m() + WALL_LIKE_SIGMAS * sigma_n * SLOPE)
    assert cloud.points_w[taken, 2].min() < 3.0 - 0.3 * SLOPE  # the lowest "wall" hit alone is further off


@pytest.mark.parametrize("sigma", [0.0, 0.02])
def test_that_the_contacts_bound_the_ground_of_their_cells_from_above(sigma):
    err = NOISY if sigma else IDEAL
    c = contacts_of(swept_cloud(wedge_m(3.0), range_sigma_m=sigma, seed=2), err)
    xe, ye = np.linspace(0, STORAGE.length_m, 81), np.linspace(0, STORAGE.width_m, 49)
    top = contact_ceiling_m(c, xe, ye)
    bounded = np.isfinite(top)
    assert bounded.sum() == 5 and np.all(np.nonzero(bounded)[0] == 0)  # the wall cells holding a contact
    cx = 0.5 * (xe[1:] + xe[:-1])
    assert np.all(top[bounded] >= wedge_m(3.0)(cx[0], 0.0))
    assert np.all(top[bounded] < 3.0 + 1.5)  # and a bound worth having (the roof is 8 m)


def test_that_a_crest_short_of_the_wall_seen_low_behind_it_makes_no_contact():
    """Material whose last hit (its crest, 1.2 m) lies above the wall seen behind it falls away unseen
    towards the wall (here to the floor 0.8 m short of it): no contact up the wall, only bare feet."""
    def crest(x, y):
        return np.clip(1.2 - 1.5 * np.abs(x - 1.6), 0.0, None)

    cloud = swept_cloud(crest, sensor_x=10.0, sensor_z=6.0, step_deg=0.25)
    wall_seen_low = (np.abs(cloud.points_w[:, 0]) < 1e-6) & (cloud.points_w[:, 2] < 1.0)
    assert wall_seen_low.any()  # the wall is seen below the crest's height, behind it
    c = contacts_of(cloud, IDEAL)
    assert np.all(c.height_m == 0.0)


def test_that_a_crest_a_pointing_error_lets_pass_as_leaning_is_not_leaning_as_measured():
    """A crest 3 m high, 2.5 m from the wall, seen over by a beam that meets the wall near 2 m: the ground behind it
    falls to the floor unseen. A sensor model stating a 1 deg pointing error lets the pair pass the leaning test
    within its noise allowance (a false contact 2 m up the wall, as measured under Appendix A's noise); it is
    flagged as not leaning as measured, and `measured_leaning` leaves it out."""
    def crest(x, y):
        return np.clip(3.0 - 1.5 * np.abs(x - 2.5), 0.0, None)

    pointing = SensorErrorModel(resolution_m=0.01, angle_sigma_rad=np.radians(1.0))
    cloud = swept_cloud(crest, sensor_x=12.0, sensor_z=7.0, step_deg=0.25)
    c = wall_contacts(cloud, structure_mask(cloud, STORAGE, pointing), STORAGE, pointing, CELL_M)
    assert len(c) == 5 and np.all(c.height_m > 1.0)  # the false contacts the allowance lets through (truth: 0)
    assert not c.leans_as_measured.any()
    assert len(c.measured_leaning()) == 0


def test_that_a_wedge_leans_on_the_wall_as_measured():
    c = contacts_of(swept_cloud(wedge_m(3.0)), IDEAL)
    assert len(c) == 5 and c.leans_as_measured.all()
    assert len(c.measured_leaning()) == 5


def test_that_a_pointing_error_does_not_take_material_at_a_far_wall_for_the_floor():
    """Seen from across the room, a pointing error's sigma at the wall is metres; the beam short of the wall hit the
    material 1.5 m up, which is no floor hit, so the contact holds the material's height, not 0."""
    pointing = SensorErrorModel(resolution_m=0.01, angle_sigma_rad=np.radians(2.0))
    cloud = swept_cloud(wedge_m(1.5), sensor_x=18.0, sensor_z=6.0)
    c = wall_contacts(cloud, structure_mask(cloud, STORAGE, pointing), STORAGE, pointing, CELL_M, floor_by_plane=True)
    assert len(c) == 5
    assert np.all(np.abs(c.height_m - 1.5) <= beam_gap_at_wall_m(sensor_x=18.0, z=1.5))
    assert np.all(contacts_of(cloud, pointing).height_m == 0.0)  # the default's test, kept until the switch
