"""Self-calibration on noisy flights (`--sensor-noise datasheet`): the noise leaves a square mount alone
and still lets a wrong one be found. The paper's building and pile 2, whose material covers the floor
wall to wall: there the pile's points next to the walls biased the fit into false corrections
(docs/sensor_noise.md); this start position and seed gave one (servo offset +2.1 deg, scale -3.7 %)
before the correction had to bring the planes' own points back. The faulted flight and its square twin
fly the small building: any building's floor and walls find the fault."""

import math

import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import read_samplelog
from firmware_py.core.sensor_noise import SensorNoiseModel
from firmware_py.core.storage import Storage
from ground.pointcloud import SensorErrorModel
from ground.report import ReportOptions, make_report
from ground.self_calibration import estimate_mount
from ground.servo_timing import Resimulated
from sitl.faults.injector import FaultSpec
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tools.pose_correction_campaign import signed_error_pct

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)

SKEW = FaultSpec(servo_offset_deg=3.0, servo_scale_pct=5.0, boresight_deg=2.0)


PAPER = Mission(p_traj=0.2)
SMALL = Mission(storage=Storage(30, 20, 10), p_traj=0.2, altitude_m=8.0, speed_m_s=2.0)
"""A quarter of the paper's floor at twice the speed: an eighth of its flight, the same planes in every sweep."""


def _fly(path, faults=None, payload="batch", initial_position=0, mission=PAPER):
    cfg = FlyConfig(mission=mission, stockpile="2", faults=faults, payload=payload,
                    initial_position=initial_position, sensor_noise=SensorNoiseModel.DATASHEET)
    fly(cfg, path / "run", force=True, progress=lambda _m: None)
    return path / "run"


def _estimate(run):
    log = read_samplelog(run / "samples.pslog")
    h, s = log.header, log.samples[log.samples["flags"] == 0]
    err = SensorErrorModel.from_header(h)
    return estimate_mount(s, h["lever_arm_body_m"], StorageFrame(), Storage(**h["storage"]), err.range_sigma_m,
                          err.range_sigma_rel, Resimulated.from_header(h), angle_sigma_rad=err.angle_sigma_rad)


def _applied(report: dict) -> bool:
    return any(isinstance(v, dict) and v.get("applied") for v in report["self_calibration"].values())


@pytest.fixture(scope="module")
def biased_run(tmp_path_factory):
    """Square, the ideal servo of the batch payload, start position 5: the fit comes out biased."""
    return _fly(tmp_path_factory.mktemp("noisy-biased"), initial_position=5)


@pytest.fixture(scope="module")
def square_run(tmp_path_factory):
    return _fly(tmp_path_factory.mktemp("noisy-square"), mission=SMALL)


@pytest.fixture(scope="module")
def skewed_run(tmp_path_factory):
    return _fly(tmp_path_factory.mktemp("noisy-skewed"), SKEW, mission=SMALL)


def test_that_a_noisy_fault_free_flight_gets_no_correction(biased_run, tmp_path):
    est = _estimate(biased_run)
    assert est.reason is None and not est.any_applied
    # The pile's toe points no longer reach the fit (only stretches of sweep along a plane may be a plane's, and
    # a band holds no more points inside the building than outside): the estimate is square, not a biased one
    # refused (it was +2.1 deg and -3.7 %, refused for holding the planes with points inside).
    assert abs(math.degrees(est.values[0])) < 0.2 and abs(est.values[1]) < 0.005
    rep = make_report(biased_run, tmp_path / "rep", ReportOptions(plots=False))
    assert not _applied(rep)
    assert not any("self-calibration from the building applied" in w for w in rep["warnings"])


def test_that_a_noisy_faulted_flight_is_still_corrected(skewed_run, square_run, tmp_path):
    est = _estimate(skewed_run)
    offset, scale, _, _ = est.values
    assert est.applied[:2] == (True, True) and est.refused is None
    assert math.degrees(offset) == pytest.approx(3.0, abs=0.2)
    assert scale == pytest.approx(0.05, abs=0.005)
    clean = make_report(square_run, tmp_path / "clean", ReportOptions(plots=False))
    fixed = make_report(skewed_run, tmp_path / "fixed", ReportOptions(plots=False))
    raw = make_report(skewed_run, tmp_path / "raw", ReportOptions(plots=False, self_calibration=False))
    assert not _applied(clean) and _applied(fixed)
    # Closer to the square mount's volume than uncorrected (measured: 0.11 against 1.52 pp; in the paper's
    # building at 1 m/s, 0.30 against 0.39 pp).
    assert abs(signed_error_pct(fixed) - signed_error_pct(clean)) < abs(signed_error_pct(raw) - signed_error_pct(clean))


def test_that_a_square_mount_under_appendix_a_noise_is_not_corrected(tmp_path):
    """Appendix A's noise, the payload in the loop, start position 0, seed 0: the fit once found a servo offset
    of 3.0 +- 0.17 deg and a scale of -5.0 +- 0.2 %, 'significant', from the pile's toe points in the floor's
    window; applied, it read pile 2 5.4 % high instead of 0.9 %. A guard (a correction must bring the planes'
    own points closer) refused it; the toe's points are now kept out of the fit (only stretches of sweep along
    a plane, a band no fuller inside than outside), and what is left of the estimate is refused too."""
    cfg = FlyConfig(mission=Mission(p_traj=0.2), stockpile="2", payload="firmware", initial_position=0,
                    sensor_noise=SensorNoiseModel.APPENDIX_A, seed=0)
    fly(cfg, tmp_path / "run", force=True, progress=lambda _m: None)
    rep = make_report(tmp_path / "run", tmp_path / "report", ReportOptions(plots=False))
    cal = rep["self_calibration"]
    assert not _applied(rep)
    assert cal["refused"] is None or cal["refused"].startswith("not applied: ")
    assert abs(cal["servo_offset_deg"]["estimate"]) < 2.5  # 3.0 deg with the toe's points; measured 1.7 without
    assert abs(signed_error_pct(rep)) < 2.0
