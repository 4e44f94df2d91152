import numpy as np

from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleFlags, new_records
from firmware_py.core.storage import Storage
from ground.pointcloud import SensorErrorModel, cloud_from_samples, structure_mask


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
    from ground.pointcloud import Cloud
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
