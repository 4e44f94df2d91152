"""The batch sample path: ideal sensing, and the paper's Appendix A noise on what is logged."""

import math

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from sitl.sensing.batch_sampler import NoiseSpec, sample_flight
from sitl.vehicle.ideal_plant import Trajectory
from sitl.world.raycast import World


def hover(n=20_000):
    t = np.arange(n) / 500.0
    pos = np.tile([20.0, -15.0, -12.0], (n, 1))  # NED: over the middle of the empty building's floor
    z = np.zeros(n)
    return Trajectory(t, pos, z, z, z + 0.3)


def sample(noise=None, seed=0):
    return sample_flight(hover(), named_waveform("semi-triangular"), World(Storage()),
                         LIDARLITE_V3.with_(resolution_m=0.0), (0.0, 0.0, 0.1), StorageFrame(), noise=noise,
                         rng=np.random.default_rng(seed))


def test_that_ideal_sensing_logs_the_true_geometry():
    rec = sample()
    assert np.all(rec["x_m"] == 20.0) and np.all(rec["yaw_rad"] == pytest.approx(0.3))
    gamma = named_waveform("semi-triangular").angle(rec["t_s"])
    assert np.allclose(rec["servo_rad"], gamma, atol=1e-6)


def test_that_appendix_a_noise_has_the_papers_sigmas_and_repeats_with_its_seed():
    clean, noisy = sample(), sample(NoiseSpec(), seed=3)
    ok = (clean["flags"] == 0) & (noisy["flags"] == 0)
    spec = NoiseSpec()
    for field, sigma in (("range_m", spec.range_sigma_m), ("servo_rad", math.radians(1.0)),
                         ("roll_rad", math.radians(0.143)), ("yaw_rad", math.radians(0.143)), ("z_m", 0.113)):
        d = noisy[field][ok].astype(float) - clean[field][ok].astype(float)
        assert abs(d.mean()) < 0.05 * sigma
        assert d.std() == pytest.approx(sigma, rel=0.05), field
    assert np.array_equal(sample(NoiseSpec(), seed=3), noisy)
    assert not np.array_equal(sample(NoiseSpec(), seed=4), noisy)


def test_that_negative_noise_is_refused():
    with pytest.raises(ValueError, match="position_sigma_m"):
        NoiseSpec(position_sigma_m=-1.0)
