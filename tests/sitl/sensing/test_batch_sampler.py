"""The batch sample path: ideal sensing, and the sensor-noise models on what is logged."""

import math

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from sitl.sensing.batch_sampler import sample_flight
from sitl.vehicle.ideal_plant import Trajectory
from sitl.world.raycast import World

LIDAR = LIDARLITE_V3.with_(resolution_m=0.0)


def hover(n=20_000):
    t = np.arange(n) / 500.0
    pos = np.tile([20.0, -15.0, -12.0], (n, 1))  # NED: over the middle of the empty building's floor
    z = np.zeros(n)
    return Trajectory(t, pos, z, z, z + 0.3)


def sample(model=SensorNoiseModel.NONE, seed=0, lidar=LIDAR):
    return sample_flight(hover(), named_waveform("semi-triangular"), World(Storage()), lidar, (0.0, 0.0, 0.1),
                         StorageFrame(), noise=SensorNoise.of(model, lidar), seed=seed)


def test_that_ideal_sensing_logs_the_true_geometry():
    rec = sample()
    assert np.all(rec["x_m"] == 20.0) and np.all(rec["yaw_rad"] == pytest.approx(0.3))
    gamma = named_waveform("semi-triangular").angle(rec["t_s"])
    assert np.allclose(rec["servo_rad"], gamma, atol=1e-6)


def test_that_no_noise_is_exactly_the_noise_free_path():
    none = sample()
    plain = sample_flight(hover(), named_waveform("semi-triangular"), World(Storage()), LIDAR, (0.0, 0.0, 0.1),
                          StorageFrame())
    assert none.tobytes() == plain.tobytes()


def test_that_appendix_a_noise_puts_the_papers_sigmas_on_the_logged_pose_and_range_and_repeats_with_its_seed():
    clean, noisy = sample(), sample(SensorNoiseModel.APPENDIX_A, seed=3)
    # The servo error moves the true beam; the firmware logs its model of the shaft: the logged angle is exact.
    assert np.array_equal(noisy["servo_rad"], clean["servo_rad"])
    # Pose: one draw per 50 Hz message, interpolated between the two on either side of each 500 Hz sample, as
    # the payload's pose buffer does: the logged error's variance is the mean of (1-f)^2 + f^2 over the samples.
    for field, sigma in (("roll_rad", math.radians(0.143)), ("yaw_rad", math.radians(0.143)), ("z_m", 0.113)):
        d = noisy[field].astype(float) - clean[field].astype(float)
        assert abs(d.mean()) < 0.2 * sigma, field
        assert d.std() == pytest.approx(sigma * 0.82, rel=0.15), field  # 10 samples a period: mean over f = k/10
    assert np.array_equal(sample(SensorNoiseModel.APPENDIX_A, seed=3), noisy)
    assert not np.array_equal(sample(SensorNoiseModel.APPENDIX_A, seed=4), noisy)


def test_that_datasheet_noise_leaves_the_pose_and_the_servo_exact_and_drops_far_grazing_returns():
    clean, noisy = sample(), sample(SensorNoiseModel.DATASHEET, seed=1)
    for field in ("servo_rad", "x_m", "roll_rad", "yaw_rad"):
        assert np.array_equal(noisy[field], clean[field]), field
    near = (clean["flags"] == 0) & (np.abs(clean["servo_rad"]) < math.radians(20))  # floor at 12-13 m, head on
    far = (clean["flags"] == 0) & (np.abs(clean["servo_rad"]) > math.radians(75))  # walls and floor, far, grazing
    assert (noisy["flags"][near] != 0).mean() < 0.001
    assert (noisy["flags"][far] != 0).mean() > 0.3
