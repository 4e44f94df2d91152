"""The pose factor of the volume interval, fitted on drifting flights (tools/calibrate_pose_interval.py)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest

from ground.uncertainty import ErrorTerms, IntervalModel
from tools.calibrate_pose_interval import fit, flights, inside, needed_k, write_model

MODEL = IntervalModel(k_unseen=1.0, k_interpolation=1.0, k_noise=1.0, k_sweeps=1.0, k_faces=1.0, k_blur=1.0)


def row(err_m3: float, noise_m3: float, pose_m3: float, profile: str = "vio") -> dict:
    return {"set": "s", "run": "r", "profile": profile, "p_traj": 5, "volume_m3": 1000.0 + err_m3,
            "true_volume_m3": 1000.0, "terms": ErrorTerms(noise_m3=noise_m3, pose_m3=pose_m3)}


def test_that_a_flight_needs_the_pose_factor_that_just_reaches_its_truth():
    assert needed_k(row(5.0, 10.0, 1.0), MODEL) == 0.0  # inside without the term
    k = needed_k(row(50.0, 30.0, 10.0), MODEL)  # sqrt(50^2 - 30^2) / 10 = 4
    assert k == pytest.approx(4.0)
    assert inside(row(50.0, 30.0, 10.0), replace(MODEL, k_pose=k))
    assert not inside(row(50.0, 30.0, 10.0), replace(MODEL, k_pose=0.99 * k))
    assert math.isinf(needed_k(row(50.0, 30.0, 0.0), MODEL))  # no height corrected: no factor helps


def test_that_the_factor_is_the_90th_percentile_of_what_the_drifting_flights_need():
    rows = [row(10.0 * (i + 1), 0.0, 1.0) for i in range(10)] + [row(500.0, 0.0, 0.0, profile="none")]
    assert fit(rows, MODEL) == pytest.approx(90.0)  # the 9th of 10 (the error-free flight is not fitted)
    with pytest.raises(SystemExit, match="no factor helps"):
        fit([row(50.0, 0.0, 0.0)] * 10, MODEL)


def test_that_the_kept_reports_are_read_with_their_p_traj_and_profile(tmp_path: Path):
    run = tmp_path / "flow-2-20-1-appendix-a"
    run.mkdir()
    storage = {"length_m": 60.0, "width_m": 40.0, "height_m": 15.0}
    (run / "truth.json").write_text(json.dumps({"mission": {"p_traj": 0.2}, "storage": storage}))
    rep = tmp_path / "flow-2-20-1-appendix-a--pose-correction"
    rep.mkdir()
    (rep / "report.json").write_text(json.dumps({"volume_m3": 10.0, "true_volume_m3": 11.0,
                                                 "interval_terms_m3": {"noise_m3": 1.0, "pose_m3": 0.5}}))
    (tmp_path / "orphan--pose-correction").mkdir()  # a report whose flight is gone is left out
    (tmp_path / "orphan--pose-correction" / "report.json").write_text(rep.joinpath("report.json").read_text())
    crashed = tmp_path / "vio-2-20-1-appendix-a"  # its true path went through the roof: no survey, as in the campaign
    crashed.mkdir()
    (crashed / "truth.json").write_text(json.dumps({"mission": {"p_traj": 0.2}, "storage": storage, "pose_error": {
        "trajectory": {"t_s": [0.0, 1.0], "true_w_m": [[30.0, 20.0, 12.0], [30.0, 20.0, 16.0]]}}}))
    (tmp_path / "vio-2-20-1-appendix-a--pose-correction").mkdir()
    (tmp_path / "vio-2-20-1-appendix-a--pose-correction" / "report.json").write_text(
        rep.joinpath("report.json").read_text())
    (r,) = flights(tmp_path, "noisy")
    assert (r["profile"], r["p_traj"], r["set"]) == ("flow", 20, "noisy")
    assert r["terms"].pose_m3 == 0.5


def test_that_the_fitted_factor_replaces_only_its_own_block(tmp_path: Path):
    from tools.calibrate_pose_interval import MODEL_BEGIN, MODEL_END
    f = tmp_path / "u.py"
    f.write_text(f"A = 1\n{MODEL_BEGIN}\nPOSE_FACTOR = 1.0\nPOSE_FACTOR_SOURCE = 'x'\n{MODEL_END}\nB = 2\n")
    k = fit([row(10.0 * (i + 1) + 0.1234567, 0.0, 1.0) for i in range(10)], MODEL)
    write_model(k, "fitted here", f)
    text = f.read_text()
    assert f"POSE_FACTOR = {k!r}\n" in text and "'fitted here'" in text and text.startswith("A = 1\n")
    written = float(text.split("POSE_FACTOR = ")[1].splitlines()[0])
    assert written == k  # every digit: the flight that set it stays inside (a rounded 8.74963 had put one out)
    assert text.endswith("B = 2\n")
    f.write_text("nothing to replace\n")
    with pytest.raises(SystemExit):
        write_model(1.0, "x", f)
