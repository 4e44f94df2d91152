"""The floor's level as the flight saw it: a height off by a constant (the lever arm's z, the altitude reference) is
measured on the floor, taken out by the pose correction when the floor lies below z = 0, warned of when it is left
there by more than the interval holds, and undone with `pilescan-ground report --lever-arm`."""

import math
import re
import shutil

import numpy as np
import pytest

from firmware_py.core.cli import ExitCode
from firmware_py.core.samplelog import SampleLogWriter, read_samplelog, rewritable_header
from firmware_py.core.storage import Storage
from ground.cli import format_summary, main
from ground.floor_check import (
    N_SIGNIFICANT,
    FloorFall,
    FloorLevel,
    fall_warning,
    floor_fall,
    floor_other_reading,
    floor_warning,
    measure_floor,
)
from ground.log_warnings import lever_arm_warning
from ground.pointcloud import Cloud, SensorErrorModel
from ground.report import ReportOptions, make_report
from ground.surface import Grid
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tests.ground.test_base import flank_over_a_corner_of_floor

STORAGE = Storage(30, 20, 10)
ERR = SensorErrorModel(range_sigma_m=0.02)
LEVER = np.array([0.0, 0.0, 0.10])


def _cloud(points_w: np.ndarray) -> Cloud:
    """Points seen from 8 m above the floor, straight down the beam."""
    origin = np.column_stack([points_w[:, :2], np.full(len(points_w), 8.0)])
    ray = points_w - origin
    rng = np.linalg.norm(ray, axis=1)
    return Cloud(points_w, ray / rng[:, None], rng, origin, len(points_w), 0)


def _floor_and_toes(level_m: float, seed: int = 0, toes: int = 400) -> np.ndarray:
    """A floor at level_m seen along the building's long sides, with a pile's toe rising off it on one side only
    (what tilts a plane fitted within the floor's noise band)."""
    rng = np.random.default_rng(seed)
    n = 3000
    x = rng.uniform(0.5, 29.5, n)
    y = np.where(rng.random(n) < 0.5, rng.uniform(0.5, 3.0, n), rng.uniform(17.0, 19.5, n))
    floor = np.column_stack([x, y, level_m + rng.normal(0.0, 0.02, n)])
    tx = rng.uniform(5.0, 25.0, toes)
    ty = rng.uniform(3.0, 4.0, toes)
    toe = np.column_stack([tx, ty, level_m + 0.12 * (ty - 3.0) + rng.normal(0.0, 0.02, toes)])
    return np.concatenate([floor, toe])


def _measured(points_w: np.ndarray) -> FloorLevel | None:
    return measure_floor(_cloud(points_w), np.zeros(len(points_w), dtype=bool), STORAGE, ERR,
                         Grid(STORAGE.length_m, STORAGE.width_m, 0.25))


@pytest.mark.parametrize("level_m", [0.0, -0.2, 0.15])
def test_that_the_floor_s_level_is_measured_where_it_lies_whatever_the_toes_on_one_side(level_m):
    f = _measured(_floor_and_toes(level_m))
    assert f is not None
    assert f.level_m == pytest.approx(level_m, abs=3e-3)
    assert 0 < f.std_error_m < 2e-3 and f.n_points > 2500


def test_that_points_under_their_tolerance_are_counted_as_the_floor_not_left_out():
    f = _measured(_floor_and_toes(-0.6))
    assert f.level_m == pytest.approx(-0.6, abs=3e-3) and f.n_under_tolerance > 2500


def test_that_material_hiding_the_floor_is_never_taken_for_a_floor_below_z0():
    """The lowest flat ring of a mound cut off above the floor passes for a floor (the sweeps cannot tell material
    covering the floor from a floor seen high), but it lies above z = 0, where nothing is warned."""
    rng = np.random.default_rng(1)
    x, y = rng.uniform(0, 30, 4000), rng.uniform(0, 20, 4000)
    mound = np.column_stack([x, y, 6.0 - 0.6 * np.hypot(x - 15, y - 10)])  # a 31 deg cone, no flat ground
    f = _measured(mound[mound[:, 2] > 0.5])
    assert f is None or f.level_m > 0.5
    assert floor_warning(f, STORAGE, LEVER, interval_half_m3=None) is None
    cliff = _measured(mound[mound[:, 2] > 0.5][:, :] * [1, 1, 10])  # as steep as a wall: no plane is a floor
    assert cliff is None or cliff.level_m > 0.5


def test_that_a_plane_lying_on_material_with_a_floor_s_worth_of_points_under_it_is_no_floor():
    """The plane the most points lie on is the flank's, 1 m up at its level and falling 4.2 %: points lie under it
    and a floor's worth lower still. Before, the report named that flank as a floor laid to a fall, and warned a pose
    correction that had anchored the height on the corner of floor that it had read a fall as a height error."""
    assert _measured(flank_over_a_corner_of_floor()) is None
    assert fall_warning(_measured(flank_over_a_corner_of_floor()), 0.25) is None


def test_that_a_floor_with_stray_points_under_it_is_still_the_floor():
    """Glitches under a floor are more than its noise's tail, but they hold no floor's worth of points at any one
    level: the floor is measured where it lies."""
    pts = _floor_and_toes(0.0)
    rng = np.random.default_rng(3)
    glitches = np.column_stack([rng.uniform(1, 29, 60), rng.uniform(1, 19, 60), rng.uniform(-2.0, -0.3, 60)])
    f = _measured(np.concatenate([pts, glitches]))
    assert f is not None and f.level_m == pytest.approx(0.0, abs=3e-3)


def test_that_a_floor_below_z0_is_warned_with_the_lever_arm_that_lifts_it():
    f = FloorLevel(level_m=-0.2, std_error_m=0.001, tilt_deg=0.1, n_points=1200, cover_pct=5.0, n_under_tolerance=0)
    w = floor_warning(f, STORAGE, LEVER, interval_half_m3=20.0)
    assert w is not None and "lies 0.20 m below z = 0" in w and "about 120 m³ low" in w
    assert "--lever-arm 0 0 -0.10" in w and "0.10 m above" in w and "0.10 m below" in w
    assert "--base fitted-floor" in w


def test_that_a_floor_within_its_noise_or_the_interval_or_above_z0_gets_no_warning():
    low = FloorLevel(-0.05, 0.001, 0.1, 1200, 5.0, 0)
    assert floor_warning(low, STORAGE, LEVER, interval_half_m3=20.0) is not None  # 30 m³ moved
    assert floor_warning(low, STORAGE, LEVER, interval_half_m3=31.0) is None  # the interval holds it
    assert floor_warning(low, STORAGE, LEVER, interval_half_m3=None) is not None  # no interval: its noise alone
    noisy = FloorLevel(-0.05, 0.05 / N_SIGNIFICANT * 1.01, 0.1, 1200, 5.0, 0)
    assert floor_warning(noisy, STORAGE, LEVER, interval_half_m3=None) is None
    # Above z = 0 a floor cannot be told from material covering it: not warned.
    assert floor_warning(FloorLevel(0.3, 0.001, 0.1, 1200, 5.0, 0), STORAGE, LEVER, 1.0) is None
    assert floor_warning(None, STORAGE, LEVER, 1.0) is None


def test_that_the_other_reading_lifts_every_surfaced_height_by_the_floor_s_depth_and_its_interval_alike():
    grid = Grid(STORAGE.length_m, STORAGE.width_m, 0.25)
    heights = np.full(grid.shape, 1.0)
    heights[:10] = np.nan  # 10 rows of 80 cells unsurfaced: 50 m² of the 600
    low = FloorLevel(-0.2, 0.001, 0.1, 1200, 5.0, 0)
    other = floor_other_reading(low, STORAGE, heights, grid, 550.0, (530.0, 570.0))
    assert other.volume_m3 == pytest.approx(550.0 + 0.2 * 550.0)
    assert other.interval_m3 == pytest.approx((640.0, 680.0)) and other.moved_m3 == pytest.approx(-110.0)
    d = other.as_dict()
    assert d["condition"].startswith("every height is 0.20 m low") and d["volume_interval_m3"] == pytest.approx(
        [640.0, 680.0])
    assert floor_other_reading(low, STORAGE, heights, grid, 550.0, (400.0, 700.0)) is None  # the interval holds it
    assert floor_other_reading(FloorLevel(0.2, 0.001, 0.1, 1200, 5.0, 0), STORAGE, heights, grid, 550.0,
                               (530.0, 570.0)) is None


def test_that_the_console_says_where_the_floor_was_seen_and_when_it_was_not():
    rep = {"volume_m3": 1584.6, "volume_interval_m3": [1558.7, 1610.5], "n_points_used": 11000, "n_samples": 21000,
           "floor_measured": FloorLevel(-0.198, 0.00025, 0.49, 1125, 4.8, 0).as_dict()}
    assert "floor seen at  -19.8 cm from z = 0 (+/-0.2 mm, over 5 % of the building)" in format_summary(rep)
    assert "floor seen at  not seen (the material hides it)" in format_summary({**rep, "floor_measured": None})
    assert "floor seen at" not in format_summary({**rep, "flights": [{}, {}]})  # each flight's own, in report.json


def _floor_with_a_pile(fall_pct: float, azimuth_deg: float, seed: int = 0) -> np.ndarray:
    """A floor laid to a fall (rising along the azimuth from the origin corner) seen wall to wall around a cone whose
    toe rises off it, the floor's points far from the cone and near it alike."""
    rng = np.random.default_rng(seed)
    n = 12000
    x, y = rng.uniform(0.5, 29.5, n), rng.uniform(0.5, 19.5, n)
    a = math.radians(azimuth_deg)
    floor = fall_pct / 100.0 * (x * math.cos(a) + y * math.sin(a))
    cone = np.maximum(0.0, 5.0 - 0.7 * np.hypot(x - 12.0, y - 10.0))
    return np.column_stack([x, y, floor + cone + rng.normal(0.0, 0.02, n)])


@pytest.mark.parametrize(("fall_pct", "azimuth_deg"), [(1.5, 30.0), (1.0, -120.0), (2.0, 90.0)])
def test_that_a_floor_laid_to_a_fall_is_named_with_its_fall_and_direction(fall_pct, azimuth_deg):
    f = _measured(_floor_with_a_pile(fall_pct, azimuth_deg))
    assert f.fall.laid_to_fall
    assert f.fall.fall_pct == pytest.approx(fall_pct, abs=0.05)
    assert f.fall.rise_azimuth_deg == pytest.approx(azimuth_deg, abs=3.0)
    line = format_summary({"volume_m3": 100.0, "n_points_used": 1, "n_samples": 1, "floor_measured": f.as_dict()})
    assert f"rising {fall_pct:.1f} % towards {azimuth_deg:.0f} deg from x" in line and "--base fitted-floor" in line


def test_that_a_level_floor_is_not_named_for_the_toe_that_tilts_its_plane():
    """The toe on one side tilts the plane fitted within the floor's band; the floor far from it does not rise."""
    f = _measured(_floor_and_toes(0.0, toes=1500))
    assert 100.0 * math.tan(math.radians(f.tilt_deg)) > 0.05  # the whole plane falls 0.06 % through the toe ...
    assert not f.fall.laid_to_fall and f.fall.fall_pct < 0.02  # ... the floor away from it 0.01 %
    assert "rising" not in format_summary({"volume_m3": 1.0, "n_points_used": 1, "n_samples": 1,
                                           "floor_measured": f.as_dict()})
    level = _measured(_floor_with_a_pile(0.0, 0.0))
    assert not level.fall.laid_to_fall


def test_that_a_floor_s_fall_is_fitted_away_from_the_material_whose_toe_tilts_it():
    rng = np.random.default_rng(4)
    x, y = rng.uniform(0.5, 29.5, 6000), rng.uniform(0.5, 19.5, 6000)
    toe = np.hypot(x - 15.0, y - 10.0) < 6.0  # a pile's toe within the floor's band: rising 2 cm a metre
    floor = np.column_stack([x, y, 0.015 * x + np.where(toe, 0.02 * (6.0 - np.hypot(x - 15.0, y - 10.0)), 0.0)
                             + rng.normal(0.0, 0.01, len(x))])
    pile = np.column_stack([rng.uniform(13.0, 17.0, 500), rng.uniform(8.0, 12.0, 500)])  # the material above it
    fall = floor_fall(floor, pile)
    assert fall.fall_pct == pytest.approx(1.5, abs=0.02) and fall.rise_azimuth_deg == pytest.approx(0.0, abs=1.0)
    assert fall.laid_to_fall
    level = floor.copy()
    level[:, 2] -= 0.015 * x
    assert floor_fall(level, pile).fall_pct < 0.02  # the toe, away from which the floor is fitted, tilts it not
    assert not FloorFall(0.004, 0.0).laid_to_fall and FloorFall(0.004, 0.003).laid_to_fall  # named from 0.5 %
    assert not FloorFall(0.009, 0.0).laid and FloorFall(0.006, 0.008).laid  # as a floor is laid to from 1 %
    assert floor_fall(floor[:10], pile) is None  # too few points for a floor
    assert floor_fall(floor, np.zeros((0, 2))).fall_pct == pytest.approx(1.5, abs=0.1)  # no material: all of it


def test_that_a_height_correction_on_a_floor_laid_to_a_fall_is_warned_with_the_way_out():
    sloped = FloorLevel(0.5, 0.003, 1.0, 5000, 20.0, 0, FloorFall(0.013, 0.0075))
    w = fall_warning(sloped, 0.14)
    assert w is not None and "up to 0.14 m" in w and "rises 1.5 % towards 30 deg from x" in w
    assert "--no-pose-correction" in w and "--base fitted-floor" in w
    assert fall_warning(sloped, 0.0) is None  # the height was not moved
    assert fall_warning(FloorLevel(0.5, 0.003, 1.0, 5000, 20.0, 0, FloorFall(0.003, 0.0)), 0.14) is None  # level
    assert fall_warning(None, 0.14) is None


def test_that_a_lever_arm_given_is_said_only_when_it_is_not_the_header_s():
    assert lever_arm_warning({"lever_arm_body_m": [0, 0, 0.1]}, (0.0, 0.0, 0.1)) is None
    assert lever_arm_warning({"lever_arm_body_m": [0, 0, 0.1]}, None) is None
    w = lever_arm_warning({"lever_arm_body_m": [0, 0, 0.3]}, (0.0, 0.0, 0.1))
    assert "taken as 0, 0, 0.1 m (--lever-arm" in w and "the log header's 0, 0, 0.3 m" in w


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """Pile 1 in the 30 x 20 m building: the pile hides most of the floor (5 % of its cells seen)."""
    out = tmp_path_factory.mktemp("floor") / "run"
    fly(FlyConfig(mission=Mission(storage=STORAGE, p_traj=0.2, altitude_m=8.0, speed_m_s=2.0), stockpile="1"), out,
        force=True)
    return out


def _with_lever_arm(run, out, lever):
    out.mkdir()
    shutil.copy(run / "truth.json", out / "truth.json")
    log = read_samplelog(run / "samples.pslog")
    w = SampleLogWriter(out / "samples.pslog", {**rewritable_header(log.header), "lever_arm_body_m": lever},
                        fsync=False)
    w.append(log.samples)
    w.close()
    return out


def test_that_a_lever_arm_entered_0_2_m_too_low_is_taken_out_by_the_pose_correction_and_named(flight, tmp_path):
    """The header puts the LiDAR 0.30 m below the autopilot where it sits 0.10 m below: every point 0.2 m low. The
    floor then lies below z = 0, where nothing but a height error puts it, so the pose correction's height brings it
    up (the walls alone had found it too small to matter: the volume 6.8 % low without a word), and says what makes
    an error so even over a flight."""
    wrong = _with_lever_arm(flight, tmp_path / "wrong", [0.0, 0.0, 0.3])
    clean = make_report(flight, tmp_path / "clean", ReportOptions(plots=False), force=True)
    assert clean["pose_correction"]["applied"] is False
    fixed = make_report(wrong, tmp_path / "bad", ReportOptions(plots=False), force=True)
    pose = fixed["pose_correction"]
    assert pose["applied"] and pose["horizontal_max_m"] == 0.0 and pose["heading_max_deg"] == 0.0
    assert fixed["volume_m3"] == pytest.approx(clean["volume_m3"], rel=0.005) and fixed["truth_in_interval"]
    assert fixed["floor_measured"]["level_m"] == pytest.approx(0.0, abs=0.01)
    said = [n for n in pose["notes"] if "lay 0.20 m below z = 0" in n]
    assert len(said) == 1 and "check the lever arm against the drone" in said[0]
    assert not any("the floor the sweeps saw" in w for w in fixed["warnings"])


def test_that_a_lever_arm_entered_0_2_m_too_low_is_warned_and_its_fix_restores_the_volume(flight, tmp_path):
    """The same flight with the pose correction off (as where the noise hides the height from it): the floor says the
    points are 0.2 m low and names the lever arm that fixes it."""
    wrong = _with_lever_arm(flight, tmp_path / "wrong", [0.0, 0.0, 0.3])
    clean = make_report(flight, tmp_path / "clean", ReportOptions(plots=False), force=True)
    assert clean["floor_measured"]["level_m"] == pytest.approx(0.0, abs=0.01)
    assert not any("the floor the sweeps saw" in w for w in clean["warnings"])
    bad = make_report(wrong, tmp_path / "bad", ReportOptions(plots=False, pose_correction=False), force=True)
    assert bad["floor_measured"]["level_m"] == pytest.approx(-0.2, abs=0.01)
    assert bad["volume_error_pct"] > 5 and not bad["truth_in_interval"]
    said = [w for w in bad["warnings"] if "the floor the sweeps saw lies 0.20 m below z = 0" in w]
    assert len(said) == 1 and "--lever-arm 0 0 0.10" in said[0]
    other = bad["volume_other_reading"]  # the verdict's "or ... if every height is 0.20 m low"
    assert other["volume_m3"] == pytest.approx(clean["volume_m3"], rel=0.005)
    assert "if every height is 0.20 m low" in bad["verdict"]
    assert clean["volume_other_reading"] is None
    assert main(["report", str(wrong), "--out", str(tmp_path / "fixed"), "--no-plots", "-q", "--no-pose-correction",
                 "--lever-arm", "0", "0", "0.10"]) == 0
    import json
    fixed = json.loads((tmp_path / "fixed" / "report.json").read_text())
    assert fixed["volume_m3"] == pytest.approx(clean["volume_m3"], rel=1e-3) and fixed["truth_in_interval"]
    assert any("(--lever-arm, body forward, right, down), not the log header's 0, 0, 0.3 m" in w
               for w in fixed["warnings"])
    assert not any("the floor the sweeps saw" in w for w in fixed["warnings"])


@pytest.mark.parametrize(("argv", "words"), [
    (["--lever-arm", "0", "0"], "--lever-arm"),
    (["--lever-arm", "0", "0", "nan"], "--lever-arm"),
    (["--lever-arm", "0", "0", "6"], "within +/-5 m"),
])
def test_that_a_bad_lever_arm_is_one_line_of_error(flight, tmp_path, capsys, argv, words):
    code = main(["report", str(flight), "--out", str(tmp_path / "r"), "--no-plots", *argv])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE and err.count("\n") == 1 and "Traceback" not in err and words in err


def test_that_a_lever_arm_entered_0_3_m_too_far_forward_is_named_not_corrected_as_a_drift(flight, tmp_path):
    """The same flight with the LiDAR entered 0.3 m forward of where it sits: every point moves along the legs, the
    other way on the way back. The drift's knots would follow it leg by leg (Ve +1.4 %); the lever arm moved by one
    vector fixed to the body explains the walls as well, so the points are placed with it and the lever arm named."""
    wrong = _with_lever_arm(flight, tmp_path / "wrong", [0.3, 0.0, 0.1])
    rep = make_report(wrong, tmp_path / "rep", ReportOptions(plots=False), force=True)
    clean = make_report(flight, tmp_path / "clean", ReportOptions(plots=False), force=True)
    pose = rep["pose_correction"]
    assert pose["applied"] and pose["horizontal_max_m"] == 0.0
    assert pose["lever_change_m"] == pytest.approx([-0.3, 0.0], abs=0.01)
    assert rep["volume_m3"] == pytest.approx(clean["volume_m3"], rel=1e-3) and rep["truth_in_interval"]
    said = [w for w in rep["warnings"] if "as well as with a drifting pose, so the points are placed" in w]
    assert len(said) == 1
    fitted = re.search(r"`--lever-arm (\S+) (\S+) (\S+)`", said[0])
    assert fitted and [float(v) for v in fitted.groups()] == pytest.approx([0.0, 0.0, 0.1], abs=0.005)
    assert not any(w.startswith("pose corrected from the building") for w in rep["warnings"])
