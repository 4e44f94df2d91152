import json

import numpy as np
import pytest

from firmware_py.core.cli import UserError
from firmware_py.core.samplelog import SampleFlags, read_samplelog
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    fly(FlyConfig(mission=Mission(p_traj=0.25)), out, force=True)
    return out


def test_that_a_run_directory_holds_log_truth_and_mesh(run_dir):
    assert {p.name for p in run_dir.iterdir()} >= {"samples.pslog", "truth.json", "pile.stl"}
    truth = json.loads((run_dir / "truth.json").read_text())
    assert truth["true_volume_m3"] == pytest.approx(7193.5, rel=0.02)
    assert truth["mission"]["p_traj"] == 0.25 and truth["storage"]["length_m"] == 60
    assert truth["pile_seed"] is not None and truth["seed"] == 0


def test_that_the_log_samples_at_500_hz_with_the_header_the_ground_needs(run_dir):
    log = read_samplelog(run_dir / "samples.pslog")
    assert log.intact
    s = log.samples
    assert np.allclose(np.diff(s["t_s"]), 0.002)
    assert log.header["storage"] == {"length_m": 60.0, "width_m": 40.0, "height_m": 15.0}
    assert {"storage_frame", "lever_arm_body_m", "sensor", "servo", "mission_id"} <= log.header.keys()
    assert np.all(np.abs(s["servo_rad"]) <= np.pi / 2 + 1e-6)
    ok = s["flags"] == 0
    assert np.allclose(s["range_m"][ok] * 100, np.round(s["range_m"][ok] * 100), atol=1e-3)  # 1 cm
    assert np.all(s["range_m"][ok] <= 40.0)


def test_that_rays_without_echo_read_1_cm_and_are_flagged(tmp_path):
    # A 100 m long hall: beams along the length at the far ends see nothing within 40 m.
    from firmware_py.core.storage import Storage
    fly(FlyConfig(mission=Mission(storage=Storage(100, 40, 15), p_traj=0.3)), tmp_path)
    s = read_samplelog(tmp_path / "samples.pslog").samples
    nr = (s["flags"] & SampleFlags.NO_RETURN) != 0
    assert nr.any()
    assert np.allclose(s["range_m"][nr], 0.01)


def test_that_flights_are_deterministic(tmp_path):
    cfg = FlyConfig(mission=Mission(p_traj=0.3), initial_position=13)
    fly(cfg, tmp_path / "a")
    fly(cfg, tmp_path / "b")
    a = read_samplelog(tmp_path / "a" / "samples.pslog").samples
    b = read_samplelog(tmp_path / "b" / "samples.pslog").samples
    assert np.array_equal(a, b)


def test_that_an_existing_run_is_not_overwritten_without_force(run_dir):
    with pytest.raises(UserError, match="already holds a run"):
        fly(FlyConfig(mission=Mission(p_traj=0.25)), run_dir)


def test_that_a_flight_into_the_pile_is_refused(tmp_path):
    with pytest.raises(ValueError, match="stockpile top"):
        fly(FlyConfig(mission=Mission(p_traj=0.25, altitude_m=7.0)), tmp_path)


def _log_without_creation_time(path):
    log = read_samplelog(path)
    return {k: v for k, v in log.header.items() if k != "created_utc"}, log.samples.tobytes()


def test_that_no_sensor_noise_flies_exactly_as_before_and_a_noise_model_is_recorded(tmp_path):
    from firmware_py.core.sensor_noise import SensorNoise
    base = dict(mission=Mission(p_traj=0.3), plant="ideal", seed=5)
    fly(FlyConfig(**base), tmp_path / "default")
    fly(FlyConfig(**base, sensor_noise="none"), tmp_path / "none")
    fly(FlyConfig(**base, sensor_noise="datasheet"), tmp_path / "datasheet")
    default = _log_without_creation_time(tmp_path / "default" / "samples.pslog")
    assert _log_without_creation_time(tmp_path / "none" / "samples.pslog") == default
    assert "sensor_noise" not in default[0]
    assert (tmp_path / "none" / "truth.json").read_text() == (tmp_path / "default" / "truth.json").read_text()
    header, samples = _log_without_creation_time(tmp_path / "datasheet" / "samples.pslog")
    want = SensorNoise.of("datasheet", FlyConfig().lidar).record()
    assert header["sensor_noise"] == want and samples != default[1]
    assert json.loads((tmp_path / "datasheet" / "truth.json").read_text())["sensor_noise"] == want
