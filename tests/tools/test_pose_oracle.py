"""tools.pose_oracle: a drifting flight re-posed with the truth it keeps, and the split of its volume error."""

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleLogWriter, new_records, read_samplelog
from firmware_py.core.storage import Storage
from tools import pose_oracle, source_digest
from tools.pose_oracle import (
    HEIGHT,
    HORIZONTAL,
    flights,
    height_table,
    horizontal_table,
    parse_run,
    repose,
    table,
    truth_correction,
    with_true_pose_in,
)

FRAME = StorageFrame(origin_ned_m=(3.0, -2.0, 0.0), heading_rad=math.radians(30.0))
STORAGE = Storage(length_m=30.0, width_m=20.0, height_m=10.0)


def _trajectory(t: np.ndarray, profile: str = "vio") -> dict:
    true_w = np.column_stack([5.0 + t, 10.0 + 0.0 * t, 6.0 + 0.0 * t])
    est_w = true_w + np.column_stack([0.01 * t, -0.02 * t, 0.1 + 0.0 * t])  # drifting, 0.1 m high
    true_yaw = np.full(len(t), 0.5)
    return {"profile": profile, "trajectory": {
        "rate_hz": 10.0, "frame": "W", "t_s": t.tolist(), "true_w_m": true_w.tolist(),
        "true_yaw_rad": true_yaw.tolist(), "estimated_w_m": est_w.tolist(),
        "estimated_yaw_rad": (true_yaw + 0.01).tolist()}}


def _run(folder: Path, name: str, profile: str = "vio") -> Path:
    """A run folder whose samples carry the estimate of `_trajectory`, and its truth."""
    run = folder / name
    run.mkdir(parents=True)
    t = np.arange(0.0, 10.0001, 0.1)
    traj = _trajectory(t, profile)
    s = new_records(len(t))
    s["t_s"] = t
    ned = FRAME.w_to_ned(np.asarray(traj["trajectory"]["estimated_w_m"]))
    s["x_m"], s["y_m"], s["z_m"] = ned[:, 0], ned[:, 1], ned[:, 2]
    s["yaw_rad"] = traj["trajectory"]["estimated_yaw_rad"]
    s["range_m"] = 5.0
    with SampleLogWriter(run / "samples.pslog", {"storage_frame": FRAME.to_dict()}, fsync=False) as w:
        w.append(s)
    (run / "truth.json").write_text(json.dumps({"true_volume_m3": 100.0, "storage": STORAGE.to_dict(),
                                                "pose_error": traj}))
    return run


def _reposed(folder: Path, name: str, components: tuple[int, ...]):
    """A run of `_run` re-posed in these components: (the run, the re-posed samples, the logged ones, their positions
    in W, and the truth's trajectory)."""
    run = _run(folder, name)
    assert repose(run, folder / "reposed", components)
    logged = read_samplelog(run / "samples.pslog").samples
    log = read_samplelog(folder / "reposed" / "samples.pslog").samples
    truth = json.loads((run / "truth.json").read_text())["pose_error"]["trajectory"]
    w = FRAME.ned_to_w(np.column_stack([log["x_m"], log["y_m"], log["z_m"]]))
    w_logged = FRAME.ned_to_w(np.column_stack([logged["x_m"], logged["y_m"], logged["z_m"]]))
    return run, log, logged, w, w_logged, truth


def test_that_the_truth_correction_is_the_true_trajectory_less_the_estimate():
    corr = truth_correction({"pose_error": _trajectory(np.array([0.0, 10.0]))})
    assert corr is not None and corr.applied
    np.testing.assert_allclose(corr.values[1], [-0.1, 0.2, -0.1, 0.01], atol=1e-12)


def test_that_a_flight_without_a_pose_error_has_no_truth_correction():
    assert truth_correction({"pose_error": None}) is None
    assert truth_correction({"pose_error": _trajectory(np.array([0.0, 1.0]), "none")}) is None


def test_that_a_re_posed_run_carries_the_true_pose_in_its_samples_and_the_rest_of_the_run_unchanged(tmp_path: Path):
    run = _run(tmp_path, "vio-1-20-0")
    (run / "pile.stl").write_text("solid x\nendsolid x\n")
    assert repose(run, tmp_path / "oracle")
    log = read_samplelog(tmp_path / "oracle" / "samples.pslog")
    assert log.intact and log.header["storage_frame"] == FRAME.to_dict()
    truth = json.loads((run / "truth.json").read_text())["pose_error"]["trajectory"]
    w = FRAME.ned_to_w(np.column_stack([log.samples["x_m"], log.samples["y_m"], log.samples["z_m"]]))
    np.testing.assert_allclose(w, truth["true_w_m"], atol=1e-4)  # float32 records
    np.testing.assert_allclose(log.samples["yaw_rad"], truth["true_yaw_rad"], atol=1e-6)
    assert (tmp_path / "oracle" / "pile.stl").read_text() == (run / "pile.stl").read_text()


def test_that_only_reported_drifting_flights_are_taken_not_error_free_flights_nor_reports(tmp_path: Path):
    for name in ("vio-1-20-0", "flow-2-5-1", "none-1-20-0", "vio-1-5-0"):
        _run(tmp_path, name, name.split("-")[0])
        if name != "vio-1-5-0":  # a flight the campaign did not report (it crashed)
            (tmp_path / f"{name}--pose-correction").mkdir()
    assert [p.name for p in flights([tmp_path])] == ["flow-2-5-1", "vio-1-20-0"]


def test_that_a_run_name_is_read_with_dashes_in_the_pile_and_the_noise():
    assert parse_run("flow-cone-1-20-3") == {"profile": "flow", "pile": "cone-1", "p_traj": 20, "seed": 3,
                                             "noise": "none"}
    assert parse_run("vio-2-5-0-appendix-a") == {"profile": "vio", "pile": "2", "p_traj": 5, "seed": 0,
                                                 "noise": "appendix-a"}
    with pytest.raises(ValueError, match="not a pose campaign"):
        parse_run("demo")


def test_that_the_table_splits_the_error_into_the_path_s_share_and_the_correction_s_residual():
    rows = [{"run": "vio-2-20-0", "folder": "pose", "profile": "vio", "ve_ref": 1.05, "ve_true_pose": 0.22,
             "ve_corrected": -0.22},
            {"run": "vio-2-20-1", "folder": "pose", "profile": "vio", "ve_ref": 1.05, "ve_true_pose": 1.00,
             "ve_corrected": 1.10}]
    line = next(row for row in table(rows).splitlines() if row.startswith("| pose |"))
    # path 0.83 and 0.05 pp; residual 0.44 and 0.10 pp; total 1.27 and 0.05 pp
    assert line == "| pose | 2 | 20 % | 2 | 0.44 / 0.83 | 1/2 | 0.27 / 0.44 | 1/2 | 0.66 | 1/2 |"


def test_that_a_run_re_posed_in_its_height_only_keeps_the_logged_position_and_heading(tmp_path: Path):
    _, log, logged, w, w_logged, truth = _reposed(tmp_path, "flow-1-20-0", HEIGHT)
    np.testing.assert_allclose(w[:, 2], np.asarray(truth["true_w_m"])[:, 2], atol=1e-4)  # the true height
    np.testing.assert_allclose(w[:, :2], w_logged[:, :2], atol=1e-4)  # the drift in x and y kept
    assert np.abs(w[:, :2] - np.asarray(truth["true_w_m"])[:, :2]).max() > 0.1
    np.testing.assert_allclose(log["yaw_rad"], logged["yaw_rad"], atol=1e-6)  # and in the heading


def test_that_the_truth_of_a_flight_with_its_true_height_has_an_estimate_off_in_x_and_y_only():
    truth = {"pose_error": _trajectory(np.array([0.0, 10.0]))}
    tr = with_true_pose_in(truth, HEIGHT)["pose_error"]["trajectory"]
    est, true = np.asarray(tr["estimated_w_m"]), np.asarray(tr["true_w_m"])
    np.testing.assert_allclose(est[:, 2], true[:, 2])
    np.testing.assert_allclose(est[1, :2] - true[1, :2], [0.1, -0.2])
    assert truth["pose_error"]["trajectory"]["estimated_w_m"][0][2] == pytest.approx(6.1)  # the input untouched


def test_that_the_height_table_sets_the_logged_height_beside_the_true_one():
    rows = [{"run": "flow-2-5-1", "folder": "pose", "profile": "flow", "ve_ref": 0.0, "ve_corrected": 3.4,
             "ve_true_height": 0.6, "traj_corrected_m": 0.194, "traj_true_height_m": 0.054},
            {"run": "vio-2-5-1", "folder": "pose", "profile": "vio", "ve_ref": 0.0, "ve_corrected": -0.2,
             "ve_true_height": 0.1, "traj_corrected_m": 0.090, "traj_true_height_m": 0.036}]
    line = next(row for row in height_table(rows).splitlines() if row.startswith("| pose |"))
    assert line == "| pose | 2 | 5 % | 2 | 0.142 / 0.045 | 1 / 2 | 1.80 / 0.35 | 1 / 1 |"


def test_that_a_run_re_posed_in_its_horizontal_only_keeps_the_logged_height_and_its_drift(tmp_path: Path):
    run, log, _, w, w_logged, truth = _reposed(tmp_path, "vio-1-20-0", HORIZONTAL)
    np.testing.assert_allclose(w[:, :2], np.asarray(truth["true_w_m"])[:, :2], atol=1e-4)  # the true x and y
    np.testing.assert_allclose(log["yaw_rad"], truth["true_yaw_rad"], atol=1e-6)  # and heading
    np.testing.assert_allclose(w[:, 2], w_logged[:, 2], atol=1e-4)  # the height as logged: 0.1 m high
    assert np.abs(w[:, 2] - np.asarray(truth["true_w_m"])[:, 2]).min() > 0.09
    est = np.asarray(with_true_pose_in(json.loads((run / "truth.json").read_text()), HORIZONTAL)
                     ["pose_error"]["trajectory"]["estimated_w_m"])
    np.testing.assert_allclose(est[:, :2], np.asarray(truth["true_w_m"])[:, :2])  # its truth: off in z only
    np.testing.assert_allclose(est[:, 2] - np.asarray(truth["true_w_m"])[:, 2], 0.1, atol=1e-12)


def test_that_the_horizontal_table_sets_the_flight_as_logged_and_corrected_beside_its_true_pose():
    rows = [{"run": "vio-1-20-2", "folder": "pose", "profile": "vio", "ve_true_pose": -0.01, "ve_logged": 3.39,
             "ve_corrected": 0.20, "applied": True, "traj_before_m": 0.143, "traj_after_m": 0.031},
            {"run": "flow-1-20-4", "folder": "pose", "profile": "flow", "ve_true_pose": 0.01, "ve_logged": 0.46,
             "ve_corrected": 0.46, "applied": False, "traj_before_m": 0.091, "traj_after_m": 0.091}]
    line = next(row for row in horizontal_table(rows).splitlines() if row.startswith("| pose |"))
    # |logged - true| 3.40 and 0.45 pp; |corrected - true| 0.21 and 0.45 pp
    assert line == "| pose | 1 | 20 % | 2 | 1/2 | 1.93 / 0.33 | 0 / 1 | 0.117 / 0.061 | 1 / 2 |"


def test_that_the_horizontal_and_the_height_questions_are_asked_one_at_a_time(tmp_path: Path, capsys):
    from tools.pose_oracle import main
    with pytest.raises(SystemExit):
        main(["--runs", str(tmp_path), "--height", "--horizontal"])
    assert "not allowed with" in capsys.readouterr().err


def test_that_a_kept_report_is_reused_only_when_the_code_that_made_it_is_the_code_now(tmp_path: Path, monkeypatch):
    """The oracle keeps the reports it makes; one made by other code (or by a version that did not say) is made
    again, so a table regenerated after a change is the change's. One made by this code is read as it is."""
    run = _run(tmp_path, "vio-1-20-0")
    made = []

    def report(cmd, **_kw):
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.json").write_text(json.dumps({"made": len(made)}))
        made.append(out)
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(pose_oracle.subprocess, "run", report)
    assert pose_oracle.reported(run, "--true-pose", pose_oracle.ALL, []) == {"made": 0}
    assert pose_oracle.reported(run, "--true-pose", pose_oracle.ALL, []) == {"made": 0} and len(made) == 1
    (made[0] / source_digest.MADE_BY).write_text("another code\n")
    assert pose_oracle.reported(run, "--true-pose", pose_oracle.ALL, []) == {"made": 1}
    (made[0] / source_digest.MADE_BY).unlink()
    assert pose_oracle.reported(run, "--true-pose", pose_oracle.ALL, []) == {"made": 2} and len(made) == 3


def test_that_the_source_digest_changes_with_any_file_of_the_ground_station(tmp_path: Path, monkeypatch):
    for package in source_digest.PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "a.py").write_text("x = 1\n")
    monkeypatch.setattr(source_digest, "ROOT", tmp_path)
    source_digest.source_digest.cache_clear()
    first = source_digest.source_digest()
    source_digest.source_digest.cache_clear()
    (tmp_path / "ground" / "a.py").write_text("x = 2\n")
    assert source_digest.source_digest() != first
    source_digest.source_digest.cache_clear()
