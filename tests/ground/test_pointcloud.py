from dataclasses import fields, replace

import numpy as np

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame
from firmware_py.core.samplelog import SampleFlags, new_records, read_samplelog
from firmware_py.core.storage import Storage
from ground.despike import SpikeThreshold
from ground.pointcloud import (
    Cloud,
    SensorErrorModel,
    beside_walls,
    cloud_from_samples,
    plane_tolerances_m,
    posed_beams,
    structure_mask,
)
from tests.ground.test_live_state import GOLDEN


def _samples(n):
    s = new_records(n)
    s["x_m"], s["y_m"], s["z_m"] = 10.0, 5.0, -12.0
    s["range_m"] = 12.0
    return s


def test_that_flagged_and_non_finite_samples_stay_out_of_the_cloud():
    s = _samples(6)
    s["flags"][1] = SampleFlags.NO_RETURN
    s["flags"][2] = SampleFlags.STALE_POSE
    s["range_m"][3] = np.nan
    s["yaw_rad"][4] = np.inf
    c = cloud_from_samples(s, [0, 0, 0], StorageFrame())
    assert len(c.points_w) == 2 and c.n_excluded == 4
    assert np.allclose(c.points_w, [[10, -5, 0]] * 2)  # NED (10, 5) -> W (10, -5) at heading 0


def test_that_wall_and_roof_points_are_recognised_within_their_error():
    st = Storage(20, 10, 8)
    s = _samples(5)
    frame = StorageFrame((0, 0, 0), np.pi / 2)  # W: x east, y north
    s["x_m"], s["y_m"], s["z_m"] = 5.0, 10.0, -4.0  # W (10, 5, 4), middle of the hall
    s["servo_rad"] = [np.pi / 2, -np.pi / 2, 0.0, np.pi / 2, 0.0]
    s["yaw_rad"] = [np.pi / 2, np.pi / 2, np.pi / 2, 0.0, np.pi]  # facing +x_W, +x_W, .., +y_W, -y_W
    s["pitch_rad"][4] = 0.0
    s["range_m"] = [5.0, 5.0, 4.0, 10.0, 4.0]
    s["roll_rad"][4] = np.pi  # upside down: the beam points up at the roof
    c = cloud_from_samples(s, [0, 0, 0], frame)
    ideal = structure_mask(c, st, SensorErrorModel())
    # starboard wall, port wall, floor (not structure), far end wall, roof
    assert ideal.tolist() == [True, True, False, True, True]
    # A point 5 cm off the wall is structure only for a sensor whose errors allow it.
    s["range_m"][0] = 4.95
    c = cloud_from_samples(s, [0, 0, 0], frame)
    assert not structure_mask(c, st, SensorErrorModel(resolution_m=0.01))[0]
    assert structure_mask(c, st, SensorErrorModel(range_sigma_m=0.025))[0]


def test_that_the_wall_tolerance_grows_with_the_cloud_so_no_wall_point_escapes_by_chance():
    from statistics import NormalDist

    import pytest

    from ground.pointcloud import N_SIGMA, Cloud, structure_n_sigma
    assert structure_n_sigma(1) == N_SIGMA  # a lone point keeps the 3 sigma floor
    for n in (60_000, 1_000_000):
        k = structure_n_sigma(n)
        assert k > N_SIGMA and n * (1 - NormalDist().cdf(k)) == pytest.approx(0.01, rel=1e-6)
    # 100,000 returns from the wall x = 0, 12 m away head on, with a 20 cm range error: none is kept as pile.
    rng = np.random.default_rng(0)
    n = 100_000
    x = rng.normal(0.0, 0.2, n)
    p = np.column_stack([x, np.full(n, 20.0), np.full(n, 8.0)])
    d = np.tile([-1.0, 0.0, 0.0], (n, 1))
    c = Cloud(p, d, 12.0 - x, np.empty((0, 3)), n, 0)
    st, err = Storage(60, 40, 15), SensorErrorModel(range_sigma_m=0.2)
    assert (~structure_mask(c, st, err, n_sigma=N_SIGMA)).sum() > 50  # 3 sigma lets ~135 through ...
    assert (~structure_mask(c, st, err)).sum() == 0  # ... the survey-sized tolerance none


def test_that_a_point_at_a_walls_foot_that_fits_the_floor_is_ground_not_wall():
    """A return on the floor beside a wall, a beam slanting towards it: within the wall's tolerance, but as
    much a floor return at height 0, so it is kept (the pile's toe and the floor along the walls are seen);
    the same beam's point 1 m up the wall is wall."""
    d = np.array([[-0.6, 0.0, -0.8], [-0.6, 0.0, -0.8]])
    p = np.array([[0.05, 20.0, 0.0], [0.05, 20.0, 1.0]])
    c = Cloud(p, d, np.array([15.0, 14.0]), np.empty((0, 3)), 2, 0)
    err = SensorErrorModel(range_sigma_m=0.025, range_sigma_rel=0.01)
    assert structure_mask(c, Storage(60, 40, 15), err).tolist() == [False, True]


def test_that_the_error_model_takes_the_larger_of_the_spec_and_the_noise_record():
    from firmware_py.core.sensor import LIDARLITE_V3
    from firmware_py.core.sensor_noise import SensorNoise
    rec = SensorNoise.of("appendix-a", LIDARLITE_V3).record()
    m = SensorErrorModel.from_header({"sensor": LIDARLITE_V3.to_dict(), "sensor_noise": rec})
    assert (m.range_sigma_m, m.range_sigma_rel, m.position_sigma_m) == (0.025, 0.01, 0.113)
    m = SensorErrorModel.from_header({"sensor": LIDARLITE_V3.to_dict(), "pose": {"position_sigma_m": 0.3},
                                      "sensor_noise": rec})
    assert m.position_sigma_m == 0.3


def _stretch(vehicle, points, dt_s=0.002):
    """A cloud of one unbroken stretch of sweep: the points in order, their beams from the vehicle."""
    p = np.asarray(points, dtype=float)
    beam = p - np.asarray(vehicle, dtype=float)
    rng = np.linalg.norm(beam, axis=1)
    return Cloud(p, beam / rng[:, None], rng, np.empty((0, 3)), len(p), 0,
                 sweep_dir=np.ones(len(p), dtype=np.int8), t_s=dt_s * np.arange(len(p)))


STORE = Storage(40.0, 25.0, 10.0)
EXACT = SensorErrorModel(resolution_m=0.01)


def test_that_a_wall_seen_at_grazing_incidence_off_its_plane_is_the_wall_not_a_pile():
    # A sweep at a corner turn runs 21 m along the wall x = 0, nearly parallel to it; a heading 0.6 deg off puts
    # the line it draws up that wall 0.23 m inside the building (measured on a VIO flight: a 6 m sliver of
    # "material", 2.6 m3 on a 136 m3 cone). The wall's tolerance at that incidence is a centimetre.
    z = np.linspace(0.3, 6.0, 60)
    line = np.column_stack([np.full_like(z, 0.23), 2.5 + 0.09 * z, z])
    mask = structure_mask(_stretch([2.2, 23.9, 6.9], line), STORE, EXACT)
    assert mask[16:-16].all()  # every point with a whole stretch either side
    assert plane_tolerances_m(_stretch([2.2, 23.9, 6.9], line), EXACT)[:, 0].max() < 0.05  # the old test's


def test_that_a_pile_leaning_on_a_wall_keeps_its_points_beside_the_wall():
    # The sweep climbs the pile's 31 deg flank to where it meets the wall y = 25, then goes on up the wall: a
    # stretch across the contact has most of its points on the wall, and the datasheet's 2.5 cm range sigma lets
    # such an L pass for a line by its scatter (measured on a wall pile of the evaluation set: 5 pile points
    # taken, Ve -0.06 -> -0.21 %). The point itself must lie on the line.
    s = np.linspace(0.0, 1.2, 40)
    slope = np.radians(31)
    flank = np.column_stack([np.full_like(s, 19.4), 25.0 - (1.2 - s) * np.cos(slope), 9.2 - (1.2 - s) * np.sin(slope)])
    up_wall = np.column_stack([np.full(40, 19.4), np.full(40, 25.0), np.linspace(9.25, 10.4, 40)])
    cloud = _stretch([19.4, 22.3, 12.0], np.vstack([flank, up_wall]))
    err = SensorErrorModel(range_sigma_m=0.025, range_sigma_rel=0.01)
    kept = ~structure_mask(cloud, STORE, err)
    assert kept[:36].all()  # the last few, within 10 cm of the wall, are within its range tolerance, as before
    assert not beside_walls(cloud, STORE, err)[:40].any()


def test_that_a_vertical_face_away_from_the_walls_is_left_to_the_surface():
    # A box's vertical face 6 m from the nearest wall, seen from 3 m: beyond what a heading error moves a wall.
    z = np.linspace(0.2, 4.0, 60)
    face = np.column_stack([np.full_like(z, 6.0), 12.0 + 0.01 * z, z])
    assert not structure_mask(_stretch([9.0, 12.0, 7.0], face), STORE, EXACT).any()


def test_that_a_stretch_broken_in_time_says_nothing():
    # The same grazing line, its samples in bursts 5 s apart (gaps in the log): no unbroken stretch, no claim.
    z = np.linspace(0.3, 6.0, 60)
    line = np.column_stack([np.full_like(z, 0.23), 2.5 + 0.09 * z, z])
    cloud = _stretch([2.2, 23.9, 6.9], line)
    gaps = np.cumsum(np.where(np.arange(60) % 20 == 0, 5.0, 0.002))
    assert not structure_mask(replace(cloud, t_s=gaps), STORE, EXACT).any()


def _clouds_equal(a: Cloud, b: Cloud) -> bool:
    """Every field of two clouds the same, to the bit."""
    return all(np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y
               for x, y in ((getattr(a, f.name), getattr(b, f.name)) for f in fields(Cloud)))


def _golden():
    log = read_samplelog(GOLDEN / "samples.pslog")
    return log.samples, log.header


def test_that_posed_beams_place_the_samples_at_other_servo_angles_as_cloud_from_samples_does():
    s, header = _golden()
    spikes = SpikeThreshold.from_header(header)
    lever, frame, tilted = [0.05, 0.0, 0.1], StorageFrame((1.0, -2.0, 0.0), 0.3), Boresight(0.02, -0.01)
    other = s.copy()
    other["servo_rad"] = s["servo_rad"] * 0.95 + 0.01  # what a re-timed servo's search tries
    other["sweep_dir"] = -s["sweep_dir"]
    posed = posed_beams(s, lever, frame, spike_threshold=spikes)
    assert posed.n_spikes > 0 or posed.usable.sum() < len(s)  # the golden log has samples left out
    for boresight in (SQUARE, tilted):
        assert _clouds_equal(posed.cloud(other["servo_rad"], other["sweep_dir"], boresight),
                             cloud_from_samples(other, lever, frame, spike_threshold=spikes, boresight=boresight))
        assert _clouds_equal(posed.cloud(s["servo_rad"], s["sweep_dir"], boresight),
                             cloud_from_samples(s, lever, frame, spike_threshold=spikes, boresight=boresight))


def test_that_posed_beams_leave_angles_they_cannot_take_as_they_are_to_cloud_from_samples():
    s, header = _golden()
    spikes, period = SpikeThreshold.from_header(header), 1.0 / header["servo"]["frequency_hz"]
    broken = s.copy()
    broken["servo_rad"][100:140] = np.nan  # not finite where the logged ones are: the spikes judged without them
    posed = posed_beams(s, [0, 0, 0], StorageFrame(), spike_threshold=spikes)
    assert _clouds_equal(posed.cloud(broken["servo_rad"], broken["sweep_dir"]),
                         cloud_from_samples(broken, [0, 0, 0], StorageFrame(), spike_threshold=spikes))
    frozen = s.copy()
    frozen["range_m"][:1500] = 10.0  # ranges a stuck servo gives, judged against the angles' turn
    still = frozen.copy()
    still["servo_rad"][:1500] = s["servo_rad"][0]  # angles that do not turn: nothing to judge the ranges against
    posed = posed_beams(frozen, [0, 0, 0], StorageFrame(), period, spikes)
    placed = cloud_from_samples(still, [0, 0, 0], StorageFrame(), period, spikes)
    assert posed.n_servo_suspect > 0 and placed.n_servo_suspect == 0
    assert _clouds_equal(posed.cloud(still["servo_rad"], still["sweep_dir"]), placed)
    unlogged = s.copy()
    unlogged["servo_rad"][7] = np.nan  # the logged angles themselves, one missing, are the logged ones
    assert cloud_from_samples(unlogged, [0, 0, 0], StorageFrame(), period, spikes).n_excluded == \
        cloud_from_samples(s, [0, 0, 0], StorageFrame(), period, spikes).n_excluded + int(s["flags"][7] == 0)
