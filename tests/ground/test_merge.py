"""Several flights of one survey merged into one report (`pilescan-ground report RUN1 RUN2 --out DIR`)."""

import hashlib
import json
import shutil

import numpy as np
import pytest
import trimesh

from firmware_py.core.samplelog import HEAD_SIZE, end_payload, read_samplelog
from firmware_py.core.storage import Storage
from ground.cli import main
from ground.report import ReportOptions, make_report
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly

SMALL = Storage(30, 20, 10)


def _fly(tmp_path, name: str, p_traj: float, phase: int = 0, storage: Storage = SMALL):
    """At 2 m/s: what a merge does with the logs, not their sampling density, is what these tests read."""
    out = tmp_path / name
    fly(FlyConfig(mission=Mission(storage=storage, altitude_m=9.0, p_traj=p_traj, speed_m_s=2.0), plant="ideal",
                  payload="batch", initial_position=phase), out, progress=lambda _m: None)
    return out


@pytest.fixture(scope="module")
def two_flights(tmp_path_factory):
    d = tmp_path_factory.mktemp("merge")
    return _fly(d, "wide", 0.35), _fly(d, "near", 0.1, phase=7)


@pytest.fixture(scope="module")
def reports(two_flights, tmp_path_factory):
    """Each flight's report alone and the two merged, with the default options, made once for the tests that only
    read them: {"a" | "b" | "m": (report directory, report)}."""
    a, b = two_flights
    d = tmp_path_factory.mktemp("merge-reports")
    return {name: (d / name, make_report(src, d / name, ReportOptions(plots=False)))
            for name, src in (("a", a), ("b", b), ("m", [a, b]))}


def _points(report_dir) -> np.ndarray:
    p = np.asarray(trimesh.load(report_dir / "cloud.ply").vertices, dtype=float)
    return p[np.lexsort(p.T[::-1])]


def test_that_merging_two_logs_gives_the_union_of_their_clouds(reports):
    (da, ra), (db, rb), (dm, rm) = reports["a"], reports["b"], reports["m"]
    assert rm["n_samples"] == ra["n_samples"] + rb["n_samples"]
    assert rm["n_samples_excluded"] == ra["n_samples_excluded"] + rb["n_samples_excluded"]
    def placed(r: dict) -> int:  # every usable sample's point, on the pile or on the building
        return r["n_points_used"] + r["n_points_removed_walls"]
    assert placed(rm) == placed(ra) + placed(rb)
    union = np.vstack([_points(da), _points(db)])
    assert np.array_equal(_points(dm), union[np.lexsort(union.T[::-1])])


def test_that_the_merged_report_sees_more_than_either_flight_and_names_both_logs(two_flights, reports):
    a, b = two_flights
    (_, alone), (dm, rm) = reports["a"], reports["m"]
    assert rm["coverage_ratio_pct"] > alone["coverage_ratio_pct"]
    assert rm["true_volume_m3"] == alone["true_volume_m3"]
    assert [f["log_sha256"] for f in rm["flights"]] == [
        hashlib.sha256((d / "samples.pslog").read_bytes()).hexdigest() for d in (a, b)]
    assert rm["flights"][0]["coverage_ratio_pct_alone"] == pytest.approx(alone["coverage_ratio_pct"])
    assert all(f["duration_s"] > 0 for f in rm["flights"])
    assert rm["metadata"]["flights_merged"] == 2
    assert rm["metadata"]["survey_duration_s"] == pytest.approx(sum(f["duration_s"] for f in rm["flights"]))
    assert alone["flights"] is None and "flights_merged" not in alone["metadata"]
    md = (dm / "report.md").read_text()
    assert f"| Flights merged | 2: {a / 'samples.pslog'} (" in md and f"; {b / 'samples.pslog'} (" in md


def _refused(argv, capsys, code: int = 2) -> str:
    assert main(argv) == code
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


def test_that_logs_of_different_buildings_are_refused_in_one_line(two_flights, tmp_path, capsys):
    other = _fly(tmp_path, "other", 0.2, storage=Storage(32, 20, 10))
    err = _refused(["report", str(two_flights[0]), str(other), "--out", str(tmp_path / "m"), "--no-plots"], capsys)
    assert "cannot merge" in err and "different buildings" in err
    assert not (tmp_path / "m" / "report.json").exists()


def test_that_runs_whose_true_volumes_differ_are_refused(two_flights, tmp_path, capsys):
    a, b = two_flights
    c = tmp_path / "c"
    c.mkdir()
    (c / "samples.pslog").write_bytes((b / "samples.pslog").read_bytes())
    truth = json.loads((b / "truth.json").read_text())
    truth["true_volume_m3"] *= 1.01
    (c / "truth.json").write_text(json.dumps(truth))
    err = _refused(["report", str(a), str(c), "--out", str(tmp_path / "m"), "--no-plots"], capsys)
    assert "true volumes differ" in err


def test_that_one_log_given_twice_is_refused(two_flights, tmp_path, capsys):
    a, _ = two_flights
    err = _refused(["report", str(a), str(a / "samples.pslog"), "--out", str(tmp_path / "m"), "--no-plots"], capsys)
    assert "are the same log" in err


def test_that_a_missing_second_run_is_refused_before_anything_is_written(two_flights, tmp_path, capsys):
    # exit 3: an input that cannot be read (firmware_py.core.cli.reading_input), as for one run
    err = _refused(["report", str(two_flights[0]), str(tmp_path / "nowhere"), "--out", str(tmp_path / "m")], capsys,
                   code=3)
    assert "nowhere" in err and not (tmp_path / "m").exists()


def test_that_the_reports_surface_file_marks_the_cells_it_fitted(reports):
    from ground.surface_file import load_surface
    da, rep = reports["a"]
    saved = load_surface(da / "surface.npz")
    assert saved.fitted is not None and saved.fitted.shape == saved.heights_m.shape
    assert 100.0 * saved.fitted.mean() == pytest.approx(rep["coverage_ratio_pct"])
    assert 0 < saved.fitted.sum() < saved.fitted.size  # the wide loop left floor unseen: filled, not fitted


def test_that_a_merged_survey_carries_the_least_certain_corrected_height_of_its_flights():
    from ground.pose_correction import PoseCorrection
    from ground.report import least_certain_height

    def pose(sigma, applied=True):
        return PoseCorrection(np.zeros(2), np.zeros((2, 4)), np.zeros((2, 4), dtype=bool), applied,
                              height_sigma_m=sigma)
    a, b = pose(0.01), pose(0.03)
    assert least_certain_height([a, None, b, pose(0.05, applied=False)]) is b
    assert least_certain_height([pose(None), None]) is None  # no height corrected: no pose term


def test_that_a_merged_survey_carries_the_least_certain_level_that_rests_on_the_logged_reference():
    from ground.pose_correction import PoseCorrection
    from ground.report import least_certain_level, logged_level_sigma_m

    def pose(level, shift=None, applied=True):
        return PoseCorrection(np.zeros(2), np.zeros((2, 4)), np.zeros((2, 4), dtype=bool), applied,
                              level_sigma_m=level, open_floor_shift_m=shift)
    a, b, open_floor = pose(0.1), pose(0.2), pose(0.4, shift=-0.3)
    assert least_certain_level([a, None, b, open_floor, pose(0.5, applied=False)]) is b
    assert logged_level_sigma_m(open_floor) is None  # anchored on a floor in the open: its own warning instead
    assert least_certain_level([pose(None), None]) is None  # every level on a confirmed floor: no level term


def test_that_untied_stretches_count_only_where_the_level_rests_on_a_floor_and_a_merge_takes_the_least_certain():
    # A level on the logged reference spans the whole flight (the level term), so its untied stretches add nothing.
    from ground.pose_correction import PoseCorrection
    from ground.report import least_certain_untied, untied_stretches_sigma_m

    def pose(untied, level=None, shift=None, applied=True):
        return PoseCorrection(np.zeros(2), np.zeros((2, 4)), np.zeros((2, 4), dtype=bool), applied,
                              untied_sigma_m=untied, level_sigma_m=level, open_floor_shift_m=shift)
    on_floor, on_reference, open_floor = pose(0.05), pose(0.09, level=0.2), pose(0.07, level=0.2, shift=-0.3)
    assert untied_stretches_sigma_m(on_floor) == 0.05
    assert untied_stretches_sigma_m(on_reference) is None
    assert untied_stretches_sigma_m(open_floor) == 0.07  # anchored on an open floor: the level rests on it
    assert untied_stretches_sigma_m(pose(0.0)) is None and untied_stretches_sigma_m(pose(0.05, applied=False)) is None
    assert least_certain_untied([on_floor, None, on_reference, open_floor, pose(0.5, applied=False)]) is open_floor
    assert least_certain_untied([pose(0.0), None]) is None


def test_that_a_report_s_interval_carries_the_untied_stretches_and_a_merge_the_least_certain_flight_s(
        two_flights, tmp_path, monkeypatch):
    from ground import report
    from ground.pose_correction import PoseCorrection
    sigmas = iter(())

    def corrected(samples, *_a, **_k):
        t = samples["t_s"]
        untied, level = next(sigmas)
        return PoseCorrection(np.array([t.min(), t.max()]), np.zeros((2, 4)), np.zeros((2, 4), dtype=bool), True,
                              untied_sigma_m=untied, level_sigma_m=level)
    monkeypatch.setattr(report, "estimate_pose_correction", corrected)

    def terms(flights, *pairs):
        nonlocal sigmas
        sigmas = iter(pairs)
        r = make_report(flights, tmp_path / f"r{len(pairs)}-{pairs[0][0]}-{pairs[0][1]}", ReportOptions(plots=False))
        return r["interval_terms_m3"], r["volume_interval_m3"]
    a, b = two_flights
    one, wide = terms(a, (0.1, None))
    assert one["untied_m3"] > 0 and one["level_m3"] == 0
    assert terms(a, (0.2, None))[0]["untied_m3"] == pytest.approx(2 * one["untied_m3"])  # the sigma times the area
    none, narrow = terms(a, (0.0, None))
    assert none["untied_m3"] == 0 and narrow[1] - narrow[0] < wide[1] - wide[0]
    on_reference = terms(a, (0.1, 0.3))[0]  # the level term spans the flight: no untied term beside it
    assert on_reference["untied_m3"] == 0 and on_reference["level_m3"] > 0
    merged = terms([a, b], (0.05, None), (0.1, None))[0]["untied_m3"]
    assert merged == pytest.approx(terms([a, b], (0.1, None), (0.1, None))[0]["untied_m3"])  # the largest flight's


def test_that_a_merged_report_warns_of_each_flight_s_height_anchored_on_a_floor_in_the_open(two_flights, tmp_path,
                                                                                           monkeypatch):
    # A merged survey has no pose of its own: each flight's anchor on a floor seen only away from the walls (which may
    # be a hollow in the pile) is said with that flight's name, as its other warnings are.
    from ground import report
    from ground.pose_correction import PoseCorrection

    def anchored(samples, *_a, **_k):
        t = samples["t_s"]
        return PoseCorrection(np.array([t.min(), t.max()]), np.zeros((2, 4)), np.zeros((2, 4), dtype=bool), True,
                              open_floor_shift_m=-0.5, level_sigma_m=0.2)
    monkeypatch.setattr(report, "estimate_pose_correction", anchored)
    rm = make_report(list(two_flights), tmp_path / "m", ReportOptions(plots=False))
    said = [w for w in rm["warnings"] if "anchored on a floor seen only away from the walls" in w]
    assert [w.split(" (")[0] for w in said] == ["flight 1", "flight 2"], rm["warnings"]
    assert all("-0.50 m" in w for w in said)


def test_that_a_merge_with_one_log_cut_short_warns_of_that_flight_once_and_is_not_closed(two_flights, reports,
                                                                                          tmp_path):
    """The near flight's log without its end block (as a power cut after its last whole block leaves it)."""
    a, b = two_flights
    cut = tmp_path / "near-cut"
    shutil.copytree(b, cut)
    log = cut / "samples.pslog"
    data = log.read_bytes()
    n = len(read_samplelog(data).samples)
    log.write_bytes(data[:len(data) - HEAD_SIZE - len(end_payload(n))])
    assert read_samplelog(log).closed_cleanly is False and read_samplelog(log).intact
    rm = reports["m"][1]
    assert rm["log"]["closed_cleanly"] is True and not any("not closed" in w for w in rm["warnings"])
    merged = make_report([a, cut], tmp_path / "m", ReportOptions(plots=False))
    assert merged["log"]["closed_cleanly"] is False
    assert sum("the sample log was not closed" in w for w in merged["warnings"]) == 1
