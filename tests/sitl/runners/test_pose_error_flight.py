"""Flights on an indoor estimate (--pose-error): the autopilot flies on it and reports it, the log is tagged
with it, truth.json keeps the true trajectory, the header says which profile flew."""

import json

import numpy as np
import pytest

from firmware_py.core.cli import RunFailure
from firmware_py.core.pose_source import PoseSource
from firmware_py.core.samplelog import read_samplelog
from firmware_py.core.storage import Storage
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from sitl.runners.serve import SIMULATOR_CLOCK, ServeOptions, serve
from sitl.sensing.pose_drift import PROFILES, PoseErrorProfile, ekf_source_params

MISSION = Mission(storage=Storage(30, 20, 12), p_traj=0.2, altitude_m=8.5)
W = PROFILES[PoseErrorProfile.FLOW].rangefinder_weight


@pytest.fixture(scope="module", params=[("ideal", "batch"), ("jsbsim", "batch"), ("jsbsim", "firmware")],
                ids=lambda p: "-".join(p))
def flow_run(request, tmp_path_factory):
    plant, payload = request.param
    out = tmp_path_factory.mktemp(f"flow-{plant}-{payload}")
    fly(FlyConfig(mission=MISSION, plant=plant, payload=payload, pose_error="flow", seed=3), out)
    truth = json.loads((out / "truth.json").read_text())
    return out, truth, read_samplelog(out / "samples.pslog"), payload


def test_that_truth_keeps_the_profile_its_seed_the_error_statistics_and_the_true_trajectory(flow_run):
    _, truth, log, _ = flow_run
    pe = truth["pose_error"]
    assert pe["profile"] == "flow" and pe["seed"] == 3
    assert pe["stats"]["horizontal_rms_m"] > 0.02 and pe["stats"]["heading_rms_deg"] > 0
    tr = pe["trajectory"]
    n = len(tr["t_s"])
    assert n > 10 * 60 and np.allclose(np.diff(tr["t_s"]), 0.1)
    assert np.shape(tr["true_w_m"]) == (n, 3) and len(tr["true_yaw_rad"]) == n
    # on the log's clock: the trajectory spans the samples
    t = log.samples["t_s"]
    assert tr["t_s"][0] <= t[0] + 1.0 and tr["t_s"][-1] >= t[-1] - 1.0


def test_that_the_log_header_says_which_profile_flew(flow_run):
    _, truth, log, _ = flow_run
    assert log.header["pose_error"]["profile"] == "flow"
    assert log.header["pose_error"]["seed"] == 3
    assert log.header["pose_error"]["params"] == truth["pose_error"]["params"]


def test_that_the_logged_pose_is_the_estimate_not_the_truth(flow_run):
    _, truth, log, payload = flow_run
    tr = truth["pose_error"]["trajectory"]
    s = log.samples[(log.samples["t_s"] >= tr["t_s"][0]) & (log.samples["t_s"] <= tr["t_s"][-1])]
    at = lambda key: np.column_stack([np.interp(s["t_s"], tr["t_s"], np.asarray(tr[key])[:, j])  # noqa: E731
                                      for j in range(3)])
    logged = FlyConfig(mission=MISSION).frame.ned_to_w(np.column_stack([s["x_m"], s["y_m"], s["z_m"]]))
    true, est = at("true_w_m"), at("estimated_w_m")
    tol = 0.02 if payload == "batch" else 0.1  # the payload interpolates the 50 Hz pose stream
    off_true = np.abs(logged - true).max(axis=0)
    assert np.abs(logged - est).max(axis=0)[:2].max() < tol
    assert off_true[2] > 0.5 and off_true[:2].max() > 0.05  # the error is there, the truth is not what was logged


def test_that_the_vehicle_flew_on_the_estimate_so_the_true_path_left_the_plan(flow_run):
    _, truth, _, _ = flow_run
    tr = truth["pose_error"]["trajectory"]
    true_z, est_z = np.asarray(tr["true_w_m"])[:, 2], np.asarray(tr["estimated_w_m"])[:, 2]
    # The estimate holds the planned height; the truth climbs over the pile (its rangefinder height)
    assert np.abs(est_z - MISSION.altitude_m).max() < 0.35
    assert true_z.max() - MISSION.altitude_m > 0.5 * W * 7.0
    assert true_z.max() < MISSION.storage.height_m - MISSION.min_clearance_m


def test_that_no_pose_error_leaves_truth_and_header_as_before(tmp_path):
    fly(FlyConfig(mission=MISSION, plant="ideal", seed=3), tmp_path)
    assert "pose_error" not in json.loads((tmp_path / "truth.json").read_text())
    assert "pose_error" not in read_samplelog(tmp_path / "samples.pslog").header


def test_that_truth_keeps_how_far_the_vehicle_stayed_above_the_pile(flow_run):
    """Over the survey only: a lockstep flight starts below its first waypoint, which may lie in the pile. The `flow`
    estimate reads low over the pile, so the vehicle climbs: more room than the plan's 0.5 m, not less."""
    _, truth, _, _ = flow_run
    near = truth["closest_pile_approach"]
    assert near["surface"] == "the pile" and 0.5 - 0.16 < near["distance_m"] < MISSION.altitude_m


def test_that_a_flow_flight_that_would_climb_into_the_roof_is_refused(tmp_path):
    with pytest.raises(ValueError, match="roof"):
        fly(FlyConfig(mission=Mission(storage=Storage(30, 20, 10), p_traj=0.2, altitude_m=8.0), plant="ideal",
                      pose_error="flow"), tmp_path)


def test_that_a_flight_whose_drift_takes_it_into_a_wall_is_a_crash_and_writes_no_survey(tmp_path):
    # The paper's building at P_traj 5 %: the legs run 2 m from the long walls, and the `flow` estimate of seed 0
    # drifts the true vehicle into the wall y = W near the end. A real flight ends there.
    out = tmp_path / "run"
    with pytest.raises(RunFailure, match=r"hit the wall y = W .*flow pose estimate"):
        fly(FlyConfig(mission=Mission(p_traj=0.05), stockpile="1", plant="ideal", pose_error="flow", seed=0), out)
    assert not (out / "truth.json").exists() and not (out / "samples.pslog").exists()
    fly(FlyConfig(mission=Mission(p_traj=0.05), stockpile="1", plant="ideal", seed=0), out)  # on the truth: clear
    approach = json.loads((out / "truth.json").read_text())["closest_approach"]
    assert approach["surface"].startswith("the wall") and approach["distance_m"] == pytest.approx(2.0, abs=0.01)


def test_that_a_drift_larger_than_the_room_to_the_walls_is_warned_before_the_flight():
    from sitl.runners.fly import drift_warning
    near = Mission(p_traj=0.05)  # legs 2 m from the long walls, a ~200 m loop
    warning = drift_warning(near, PoseErrorProfile.FLOW)
    assert warning is not None and "2.00 m from the walls" in warning and "P_traj" in warning
    assert drift_warning(near, PoseErrorProfile.NONE) is None  # flown on the truth: the plan keeps clear
    assert drift_warning(Mission(p_traj=0.2), PoseErrorProfile.FLOW) is None  # 8 m from the walls


def test_that_a_bad_profile_is_one_clear_error():
    with pytest.raises(ValueError, match="none, flow, vio"):
        FlyConfig(mission=MISSION, pose_error="bogus")


def test_that_serve_needs_the_jsbsim_vehicle_for_a_pose_error():
    with pytest.raises(ValueError, match="jsbsim"):
        ServeOptions(mission=MISSION, vehicle="kinematic", pose_error=PoseErrorProfile.VIO)
    assert ServeOptions(mission=MISSION, pose_error="vio").fly_config().pose_error is PoseErrorProfile.VIO


def test_that_serve_keeps_the_true_and_estimated_trajectories_on_the_simulators_clock(tmp_path):
    # A short served run (nobody flies it: the vehicle waits on the ground while its estimate walks): truth.json
    # holds the trajectories as fly's does, stamped as the simulator's clock, which the payload's log is not on.
    out = tmp_path / "served"
    code = serve(ServeOptions(mission=MISSION, url="udp:127.0.0.1:0", duration_s=1.5, out=out,
                              devices_url="tcp:127.0.0.1:0", pose_error="vio"))
    assert code == 0
    truth = json.loads((out / "truth.json").read_text())
    traj = truth["pose_error"]["trajectory"]
    assert traj["clock"] == SIMULATOR_CLOCK
    assert "closest_pile_approach" in truth and truth["closest_pile_approach"] is None  # on clear floor, no pile under
    t = np.asarray(traj["t_s"])
    assert len(t) >= 10 and 0.0 <= t[0] and t[-1] <= 1.5 + 0.1 and np.all(np.diff(t) > 0)
    true_w, est_w = np.asarray(traj["true_w_m"]), np.asarray(traj["estimated_w_m"])
    assert true_w.shape == est_w.shape == (len(t), 3)
    assert np.abs(est_w - true_w).max() > 0.0  # the estimate walks from the start


def test_that_the_header_says_what_the_autopilot_s_ekf_took_its_pose_from(flow_run):
    _, _, log, _ = flow_run
    # the firmware read them from the simulated autopilot over MAVLink; the batch path writes the same
    assert log.header["autopilot_params"] == ekf_source_params(PoseErrorProfile.FLOW)
    source = PoseSource.from_header(log.header)
    assert source.horizontal_drifts and source.height_from_rangefinder
    assert source.describe().startswith("position optical flow velocity, integrated; height barometer, the downward "
                                        "rangefinder below 70 % of its range")


def test_that_the_report_measures_the_rangefinder_s_share_of_the_height_and_takes_it_out(flow_run, tmp_path):
    from ground.report import ReportOptions, make_report
    out, _, _, payload = flow_run
    if payload != "firmware":
        pytest.skip("the three paths write the same header (above): the firmware's flight, as flown, shows the step")
    on = make_report(out, tmp_path / "on", ReportOptions(plots=False))
    off = make_report(out, tmp_path / "off", ReportOptions(plots=False, pose_correction=False))
    rf = on["rangefinder_height"]
    assert rf["applied"] and abs(rf["share"] - W) < 0.1 and rf["sigma"] < 0.05  # the SITL's weight, from the data
    assert off["rangefinder_height"] is None  # with the pose correction off, nothing is taken out
    assert abs(on["volume_error_pct"]) < 0.5 * abs(off["volume_error_pct"])
    assert any("followed the pile" in w for w in on["warnings"])
    assert not any("came from its downward rangefinder" in w for w in on["warnings"])  # taken out: no alarm
    # the lift over time it reports puts the logged trajectory where the survey placed it: nearer the truth
    from tools.pose_correction_campaign import trajectory_rms_m
    truth = json.loads((out / "truth.json").read_text())
    _, with_lift = trajectory_rms_m(truth, on["pose_correction"], rf)
    _, without_lift = trajectory_rms_m(truth, on["pose_correction"])
    assert with_lift < without_lift


def test_that_a_planned_loop_is_warned_of_drift_by_its_own_waypoints():
    """The coverage planner's loops have no P_traj: their room to the walls is their waypoints' (it raised an
    AttributeError, a traceback from `fly --mission coverage --pose-error flow`)."""
    from sitl.missions.coverage import LoopMission
    from sitl.runners.fly import drift_warning, legs_room_m
    s = Mission().storage
    def loop(south_m: float) -> LoopMission:  # 8 m from three walls, south_m from the fourth
        wp = [(8.0, south_m), (s.length_m - 8.0, south_m), (s.length_m - 8.0, s.width_m - 8.0),
              (8.0, s.width_m - 8.0), (8.0, south_m)]
        return LoopMission(storage=s, waypoints=tuple(wp))
    near = loop(1.5)
    assert legs_room_m(near) == pytest.approx(1.5)
    warning = drift_warning(near, PoseErrorProfile.FLOW)
    assert warning is not None and "1.50 m from the walls" in warning and "legs further from the walls" in warning
    assert drift_warning(loop(8.0), PoseErrorProfile.VIO) is None  # 8 m of room, a 1.5 % drift of ~150 m
    assert legs_room_m(Mission(p_traj=0.05)) == pytest.approx(2.0)  # the rectangle: P_traj of the shorter side
