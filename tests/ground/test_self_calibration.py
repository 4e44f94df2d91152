"""Self-calibration from the building: a mis-mounted LiDAR on a mis-calibrated servo, flown in the
SITL (the firmware in the loop), is found from the floor and walls; a square one is left alone."""

import json
import math
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame
from firmware_py.core.samplelog import SAMPLE_DTYPE, SampleLogWriter, read_samplelog, rewritable_header
from firmware_py.core.servo_model import servo_angles
from firmware_py.core.storage import Storage
from ground import log_warnings, report
from ground.plane_stretches import beams
from ground.pose_correction import KNOT_SWEEPS, PoseCorrectionOptions, knot_times, prior_sigmas
from ground.pose_knots import knot_basis
from ground.report import ReportOptions, make_report
from ground.self_calibration import (
    INSIDE_SIGN,
    N_GROUPS,
    PLANE_SETS,
    DriftNuisance,
    KnownMount,
    MountEstimate,
    ServoAngles,
    _DriftFit,
    _trim_inside,
    describe,
    estimate_mount,
    lever_alternative,
    not_estimated,
    plane_set_errors,
)
from ground.servo_timing import Resimulated
from sitl.faults.injector import FaultSpec
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tools.pose_correction_campaign import signed_error_pct

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)

STORAGE = Storage(30, 20, 10)


def _fly(tmp_path, faults, pile="1", storage=STORAGE, altitude_m=8.0, speed_m_s=2.0, pose_error="none",
         payload="batch", p_traj=0.2):
    """At 2 m/s by default: half the flight of 1 m/s, the same floor and walls in every sweep. The batch payload
    by default: it flies the mounting's faults as the firmware's emulated servo and LiDAR do
    (tests/sitl/runners/test_lockstep_payload.py holds the two to each other), at a fifth of the cost. The flights
    whose tests are about what the firmware's own data do to the fit (its pose timing and modelled servo) fly it."""
    cfg = FlyConfig(mission=Mission(storage=storage, p_traj=p_traj, altitude_m=altitude_m, speed_m_s=speed_m_s),
                    stockpile=pile, faults=faults, payload=payload, pose_error=pose_error)
    fly(cfg, tmp_path / "run", force=True)
    return tmp_path / "run"


def _usable(run):
    log = read_samplelog(run / "samples.pslog")
    return log.samples[log.samples["flags"] == 0], log.header


def _estimate(run, boresight: Boresight = SQUARE, keep=None, storage=STORAGE):
    s, h = _usable(run)
    s = s if keep is None else s[keep(s)]
    return estimate_mount(s, h["lever_arm_body_m"], StorageFrame(), storage, h["sensor"]["range_sigma_m"],
                          h["sensor"]["range_sigma_rel"], Resimulated.from_header(h), boresight)


def _with_header(run, out, **fields):
    """The run again, its log header saying these fields otherwise."""
    out.mkdir()
    shutil.copy(run / "truth.json", out / "truth.json")
    log = read_samplelog(run / "samples.pslog")
    w = SampleLogWriter(out / "samples.pslog", {**rewritable_header(log.header), **fields}, fsync=False)
    w.append(log.samples)
    w.close()
    return out


def _with_boresight(run, out, boresight: Boresight):
    """The run again, its log header saying the LiDAR was configured with this boresight (--boresight)."""
    return _with_header(run, out, boresight=boresight.to_dict())


def _straight_legs(s):
    """The samples flown within 1 deg of a wall's direction: no turn, so no wall faces the track."""
    yaw = np.unwrap(s["yaw_rad"].astype(float))
    return np.abs((yaw + math.pi / 4) % (math.pi / 2) - math.pi / 4) < math.radians(1.0)


@pytest.fixture(scope="module")
def square_run(tmp_path_factory):
    return _fly(tmp_path_factory.mktemp("square"), None, payload="firmware")


@pytest.fixture(scope="module")
def skewed_run(tmp_path_factory):
    return _fly(tmp_path_factory.mktemp("skewed"), FaultSpec(servo_offset_deg=3.0, servo_scale_pct=5.0,
                                                            boresight_deg=2.0), payload="firmware")


SKEW = FaultSpec(servo_offset_deg=3.0, servo_scale_pct=5.0, boresight_deg=2.0)


@pytest.fixture(scope="module")
def hidden_floor_runs(tmp_path_factory):
    """The paper's pile 2 in the small building: its material covers the floor wall to wall."""
    return (_fly(tmp_path_factory.mktemp("square2"), None, pile="2"),
            _fly(tmp_path_factory.mktemp("skewed2"), SKEW, pile="2"))


@pytest.fixture(scope="module")
def drifting_runs(tmp_path_factory):
    """A square and a skewed mount flown on the same drifting indoor estimate (the SITL's `vio` profile)."""
    return (_fly(tmp_path_factory.mktemp("drift-square"), None, pose_error="vio", payload="firmware"),
            _fly(tmp_path_factory.mktemp("drift-skewed"), SKEW, pose_error="vio", payload="firmware"))


@pytest.fixture(scope="module")
def skewed_report(skewed_run, tmp_path_factory):
    """The skewed flight's report with the default options (two tests read it: one report, not two)."""
    return make_report(skewed_run, tmp_path_factory.mktemp("skewed-report") / "rep", ReportOptions(plots=False))


@pytest.fixture(scope="module")
def square_report(square_run, tmp_path_factory):
    """The square flight's report with the default options (two tests compare with it: one report, not two)."""
    return make_report(square_run, tmp_path_factory.mktemp("square-report") / "rep", ReportOptions(plots=False))


@pytest.fixture(scope="module")
def square(square_run):
    return _estimate(square_run)


@pytest.fixture(scope="module")
def skewed(skewed_run):
    return _estimate(skewed_run)


def test_that_a_square_mount_gets_no_correction(square):
    assert square.reason is None and not square.any_applied
    assert sum(square.points) > 1000


def test_that_offset_scale_and_tilt_together_are_each_found(skewed):
    offset, scale, tilt, _ = skewed.values
    assert math.degrees(offset) == pytest.approx(3.0, abs=0.1)
    assert scale == pytest.approx(0.05, abs=0.005)
    assert math.degrees(tilt) == pytest.approx(2.0, abs=0.2)
    assert skewed.applied[:3] == (True, True, True)
    assert skewed.rms_after_m < skewed.rms_before_m / 5


def test_that_each_estimate_is_within_a_few_of_its_own_standard_errors_or_a_tenth_degree(skewed):
    truth = (math.radians(3.0), 0.05, math.radians(2.0))
    for v, e, t in zip(skewed.values[:3], skewed.std_errors[:3], truth, strict=True):
        assert abs(v - t) <= max(5 * e, math.radians(0.1))


def test_that_too_few_samples_say_why_and_apply_nothing():
    est = estimate_mount(np.zeros(10, dtype=SAMPLE_DTYPE), (0, 0, 0), StorageFrame(),
                         STORAGE, 0.025, 0.01)
    assert not est.any_applied and "too few usable samples" in est.reason
    assert not_estimated("x").correction()[0] == 0.0


def test_that_the_report_applies_it_says_so_and_gets_the_volume_back(skewed_run, skewed_report, square_report,
                                                                     tmp_path):
    clean = square_report
    fixed = skewed_report
    raw = make_report(skewed_run, tmp_path / "raw", ReportOptions(plots=False, self_calibration=False))
    assert clean["self_calibration"]["servo_offset_deg"]["applied"] is False
    assert not any("self-calibration" in w for w in clean["warnings"])
    assert fixed["self_calibration"]["servo_scale"]["applied"] is True
    assert fixed["self_calibration"]["fitted_with_drift"] is False
    assert any(w.startswith("self-calibration from the building applied: servo offset +3.0") for w in fixed["warnings"])
    assert not any("fitted together with the pose's drift" in w for w in fixed["warnings"])
    assert raw["self_calibration"] is None
    assert abs(signed_error_pct(fixed) - signed_error_pct(clean)) < 0.3
    assert abs(signed_error_pct(raw) - signed_error_pct(clean)) > abs(signed_error_pct(fixed) - signed_error_pct(clean))


def test_that_a_mount_given_is_applied_as_given_in_place_of_the_self_calibration(skewed_run, square_report, tmp_path):
    """The skewed flight reported with the mount it flew given (`--mount 3 5 2 0`): nothing is estimated, the mount
    is applied as given and said so, report.json stays JSON (no NaN for the fit that was not made), and the volume
    comes back to the square flight's."""
    given = make_report(skewed_run, tmp_path / "given", ReportOptions(
        plots=False, mount=KnownMount(math.radians(3.0), 0.05, math.radians(2.0), 0.0)))
    cal = given["self_calibration"]
    assert cal["given"] is True and cal["rms_before_m"] is None and cal["servo_scale"]["std_error"] is None
    assert cal["servo_offset_deg"]["estimate"] == pytest.approx(3.0) and cal["servo_offset_deg"]["applied"] is True
    assert cal["servo_scale"]["estimate"] == pytest.approx(0.05) and cal["boresight_tilt_deg"]["applied"] is True
    assert cal["sweep_yaw_deg"]["applied"] is False
    said = [w for w in given["warnings"] if "--mount" in w]
    assert said == ["the mount as given (--mount) applied in place of the self-calibration from the building: servo "
                    "offset +3.00 deg, servo scale +5.00 %, boresight tilt +2.00 deg"]
    assert not any(w.startswith("self-calibration from the building") for w in given["warnings"])

    def no_constant(name):
        raise AssertionError(f"report.json holds {name}, which is no JSON")
    json.loads((tmp_path / "given" / "report.json").read_text(), parse_constant=no_constant)
    assert abs(signed_error_pct(given) - signed_error_pct(square_report)) < 0.3


def test_that_a_known_mount_is_held_to_what_a_mounting_can_be_off_by_and_applies_what_is_not_zero():
    est = KnownMount(servo_scale=-0.02).estimate()
    assert est.given and est.applied == (False, True, False, False) and est.values == (0.0, -0.02, 0.0, 0.0)
    assert est.correction()[:2] == (0.0, -0.02)
    assert not KnownMount().estimate().any_applied
    assert describe(est).endswith("servo scale -2.00 %")
    for bad, words in ((dict(servo_offset_rad=math.radians(21)), "servo offset must be within +/-20 deg .*got 21 deg"),
                       (dict(servo_scale=0.31), "servo scale must be within +/-30 % .*got 31 %"),
                       (dict(tilt_rad=math.nan), "tilt must be within"),
                       (dict(sweep_yaw_rad=-math.inf), "sweep yaw must be within")):
        with pytest.raises(ValueError, match=words.replace("+", r"\+")):
            KnownMount(**bad)


def test_that_the_tilt_estimated_is_the_deviation_from_the_configured_one(skewed_run):
    """The true tilt is 2 deg: configured as 2 deg, the deviation found is nil; offset and scale unchanged."""
    on_top = _estimate(skewed_run, Boresight(math.radians(2.0)))
    offset, scale, tilt, _ = on_top.values
    assert math.degrees(tilt) == pytest.approx(0.0, abs=0.2)
    assert math.degrees(offset) == pytest.approx(3.0, abs=0.1) and scale == pytest.approx(0.05, abs=0.005)
    wrong = _estimate(skewed_run, Boresight(math.radians(-1.0)))  # configured 1 deg the other way: 3 deg to find
    assert math.degrees(wrong.values[2]) == pytest.approx(3.0, abs=0.2)


def test_that_the_report_places_points_with_the_headers_boresight(skewed_run, skewed_report, tmp_path):
    configured = make_report(_with_boresight(skewed_run, tmp_path / "run", Boresight(math.radians(2.0))),
                             tmp_path / "rep", ReportOptions(plots=False))
    plain = skewed_report
    assert configured["boresight_deg"] == pytest.approx({"tilt": 2.0, "sweep_yaw": 0.0})
    assert plain["boresight_deg"] == {"tilt": 0.0, "sweep_yaw": 0.0}
    assert configured["self_calibration"]["boresight_tilt_deg"]["estimate"] == pytest.approx(0.0, abs=0.2)
    assert plain["self_calibration"]["boresight_tilt_deg"]["estimate"] == pytest.approx(2.0, abs=0.2)
    assert abs(signed_error_pct(configured) - signed_error_pct(plain)) < 0.3


def test_that_a_floor_hidden_by_the_pile_is_calibrated_from_the_walls_alone(hidden_floor_runs, tmp_path):
    square_run, skewed_run = hidden_floor_runs
    square, skewed = _estimate(square_run), _estimate(skewed_run)
    assert skewed.points[0] < sum(skewed.points[1:]) / 50  # next to no floor seen
    assert not square.any_applied and square.reason is None
    offset, scale, tilt, _ = skewed.values
    assert math.degrees(offset) == pytest.approx(3.0, abs=0.1)
    assert scale == pytest.approx(0.05, abs=0.005)
    assert math.degrees(tilt) == pytest.approx(2.0, abs=0.2)
    assert skewed.applied[:3] == (True, True, True)
    clean = make_report(square_run, tmp_path / "clean", ReportOptions(plots=False))
    fixed = make_report(skewed_run, tmp_path / "fixed", ReportOptions(plots=False))
    raw = make_report(skewed_run, tmp_path / "raw", ReportOptions(plots=False, self_calibration=False))
    assert abs(signed_error_pct(fixed) - signed_error_pct(clean)) < 0.3
    assert abs(signed_error_pct(raw) - signed_error_pct(clean)) > abs(signed_error_pct(fixed) - signed_error_pct(clean))


def test_that_without_a_drift_the_walls_carry_the_fit_and_the_floor_only_where_no_wall_is_seen(skewed_run, skewed):
    """The walls first: where a pile hides the floor, its toe passes for floor under noise (`estimate_mount`'s "Why the
    walls first"). A building whose walls the sweeps never reach (here: every point within 1 m of a wall taken out)
    is calibrated from its floor."""
    assert skewed.points[0] == 0 and sum(skewed.points[1:]) > 1000
    s, h = _usable(skewed_run)
    b, _ = beams(s, h["lever_arm_body_m"], StorageFrame(), SQUARE)
    p = b.vehicle_w + b.to_point_w
    inside = ((p[:, 0] > 1.0) & (p[:, 0] < STORAGE.length_m - 1.0) & (p[:, 1] > 1.0)
              & (p[:, 1] < STORAGE.width_m - 1.0))
    floor = _estimate(skewed_run, keep=lambda _s: inside)
    assert floor.reason is None and floor.points[1:] == (0, 0, 0, 0) and floor.points[0] > 100
    assert math.degrees(floor.values[0]) == pytest.approx(3.0, abs=0.15)
    assert floor.values[1] == pytest.approx(0.05, abs=0.005)  # (not significant: a few hundred floor points)


def test_that_without_turns_the_boresight_is_held_square_and_the_servo_still_found(tmp_path):
    """The paper's building: its long legs hold the heading within 1 deg of the walls for most of the
    flight at 1 m/s. (In the small building, or at 2 m/s, the same cut leaves enough heading wobble that the
    tilt and yaw pass the gate and come out mixed: see the design notes.) At P_traj 30 %: legs of 24 and 16 m,
    a flight 30 % shorter than at 20 %, and the tilt and yaw are still held with the gate made 4 times easier to
    pass (as at 20 %)."""
    run = _fly(tmp_path, SKEW, storage=Storage(60, 40, 15), altitude_m=12.0, speed_m_s=1.0, payload="firmware",
               p_traj=0.3)
    est = _estimate(run, keep=_straight_legs, storage=Storage(60, 40, 15))
    assert est.observable == (True, True, False, False)
    assert est.values[2:] == (0.0, 0.0) and est.applied[2:] == (False, False)
    assert math.degrees(est.values[0]) == pytest.approx(3.0, abs=0.15)
    assert est.values[1] == pytest.approx(0.05, abs=0.005)
    assert est.applied[:2] == (True, True)
    assert "held square, as the structure seen does not constrain it: boresight tilt, sweep-plane yaw" in describe(est)
    assert est.as_dict()["boresight_tilt_deg"]["observable"] is False


def test_that_the_walls_facing_the_track_pin_the_boresight_and_those_beside_it_the_servo(skewed_run, skewed):
    s, h = _usable(skewed_run)
    sets = plane_set_errors(s, h["lever_arm_body_m"], StorageFrame(), STORAGE, skewed, Resimulated.from_header(h))
    assert set(sets) == set(PLANE_SETS)
    beside, facing = sets["walls beside the track"][1], sets["walls facing the track"][1]
    assert facing[2] < beside[2] / 3 and facing[3] < beside[3] / 3  # tilt and yaw: along-track shifts
    assert beside[0] < facing[0] and beside[1] < facing[1]  # offset and scale: the beam's elevation
    assert sets["all"][0] == sum(sets[k][0] for k in PLANE_SETS[:3])


def test_that_points_scattered_at_random_are_no_building_and_get_no_correction():
    rng = np.random.default_rng(1)
    s = np.zeros(3000, dtype=SAMPLE_DTYPE)
    s["t_s"] = np.arange(3000) / 500.0
    s["range_m"] = rng.uniform(0.1, 30.0, 3000)
    s["servo_rad"] = rng.uniform(-1.5, 1.5, 3000)
    s["x_m"], s["y_m"], s["z_m"] = rng.uniform(0, 20, 3000), rng.uniform(0, 30, 3000), -8.0
    s["yaw_rad"] = rng.uniform(-3.0, 3.0, 3000)
    s["sweep_dir"] = rng.choice([-1, 1], 3000)
    s["roll_rad"][5] = np.nan  # a non-finite pose is left out, not fitted
    est = estimate_mount(s, (0, 0, 0.1), StorageFrame(), STORAGE, 0.025, 0.01)
    # No stretch of these "sweeps" runs along a plane (ground.plane_stretches), so no point may be the floor's
    # or a wall's.
    assert not est.any_applied and est.reason == "the building's floor and walls were not found in the cloud"
    s["t_s"] = np.nan  # without times there are no stretches to test: then the fit's own misfit says it
    est = estimate_mount(s, (0, 0, 0.1), StorageFrame(), STORAGE, 0.025, 0.01)
    assert not est.any_applied and "does not explain the floor and walls" in est.reason


def test_that_a_boresight_correction_alone_is_applied_to_the_volume(square_run, square_report, tmp_path):
    """A log whose header says the LiDAR leans 2 deg forward, flown square: the building finds the tilt back to
    square, and the volume is the square flight's. The boresight changes no sample (it enters when the points
    are placed), so the report must survey again for it alone (it had kept the uncorrected survey while saying
    the correction was applied)."""
    declared = _with_boresight(square_run, tmp_path / "declared", Boresight(math.radians(2.0)))
    clean = square_report
    fixed = make_report(declared, tmp_path / "fixed", ReportOptions(plots=False))
    raw = make_report(declared, tmp_path / "raw", ReportOptions(plots=False, self_calibration=False))
    cal = fixed["self_calibration"]
    assert cal["boresight_tilt_deg"]["applied"] is True
    assert not cal["servo_offset_deg"]["applied"] and not cal["servo_scale"]["applied"]
    assert fixed["volume_m3"] != raw["volume_m3"]
    assert abs(fixed["volume_m3"] - clean["volume_m3"]) < abs(raw["volume_m3"] - clean["volume_m3"]) / 3
    assert not any("nor the pose correction explains it" in w for w in clean["warnings"] + fixed["warnings"])


@pytest.mark.parametrize("tilt_rad, yaw_rad, why", [
    (0.2, 0.0, "the mounting model does not explain"),
    # the self-calibration found its parameters unobservable, the pose correction the structure off: such a one read
    # 18.8 % high with no warning but the interval's width (-0.3, 0.1 until a pile's flank in a sweep nearly
    # parallel to a wall stopped passing for that wall: that one is found now, the next test)
    (-0.3, 0.2, "the floor and walls seen constrain none of the mounting's parameters")],
    ids=["the mount's fit refuted", "the mount unobservable, the drift's fit refuted"])
def test_that_a_header_boresight_the_building_refutes_is_warned_when_nothing_explains_it(square_run, tmp_path,
                                                                                         tilt_rad, yaw_rad, why):
    unexplained = "neither the mount's self-calibration nor the pose correction explains it"
    # a boresight it was not mounted at (11.5 deg of tilt; 17 deg and 6 deg of yaw)
    tilted = _with_boresight(square_run, tmp_path / "tilted", Boresight(tilt_rad, yaw_rad))
    rep = make_report(tilted, tmp_path / "rep", ReportOptions(plots=False))
    assert rep["self_calibration"]["reason"].startswith(why)
    warned = [w for w in rep["warnings"] if unexplained in w]
    assert warned, rep["warnings"]  # before: only in report.json
    # Either way the mount's own finding is the structure off its planes, and the warning says so: parameters the
    # structure pins down nowhere because it stays off its planes are the unexplained case (then the report also
    # fits the mount beside a drift), not a building that shows the mount too little.
    assert f"self-calibration: {why}" in warned[0] and "cm off their planes" in warned[0].split("pose correction:")[0]


def test_that_a_header_boresight_17_deg_off_is_found_and_undone(square_run, square_report, tmp_path):
    # 17.2 deg of tilt and 5.7 deg of yaw entered that the LiDAR was not mounted at. The self-calibration called the
    # mount unobservable (Ve 18.8 %, warned) until a stretch along a wall had to be in a sweep crossing the wall by
    # more than a chord as steep as a pile's would show: measured, it is found and undone now.
    wrong = Boresight(-0.3, 0.1)
    rep = make_report(_with_boresight(square_run, tmp_path / "tilted", wrong), tmp_path / "rep",
                      ReportOptions(plots=False))
    cal = rep["self_calibration"]
    assert cal["reason"] is None
    assert abs(cal["boresight_tilt_deg"]["estimate"] + math.degrees(wrong.tilt_rad)) < 0.1  # undoes the header's
    assert abs(cal["sweep_yaw_deg"]["estimate"] + math.degrees(wrong.sweep_yaw_rad)) < 0.2
    assert abs(rep["volume_error_pct"] - square_report["volume_error_pct"]) < 0.05


def test_that_a_header_building_the_sweeps_measure_otherwise_is_warned_and_storage_reports_it_as_measured(
        square_run, square_report, tmp_path):
    # A building entered 0.3 m long: the pose correction moved the flight towards a wall that is not there, and the
    # volume read 1.6 % high with the truth outside its interval, and nothing said but the correction's size.
    long = _with_header(square_run, tmp_path / "long", storage=Storage(30.3, 20.0, 10.0).to_dict())
    rep = make_report(long, tmp_path / "rep", ReportOptions(plots=False))
    assert abs(rep["volume_m3"] - square_report["volume_m3"]) > 0.01 * square_report["volume_m3"]  # the premise
    length = rep["building_measured"]["length"]
    assert length["differs"] and abs(length["measured_m"] - 30.0) < 0.01 and length["header_m"] == 30.3
    assert not rep["building_measured"]["width"]["differs"]
    assert any("the building is not the size the log header says" in w and "--storage 30.00x20.00x10" in w
               for w in rep["warnings"]), rep["warnings"]
    assert not any("not the size the log header says" in w for w in square_report["warnings"])
    # reported with the building as measured: the square flight's volume (which neither estimate changed, so they are
    # left out here: a third of the report's time), and the report says whose building it is
    assert not any(square_report["self_calibration"][k]["applied"]
                   for k in ("servo_offset_deg", "servo_scale", "boresight_tilt_deg", "sweep_yaw_deg"))
    assert not square_report["pose_correction"]["applied"]
    fixed = make_report(long, tmp_path / "fixed", ReportOptions(plots=False, storage=Storage(30.0, 20.0, 10.0),
                                                                self_calibration=False, pose_correction=False))
    assert abs(fixed["volume_m3"] - square_report["volume_m3"]) < 0.001 * square_report["volume_m3"]
    assert any("(--storage), not the log header's 30.3 x 20 x 10 m" in w for w in fixed["warnings"])
    assert not any("not the size the log header says" in w for w in fixed["warnings"])


def test_that_a_plane_s_band_keeps_no_more_points_inside_than_outside_the_farthest_inside_dropped():
    # The floor's band: two points below it (outside the building), five above; x = 0's: one each side.
    j = np.array([0, 0, 0, 0, 0, 0, 0, 1, 1, -1])
    inside = np.where(j >= 0, INSIDE_SIGN[np.maximum(j, 0)], 1.0)
    r = inside * np.array([-0.01, -0.02, 0.01, 0.30, 0.02, 0.50, 0.04, 0.01, -0.01, 0.9])
    kept = _trim_inside(j, r, np.full(len(j), 0.05))
    assert list(kept) == [0, 0, 0, -1, 0, -1, -1, 1, 1, -1]  # the floor keeps its two nearest inside


def test_that_a_lever_arm_entered_off_is_found_as_one_body_fixed_move_whatever_the_heading_and_the_pile():
    # Beams on legs flown both ways along x and across, each point on one of the floor and four walls; the lever arm
    # entered 5 cm too far right puts every point 5 cm to the body's right of where it is; a fifth are pile points
    # near the planes, far off them.
    from types import SimpleNamespace

    from firmware_py.core.frames import rot_body_to_ned
    rng = np.random.default_rng(3)
    n_pts = 4000
    yaw = rng.choice([0.0, math.pi, math.pi / 2, -math.pi / 2], n_pts)
    r_wb = rot_body_to_ned(rng.normal(0, 0.03, n_pts), rng.normal(0, 0.03, n_pts), yaw)
    planes = np.array([[0, 0, 1.0], [1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
    normals = planes[rng.integers(0, 5, n_pts)]
    moved = np.array([0.0, 0.05, 0.0])  # the points' error, in the body
    r_square = np.einsum("nij,j,ni->n", r_wb, moved, normals) + rng.normal(0, 0.005, n_pts)
    pile = rng.random(n_pts) < 0.2
    r_square[pile] += rng.uniform(0.05, 0.3, pile.sum())
    dl, rms = lever_alternative(SimpleNamespace(r_wb=r_wb), np.arange(n_pts), normals, r_square,
                                np.full(n_pts, 0.015))
    assert np.allclose(dl, -moved, atol=0.005)  # the lever arm that puts them back: 5 cm to the left
    assert rms < 0.01  # what is left is the noise (and the pile's few, in a robust spread)


def test_that_a_mount_refused_for_a_lever_arm_names_the_lever_arm_to_report_again_with():
    est = MountEstimate((0.0, 0.01, 0.0, 0.0), (math.nan,) * 4, (False,) * 4, (100, 50, 50, 50, 50), 0.05, 0.05,
                        refused="not applied: the lever arm moved by ...", lever_change_m=(-0.2, 0.0, 0.01))
    w = log_warnings.lever_change_warning(est, np.array([0.0, 0.0, 0.1]))
    assert "moved by -20.0, +0.0, +1.0 cm (forward, right, down)" in w and "none was applied" in w
    assert "`--lever-arm -0.200 0.000 0.110`" in w
    assert est.as_dict()["lever_change_m"] == [-0.2, 0.0, 0.01]
    square = MountEstimate((0.0,) * 4, (math.nan,) * 4, (False,) * 4, (100, 50, 50, 50, 50), 0.01, 0.01)
    assert log_warnings.lever_change_warning(square, np.zeros(3)) is None and square.as_dict()["lever_change_m"] is None
    assert log_warnings.lever_change_warning(None, np.zeros(3)) is None


def test_that_a_pose_correction_that_found_a_lever_arm_names_it_too():
    from ground.pose_correction import not_applied
    pose = not_applied("not applied: ... a lever arm entered off, not a drifting pose", lever_change_m=(0.0, -0.3))
    w = log_warnings.lever_change_warning(None, np.array([0.0, 0.3, 0.1]), pose)
    assert "moved by +0.0, -30.0, +0.0 cm (forward, right, down) as well as with a drifting pose" in w
    assert "the points are placed with the lever arm they fit" in w
    assert "`--lever-arm 0.000 0.000 0.100`" in w  # -0.000 printed as 0.000
    assert log_warnings.lever_change_warning(None, np.zeros(3), not_applied("too small to matter")) is None


def _drift_of(s, h) -> DriftNuisance:
    """The pose correction's knots and prior over the samples' time, as the report gives them."""
    spacing = KNOT_SWEEPS / h["servo"]["frequency_hz"]
    opts = PoseCorrectionOptions()
    return DriftNuisance(knot_times(float(s["t_s"].min()), float(s["t_s"].max()), spacing),
                         prior_sigmas(spacing, 2.0, opts)[:3],
                         np.array([opts.max_position_error_m] * 2 + [opts.max_vertical_error_m]))


@pytest.fixture(scope="module")
def joint_fit(drifting_runs):
    """The skewed mount on the drifting estimate, fitted with the drift beside it: (the estimate, what each joint fit on
    planes held returned over all the points, what it returned on each group of sweeps), each as (the fit, (mount,
    drift), window, free)."""
    _, skewed = drifting_runs
    s, h = _usable(skewed)
    ended, groups = [], []
    real_held = _DriftFit.held

    def held(self, q, delta, window, sub=None, free=None):
        out = real_held(self, q, delta, window, sub, free)
        (ended if sub is None else groups).append((self, out, window, free))
        return out

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(_DriftFit, "held", held)
        joint = estimate_mount(s, h["lever_arm_body_m"], StorageFrame(), STORAGE, h["sensor"]["range_sigma_m"],
                               h["sensor"]["range_sigma_rel"], Resimulated.from_header(h), drift=_drift_of(s, h))
    return joint, ended, groups


def test_that_a_mount_under_a_drifting_pose_is_found_with_the_drift_fitted_beside_it(drifting_runs, joint_fit):
    """The drift bends the structure as no mount does, so the mount alone is not found; with a smooth drift of the
    position fitted beside it (and thrown away) the servo's offset and scale and the tilt come out, and a square mount
    on the same drift stays square."""
    square, skewed = drifting_runs
    s, h = _usable(skewed)
    args = (s, h["lever_arm_body_m"], StorageFrame(), STORAGE, h["sensor"]["range_sigma_m"],
            h["sensor"]["range_sigma_rel"], Resimulated.from_header(h))
    assert not estimate_mount(*args).any_applied
    joint = joint_fit[0]
    assert joint.applied[:3] == (True, True, True)
    assert abs(math.degrees(joint.values[0]) - 3.0) < 0.1
    assert abs(joint.values[1] - 0.05) < 0.005
    assert abs(math.degrees(joint.values[2]) - 2.0) < 0.5
    s, h = _usable(square)
    assert not estimate_mount(s, *args[1:], drift=_drift_of(s, h)).any_applied


@pytest.mark.parametrize("start", [(1.0, -1.0, 0.5), (math.nan,) * 3], ids=["a metre off", "not finite"])
def test_that_of_two_starts_for_the_drift_the_fit_keeps_the_one_the_structure_agrees_with(drifting_runs, start):
    """The joint fit runs from no drift and from the start it is given (the pose correction's own fit) and keeps the
    fit that puts more points on the floor and walls: a start a metre off everywhere loses to no drift (from it alone
    the fit is refused, 0.8 cm off), a start that is not finite is skipped, and the mount still comes out."""
    _, skewed = drifting_runs
    s, h = _usable(skewed)
    drift = _drift_of(s, h)
    far = DriftNuisance(drift.knots_s, drift.step_sigma_m, drift.abs_sigma_m, np.tile(start, (len(drift.knots_s), 1)))
    joint = estimate_mount(s, h["lever_arm_body_m"], StorageFrame(), STORAGE, h["sensor"]["range_sigma_m"],
                           h["sensor"]["range_sigma_rel"], Resimulated.from_header(h), drift=far)
    assert joint.applied[:3] == (True, True, True)
    assert abs(math.degrees(joint.values[0]) - 3.0) < 0.1
    assert abs(math.degrees(joint.values[2]) - 2.0) < 0.5


def test_that_the_mount_and_the_drift_fitted_together_end_where_a_further_fit_hardly_moves_them(joint_fit):
    """The joint fit ends on planes held, by reweighted rounds to convergence (`_DriftFit.held`), the planes assigned
    again where it ended until that moves nothing beyond the noise: one more such fit moves the mount by less than
    0.01 deg and the drift by less than a centimetre. (The rounds that assign the planes at every step had stopped
    with the tilt still moving tenths of a degree a round and the drift decimetres, and the mount fitted alone on the
    drift they left moved the tilt 0.5 deg further.) Its standard errors come from groups of sweeps each fitted with
    a drift of its own, not with the whole fit's held."""
    joint, ended, groups = joint_fit
    assert joint.applied[:3] == (True, True, True)
    fit, (q, delta), window, free = ended[-1]
    q2, delta2 = fit.held(q, delta, window, free=free)
    assert math.degrees(np.abs(q2 - q).max()) < 0.01
    assert np.abs(delta2 - delta).max() < 0.01
    assert len(groups) == N_GROUPS
    assert all(np.abs(d - delta).max() > 1e-4 for _, (_, d), _, _ in groups)  # each group's drift its own


def test_that_a_joint_step_solves_the_normal_equations_of_the_whole_jacobian_written_out():
    """`_DriftFit._step` sums the normal equations knot interval by knot interval (dense, for speed): on points at
    random times, planes and weights, its step is the one of the whole Jacobian (the drift's columns beside the
    mount's) with the arctan loss's weights and the prior, and a parameter held does not move."""
    rng = np.random.default_rng(7)
    n_pts, n_k = 500, 6
    t_s = rng.uniform(0.0, 10.0, n_pts)
    kk, ff = knot_basis(t_s, np.linspace(0.0, 10.0, n_k))
    normals = rng.normal(size=(4, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    square = rng.normal(size=(3 * n_k + 4, 3 * n_k + 4))
    fit = SimpleNamespace(idx=np.arange(n_pts), kk=kk, ff=ff, n=normals, n_k=n_k, p_all=square @ square.T)
    keep, j = rng.permutation(n_pts)[:400], rng.integers(0, 4, 400)
    r, w_m = rng.normal(0.0, 0.01, 400), rng.uniform(0.003, 0.02, 400)
    jac, delta, free = rng.normal(size=(400, 4)), rng.normal(0.0, 0.1, (n_k, 3)), np.array([True, False, True, True])
    d_delta, d_q = _DriftFit._step(fit, keep, j, r, w_m, np.zeros(4), delta, lambda _q: jac, free)
    a = np.hstack([_DriftFit._drift_columns(fit, keep, j).toarray(), jac * free])
    w = 1.0 / (1.0 + (r / w_m) ** 4) / w_m ** 2
    normal = a.T @ (w[:, None] * a) + fit.p_all + np.diag(np.r_[np.zeros(3 * n_k), ~free])
    step = np.linalg.solve(normal, -a.T @ (w * r) - fit.p_all @ np.r_[delta.T.ravel(), np.zeros(4)])
    np.testing.assert_allclose(np.r_[d_delta.T.ravel(), d_q], np.r_[step[:3 * n_k], step[3 * n_k:] * free],
                               rtol=1e-9, atol=1e-12)
    assert d_q[1] == 0.0


def test_that_a_mount_fitted_beside_a_drift_with_its_boresight_held_fits_the_servo_alone_and_says_so(drifting_runs):
    """The report may hold the boresight as configured (`held`): the tilt and yaw are then exactly the configured
    ones and not applied, the servo's offset and scale are fitted beside the drift without them and still found, and
    the report's line and report.json say they were held by choice, not for want of data."""
    _, skewed = drifting_runs
    s, h = _usable(skewed)
    est = estimate_mount(s, h["lever_arm_body_m"], StorageFrame(), STORAGE, h["sensor"]["range_sigma_m"],
                         h["sensor"]["range_sigma_rel"], Resimulated.from_header(h), drift=_drift_of(s, h),
                         held=report.BORESIGHT_HELD)
    assert est.applied == (True, True, False, False)
    assert est.values[2:] == (0.0, 0.0)
    assert est.held == (False, False, True, True)
    assert abs(math.degrees(est.values[0]) - 3.0) < 0.2
    line = describe(est)
    assert "held as configured, as the flight is explained as well without them: boresight tilt, sweep-plane yaw" \
        in line
    assert "does not constrain" not in line
    d = est.as_dict()
    assert d["boresight_tilt_deg"]["held_as_configured"] and not d["servo_scale"]["held_as_configured"]


def _estimates(applied):
    est = MountEstimate((0.01, 0.05, 0.03, 0.03), (0.001,) * 4, applied, (100,) * 5, 0.05, 0.004, with_drift=True)
    return report._Estimates(est, np.zeros(0, dtype=SAMPLE_DTYPE), SQUARE, None, joint=True)


@pytest.mark.parametrize("joint_applied, simpler_found, boresight_better, kept", [
    ((True, True, True, False), True, False, "simpler"),
    ((True, True, True, False), True, True, "joint"),
    ((True, True, True, False), False, None, "joint"),
    ((True, True, False, False), None, None, "joint"),
], ids=["no better with it", "better with it", "nothing without it", "no boresight"])
def test_that_a_boresight_fitted_beside_a_drift_is_kept_only_where_it_explains_the_flight_better(
        monkeypatch, joint_applied, simpler_found, boresight_better, kept):
    """Beside a drift a tilt or yaw can take up what the drift's translation cannot follow: the mount with the
    boresight held is fitted (only when the joint one applied a boresight) and kept unless the boresight explains the
    floor, walls and pile seen twice better; with nothing applied without it, the joint mount stands."""
    joint, simpler = _estimates(joint_applied), _estimates((True, True, False, False))
    asked = []

    def without():
        asked.append(True)
        return simpler if simpler_found else None

    monkeypatch.setattr(report, "_explains_more", lambda first, second, *_: boresight_better)
    got = report._boresight_if_needed(joint, without, np.zeros(3), StorageFrame(), STORAGE, 0.0)
    assert got is (simpler if kept == "simpler" else joint)
    assert bool(asked) == any(joint_applied[2:])


def test_that_a_drift_start_of_the_wrong_shape_is_refused():
    with pytest.raises(ValueError, match="start"):
        DriftNuisance(np.arange(4.0), np.ones(3), np.ones(3), np.zeros((3, 3)))


def _assert_found_beside_the_drift(tmp_path, profile: str, fault: str, size: float, tolerance: float,
                                   mission: Mission) -> None:
    """A batch flight of the paper's pile 1 on this mission (a fifth of a firmware flight's cost) on this drift with
    this one mount fault (a `FaultSpec` field in degrees, which report.json's self-calibration names alike): the report
    finds the fault within tolerance, fitted with the drift beside it, corrects the pose on it, and reads within 1 %."""
    cfg = FlyConfig(mission=mission, stockpile="1", payload="batch", seed=0, pose_error=profile,
                    faults=FaultSpec(**{fault: size}))
    fly(cfg, tmp_path / "run", force=True, progress=lambda _m: None)
    rep = make_report(tmp_path / "run", tmp_path / "rep", ReportOptions(plots=False))
    cal = rep["self_calibration"]
    assert cal["fitted_with_drift"] is True and cal[fault]["applied"], cal
    assert abs(cal[fault]["estimate"] - size) < tolerance
    assert rep["pose_correction"]["applied"] is True
    assert abs(signed_error_pct(rep)) < 1.0


def test_that_a_mount_proposed_beside_a_drift_is_judged_by_the_pose_correction_not_by_what_the_drift_leaves(tmp_path):
    """A servo 3 deg off on a `flow` flight over the paper's pile 1: the joint fit (the mount with a translation drift
    beside it) finds the offset and leaves the walls about 1 cm off their planes against 0.3 cm of noise, since the
    heading's drift and the downward rangefinder's share are not in its nuisance. The proposal goes to the pose
    correction, which has a heading of its own and fits the samples with the share out, and which judges the planes
    itself. Refused by the mount fit for what the drift left, the report kept neither the mount nor the pose: Ve
    -3.2 % here (the firmware's flights of seeds 0 and 1 over piles 1 and 2: -13.9 and -8.4 %). Measured: -0.50 %,
    the offset +3.07 +- 0.09 deg. The batch payload at 2 m/s: a fifth of a firmware flight's cost, and this flight's
    mount was refused as the firmware's were."""
    _assert_found_beside_the_drift(tmp_path, "flow", "servo_offset_deg", 3.0, 0.2, Mission(p_traj=0.2, speed_m_s=2.0))


def test_that_a_sweep_yawed_off_square_that_the_drift_took_up_is_found_with_the_drift_beside_it(tmp_path):
    """A sweep yawed 2 deg on a `vio` flight: the mount's fit alone refuses (the drift bends the structure), and the
    pose correction alone explains the floor and walls, since a yawed sweep moves each side's points along the track,
    which the walls beside the track do not see, and its knots take the rest up as a drift. The mount fitted with the
    drift beside it finds the yaw, and is kept because it explains the pile seen on opposite passes better at no cost
    on the floor and walls (`explains_more`). In the module's small building at 2 m/s: before, the yaw was not found
    (Ve -3.27 %); measured: +2.12 deg, Ve -0.20 %."""
    _assert_found_beside_the_drift(tmp_path, "vio", "sweep_yaw_deg", 2.0, 0.5,
                                   Mission(storage=STORAGE, p_traj=0.2, altitude_m=8.0, speed_m_s=2.0))


def test_that_the_report_corrects_a_mount_fault_and_a_drift_together(drifting_runs, square_report, tmp_path,
                                                                     monkeypatch):
    """A mount fault under a drifting pose: the mount's fit alone refuses (the drift bends the structure), the pose's
    alone refuses (the mount does), so the report fits the mount with a drift beside it, started also from the drift
    the pose's fit found, and corrects the pose on that mount. The volume: the square mount on the same drift reads
    +0.46 % against the error-free flight's +0.01 % (the pose correction's own residual, beyond issue 15's 0.3 pp on
    this drift), so the faulted flight is held to that residual plus 0.3 pp (the mount check's bound). Measured:
    -0.30 % (-0.11 % until a pile's flank in a sweep nearly parallel to a wall stopped passing for that wall, when the
    square mount read +0.50 %); both refused, -2.10 %."""
    square, skewed = drifting_runs
    clean = square_report
    real_mount_of, starts = report._mount_of, []

    def mount_of(*a, **k):
        drift = a[7] if len(a) > 7 else k.get("drift")
        starts.append(None if drift is None else drift.start_m)
        return real_mount_of(*a, **k)

    monkeypatch.setattr(report, "_mount_of", mount_of)
    fixed = make_report(skewed, tmp_path / "fixed", ReportOptions(plots=False))
    monkeypatch.undo()
    given = [m for m in starts if m is not None]
    assert given[0].shape[1] == 3 and np.abs(given[0]).max() > 0.01  # the pose's own drift fit
    # and, the tilt applied beside the servo, once more from the same start with the boresight held; the tilt, which
    # is there, explains the flight better and is kept
    assert len(given) == 2 and np.array_equal(given[1], given[0])
    cal = fixed["self_calibration"]
    assert all(cal[k]["applied"] for k in ("servo_offset_deg", "servo_scale", "boresight_tilt_deg"))
    assert abs(cal["servo_offset_deg"]["estimate"] - 3.0) < 0.1
    assert cal["fitted_with_drift"] is True
    assert any(w.startswith("self-calibration from the building applied") and "fitted together with the pose's drift"
               in w for w in fixed["warnings"])
    assert fixed["pose_correction"]["applied"] is True
    twin = make_report(square, tmp_path / "twin", ReportOptions(plots=False))
    residual = abs(signed_error_pct(twin) - signed_error_pct(clean))  # what the drift's correction leaves alone
    assert abs(signed_error_pct(fixed) - signed_error_pct(clean)) < residual + 0.3
    monkeypatch.setattr(report, "_mount_with_drift", lambda *a, **k: None)  # as before the joint fit
    both_refused = make_report(skewed, tmp_path / "refused", ReportOptions(plots=False))
    assert not any(v["applied"] for k, v in both_refused["self_calibration"].items() if k.endswith(("_deg", "scale")))
    assert both_refused["pose_correction"]["applied"] is False
    assert "a drifting pose does not explain them" in both_refused["pose_correction"]["reason"]
    assert abs(signed_error_pct(both_refused) - signed_error_pct(clean)) > 1.0


def test_that_a_second_fit_on_the_same_drive_re_simulates_nothing_and_gets_the_same_angles(monkeypatch):
    """The mount is fitted several times a report on the same samples; each fit's servo re-simulations at the same
    scales are remembered by the drive and the scale, and what is remembered is what would be computed."""
    from pathlib import Path

    import ground.self_calibration as sc

    log = read_samplelog(Path(__file__).resolve().parents[1] / "golden" / "samples.pslog")
    resim = Resimulated.from_header(log.header)
    assert resim is not None
    sc.forget_sims()
    runs = []
    monkeypatch.setattr(sc, "servo_angles", lambda *a, **k: runs.append(1) or servo_angles(*a, **k))
    first = ServoAngles(log.samples, resim)
    at_5pct = first.exact(0.05).copy()
    assert len(runs) == 2  # the nominal sweep and the 5 % one
    second = ServoAngles(log.samples, resim)
    assert np.array_equal(second.exact(0.05), at_5pct) and np.array_equal(second.nominal, first.nominal)
    assert len(runs) == 2
    with pytest.raises(ValueError, match="read-only"):
        second.nominal[0] = 0.0  # shared between the fits: nobody may write into it
    other = log.samples.copy()
    other["t_s"] += 0.01  # another drive: its own re-simulation
    ServoAngles(other, resim)
    assert len(runs) == 3
    sc.forget_sims()
    ServoAngles(log.samples, resim)
    assert len(runs) == 4
