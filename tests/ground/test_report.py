"""End to end: ideal flight -> sample log -> ground report, against the known truth."""

import json
import math
import shutil

import numpy as np
import pytest

from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.site import DEFAULT_SITE, Site
from firmware_py.core.storage import Storage
from ground.report import ReportOptions, make_report
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tests.sitl.conftest import frustum_mesh

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)

REQUIRED_KEYS = {"volume_m3", "true_volume_m3", "volume_error_pct", "coverage_ratio_pct", "n_samples",
                 "n_points_used"}


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory):
    """Pile 1 in the paper's building at P_traj 10 %, flown once for the tests that only read it."""
    out = tmp_path_factory.mktemp("paper") / "run"
    fly(FlyConfig(mission=Mission(p_traj=0.1)), out)
    return out


SMALL = Mission(storage=Storage(30, 20, 10), altitude_m=9.0, p_traj=0.2)


@pytest.fixture(scope="module")
def small_noisy_run(tmp_path_factory):
    """A small building flown once under Appendix A's noise, for the tests that only read it."""
    out = tmp_path_factory.mktemp("small-noisy") / "noisy"
    fly(FlyConfig(mission=SMALL, plant="ideal", sensor_noise="appendix-a", seed=1), out)
    return out


@pytest.fixture(scope="module")
def paper_report(paper_run, tmp_path_factory):
    """The report of paper_run's log alone (no truth.json beside it), made once for the tests that only read it."""
    return make_report(paper_run / "samples.pslog", tmp_path_factory.mktemp("paper-report") / "rep",
                       ReportOptions(plots=False))


@pytest.mark.parametrize("pile", ["1", "2"])
def test_that_paper_piles_at_p_traj_5_come_within_1_percent(tmp_path, pile):
    fly(FlyConfig(mission=Mission(p_traj=0.05), stockpile=pile), tmp_path / "run")
    rep = make_report(tmp_path / "run", tmp_path / "rep", ReportOptions(plots=False))
    assert rep["volume_error_pct"] < 1.0
    assert rep["coverage_ratio_pct"] > 99.0
    assert REQUIRED_KEYS <= rep.keys()


def test_that_a_cone_stl_comes_within_2_percent(tmp_path):
    """In the paper's building at 2 m/s: the STL's volume, not the sampling density, is what this reads."""
    path = tmp_path / "cone.stl"
    frustum_mesh(12.0, 2.0, 6.0, (30.0, 20.0)).export(path)
    fly(FlyConfig(mission=Mission(p_traj=0.2, speed_m_s=2.0), stockpile=str(path)), tmp_path / "run")
    rep = make_report(tmp_path / "run", tmp_path / "rep", ReportOptions(plots=False))
    assert rep["true_volume_m3"] == pytest.approx(math.pi * 6 / 3 * (144 + 24 + 4), rel=1e-3)
    assert rep["volume_error_pct"] < 2.0


def test_that_the_result_does_not_depend_on_where_the_building_sits_in_ned(tmp_path, paper_report):
    """The second building's corner is 20 m south, 35 m east and 0.4 m below the EKF origin, turned 123 deg. The
    first is paper_run's, at the default site (its report without the truth: the volume is the same)."""
    mission = Mission(p_traj=0.1)
    ekf = DEFAULT_SITE.corner
    corner = GeodeticPoint(*ekf.to_global(-20.0, 35.0), ekf.alt_m - 0.4)
    placed = FlyConfig(mission=mission, site=Site(corner, math.radians(123)), ekf_origin_at=ekf)
    assert placed.frame.origin_ned_m == pytest.approx((-20.0, 35.0, 0.4), abs=1e-6)
    fly(placed, tmp_path / "placed")
    rep = make_report(tmp_path / "placed", tmp_path / "rep", ReportOptions(plots=False))
    assert paper_report["volume_m3"] == pytest.approx(rep["volume_m3"], rel=1e-4)
    assert rep["volume_error_pct"] < 1.0


def test_that_a_full_report_writes_every_output(tmp_path):
    """The small building at 2 m/s: what is written, not the survey, is what this reads."""
    fly(FlyConfig(mission=Mission(storage=Storage(30, 20, 10), altitude_m=9.0, p_traj=0.1, speed_m_s=2.0)),
        tmp_path / "run")
    rep = make_report(tmp_path / "run", tmp_path / "rep")
    names = {p.name for p in (tmp_path / "rep").iterdir()}
    assert {"report.json", "report.md", "report.html", "cloud.ply", "cloud_top.png", "height_map.png",
            "coverage.png"} <= names
    on_disk = json.loads((tmp_path / "rep" / "report.json").read_text())
    assert on_disk["volume_m3"] == pytest.approx(rep["volume_m3"])
    assert f"{rep['volume_m3']:,.1f}" in (tmp_path / "rep" / "report.md").read_text()
    # what the autopilot's EKF took the pose from, as the log header says: stated, kept, and no warning for GNSS
    assert rep["pose_source"] == "position GNSS; height barometer (ArduPilot EKF3, source set 1)"
    assert rep["autopilot_params"]["EK3_SRC1_POSZ"] == 1.0
    assert "Pose source (autopilot EKF)" in (tmp_path / "rep" / "report.md").read_text()
    assert not any("autopilot's" in w for w in rep["warnings"])


def test_that_a_log_cut_by_a_power_failure_still_reports_with_a_warning(tmp_path, paper_run):
    shutil.copytree(paper_run, tmp_path / "run")  # cut a copy: the flight is shared
    log = tmp_path / "run" / "samples.pslog"
    data = log.read_bytes()
    log.write_bytes(data[: len(data) * 2 // 3 + 17])
    rep = make_report(tmp_path / "run", tmp_path / "rep", ReportOptions(plots=False))
    assert rep["log"]["blocks_truncated"] == 1 and rep["log"]["closed_cleanly"] is False
    assert any("damaged" in w for w in rep["warnings"])
    assert sum("the sample log was not closed" in w for w in rep["warnings"]) == 1
    assert rep["n_samples"] < 0.7 * (len(data) / 59)
    unseen = [w for w in rep["warnings"] if "never seen" in w]  # a third of the flight is missing
    assert len(unseen) == 1 and "x 0-27 m" in unseen[0]
    lo, hi = rep["volume_interval_m3"]
    assert lo < rep["volume_m3"] < hi


def test_that_a_log_its_payload_closed_says_so_and_is_not_warned_of(paper_report):
    assert paper_report["log"]["closed_cleanly"] is True
    assert not any("not closed" in w for w in paper_report["warnings"])


def test_that_the_truth_can_be_given_or_absent(tmp_path, paper_run, paper_report):
    log = paper_run / "samples.pslog"
    rep = paper_report  # the log alone
    assert rep["true_volume_m3"] is None and rep["volume_error_pct"] is None
    rep = make_report(log, tmp_path / "b", ReportOptions(plots=False, truth_volume_m3=rep["volume_m3"] * 1.1))
    assert rep["volume_error_pct"] == pytest.approx(100 / 11, rel=1e-9)
    assert np.isfinite(rep["coverage_ratio_pct"])


def test_that_the_report_shows_the_sensor_noise_the_log_header_states(tmp_path, paper_report, small_noisy_run):
    rep = make_report(small_noisy_run, tmp_path / "rep", ReportOptions(plots=False))
    assert rep["sensor_noise"].startswith("appendix-a: range 2.5 cm, servo angle 1 deg, attitude 0.143 deg")
    assert "Sensor noise (simulated)" in (tmp_path / "rep" / "report.md").read_text()
    assert paper_report["sensor_noise"] == "none stated in the log header"  # a flight without sensor noise



def test_that_the_pointing_bias_lifts_a_survey_under_a_pointing_error_on_request(tmp_path, small_noisy_run):
    """Appendix A's degree of pointing error places every point behind the surface (ground.pointing_bias): asked to,
    the report moves them back towards the sensor and fits again, which raises the volume; without a pointing error
    in the header there is nothing to move."""
    plain = make_report(small_noisy_run, tmp_path / "plain", ReportOptions(plots=False))
    moved = make_report(small_noisy_run, tmp_path / "moved", ReportOptions(plots=False, pointing_bias=True))
    assert moved["pointing_bias"] is True and plain["pointing_bias"] is False
    assert moved["volume_m3"] > plain["volume_m3"]
    fly(FlyConfig(mission=SMALL, plant="ideal", seed=1), tmp_path / "clean")
    a = make_report(tmp_path / "clean", tmp_path / "a", ReportOptions(plots=False))
    b = make_report(tmp_path / "clean", tmp_path / "b", ReportOptions(plots=False, pointing_bias=True))
    assert a["volume_m3"] == b["volume_m3"]

def test_that_a_structure_off_its_planes_is_warned_when_either_estimator_finds_it_and_neither_corrects_it():
    from ground.log_warnings import unexplained_structure_warning
    from ground.pose_correction import PoseCorrection, not_applied
    from ground.self_calibration import MountEstimate, not_estimated
    unobservable = not_estimated("the floor and walls seen constrain none of the mounting's parameters")
    off_mount = not_estimated("the mounting model does not explain the floor and walls seen", unexplained=True)
    off_pose = not_applied("not applied: the floor and walls stay 1.6 cm off their planes", unexplained=True)
    small = not_applied("not applied: too small to matter")
    # the pose correction's finding alone is enough: an unobservable mount explained nothing (a header boresight
    # 17 deg wrong read 18.8 % high, and only the interval's width said anything)
    w = unexplained_structure_warning(unobservable, off_pose)
    assert w is not None and "neither the mount's self-calibration nor the pose correction explains it" in w
    assert "pose correction: the floor and walls stay 1.6 cm off" in w and "not applied:" not in w
    w = unexplained_structure_warning(off_mount, off_pose)
    assert "self-calibration: the mounting model does not explain" in w and "pose correction: the floor" in w
    assert "the pose correction was off" in unexplained_structure_warning(off_mount, None)
    assert "the mount's self-calibration was off" in unexplained_structure_warning(None, off_pose)
    # nothing found off, or something applied that explains it: no warning
    assert unexplained_structure_warning(unobservable, small) is None
    assert unexplained_structure_warning(None, None) is None
    corrected = PoseCorrection(np.zeros(2), np.zeros((2, 4)), np.ones((2, 4), dtype=bool), True)
    assert unexplained_structure_warning(off_mount, corrected) is None
    calibrated = MountEstimate((0.05, 0.0, 0.0, 0.0), (0.001,) * 4, (True, False, False, False), (0,) * 5, 0.0, 0.0)
    assert unexplained_structure_warning(calibrated, off_pose) is None


def test_that_floor_the_rangefinder_could_not_reach_is_said_and_a_flight_that_reached_everything_is_quiet(
        tmp_path, paper_report):
    """The LIDAR-Lite v3's datasheet returns at P_traj 30 %: the legs 12 m from the walls see no echo from the floor
    at their feet (ground.echo_reach), and the fill there holds several percent of the volume."""
    fly(FlyConfig(mission=Mission(p_traj=0.3), plant="ideal", sensor_noise="datasheet"), tmp_path / "run")
    four = ReportOptions(plots=False, max_interval_pct=4.0)  # the interval's term for it: 2.2 % of the volume
    rep = make_report(tmp_path / "run", tmp_path / "rep", four)
    echo = rep["echo"]
    assert echo["no_echo"] > 0.1 * echo["samples_aimed"] and echo["beyond_reach"] > 0.9 * echo["no_echo"]
    warned = [w for w in rep["warnings"] if "beyond the Garmin LIDAR-Lite v3's reach" in w]
    assert len(warned) == 1 and "the fill put" in warned[0]
    assert echo["unseen_term_m3"] > 0.02 * rep["volume_m3"]  # over half of a 4 % tolerance
    assert echo["fill_out_of_reach_m3"] > 0.04 * rep["volume_m3"]  # what the fill put there: the volume reads high
    quiet = paper_report["echo"]  # an ideal sensor at P_traj 10 %: what it did not echo was beyond the building's floor
    assert max(quiet["fill_out_of_reach_m3"], quiet["unseen_term_m3"]) < 0.001 * paper_report["volume_m3"]
    assert not [w for w in paper_report["warnings"] if "echo" in w]


def test_that_the_wall_contact_fill_keeps_the_curvature_slopes_when_the_surface_takes_the_gp_slopes(
        tmp_path, paper_run, monkeypatch):
    """`--surface-slopes gp` is the points' own surface's: the fit through the wall contacts that fills the unseen
    strips keeps scipy's slopes (ground.report.CONTACT_FIT_SLOPES), which the GP's lifted along a wall."""
    import ground.report as report
    from ground.smoothing import NodeSlopes

    asked = []
    real = report.fit_heights  # the contact fit's surface (the points' own is `fit_surface`)

    def spy(points_w, grid, method, sigma_m, smoothing, **kwargs):
        asked.append(smoothing.slopes)
        return real(points_w, grid, method, sigma_m, smoothing, **kwargs)
    monkeypatch.setattr(report, "fit_heights", spy)
    rep = make_report(paper_run, tmp_path / "rep", ReportOptions(plots=False, surface_slopes=NodeSlopes.GP))
    assert rep["surface_slopes"] == "gp"
    assert asked and set(asked) == {NodeSlopes.CURVATURE}
