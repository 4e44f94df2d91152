"""The report refuses files it cannot trust and leaves out records no payload could have written."""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path

import numpy as np
import pytest

from firmware_py.core.cli import UserError
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD, encode_block, read_samplelog
from firmware_py.core.storage import Storage
from ground.cli import main
from ground.plausibility import MAX_GAP_S, in_time, out_of_time
from ground.report import ReportOptions, check_grid_memory, make_report

GOLDEN = Path(__file__).resolve().parents[1] / "golden"


@pytest.fixture(scope="module")
def golden():
    log = read_samplelog(GOLDEN / "samples.pslog")
    return log.header, log.samples


def write_log(path: Path, header: dict, samples: np.ndarray) -> Path:
    path.write_bytes(encode_block(b"H", json.dumps(header).encode()) + encode_block(b"S", samples.tobytes()))
    return path


def one_line_error(capsys, argv: list[str]) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code != 0 and "\n" not in err and "Traceback" not in err, err
    return err


def report(src: Path, tmp_path: Path, **opts) -> dict:
    return make_report(src, tmp_path / "out", ReportOptions(plots=False, **opts), force=True)  # tests report twice


def test_that_a_version_99_log_is_refused_not_read_as_version_1(golden, tmp_path, capsys):
    h, s = golden
    log = write_log(tmp_path / "v99.pslog", {**h, "format_version": 99}, s)
    err = one_line_error(capsys, ["report", str(log), "--out", str(tmp_path / "o"), "--no-plots"])
    assert "version 99" in err and "supports version 1" in err


def test_that_report_refuses_dev_zero_at_once(tmp_path, capsys):
    err = one_line_error(capsys, ["report", "/dev/zero", "--out", str(tmp_path / "o")])
    assert "character device, not a regular file" in err


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_that_report_refuses_a_fifo_instead_of_hanging(tmp_path, capsys):
    os.mkfifo(tmp_path / "pipe")
    err = one_line_error(capsys, ["report", str(tmp_path / "pipe"), "--out", str(tmp_path / "o")])
    assert "FIFO" in err


def test_that_a_sparse_multi_gigabyte_log_is_refused_by_its_size(tmp_path, capsys):
    big = tmp_path / "big.pslog"
    with open(big, "wb") as f:
        f.truncate(5 * 1024**3)
    err = one_line_error(capsys, ["report", str(big), "--out", str(tmp_path / "o")])
    assert "byte limit" in err


@pytest.mark.parametrize("truth, why", [
    ("[" * 100_000 + "]" * 100_000, "deeper than"),
    ('{"true_volume_m3": true}', "must be a finite number, got a boolean"),
    ('{"true_volume_m3": -3}', "must be >= 0"),
    ('{"true_volume_m3": NaN}', "not valid JSON"),
    ("[1]", "must be a JSON object"),
])
def test_that_a_hostile_truth_file_gives_one_line(golden, tmp_path, capsys, truth, why):
    run = tmp_path / "run"
    run.mkdir()
    write_log(run / "samples.pslog", *golden)
    (run / "truth.json").write_text(truth)
    assert why in one_line_error(capsys, ["report", str(run), "--out", str(tmp_path / "o"), "--no-plots"])


def test_that_storage_dimensions_given_as_booleans_are_not_a_1m_building(golden, tmp_path, capsys):
    h, s = golden
    log = write_log(tmp_path / "b.pslog", {**h, "storage": {"length_m": True, "width_m": True, "height_m": True}}, s)
    err = one_line_error(capsys, ["report", str(log), "--out", str(tmp_path / "o"), "--no-plots"])
    assert "storage length_m must be a number, got True" in err


def test_that_a_lever_arm_of_booleans_is_refused(golden, tmp_path):
    h, s = golden
    log = write_log(tmp_path / "b.pslog", {**h, "lever_arm_body_m": [True, False, True]}, s)
    with pytest.raises(UserError, match="lever_arm_body_m must be a list of numbers"):
        report(log, tmp_path)


def usable(s: np.ndarray) -> np.ndarray:
    return ((s["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0) & (s["range_m"] > 0)


def test_that_a_clean_log_has_no_implausible_records(golden, tmp_path):
    rep = report(write_log(tmp_path / "c.pslog", *golden), tmp_path)
    assert rep["n_samples_implausible"] == 0 and rep["implausible"] == {"servo_angle": 0, "range": 0, "pose": 0,
                                                                                "time": 0}


def test_that_a_record_or_two_out_of_time_are_left_out_and_a_clock_fault_keeps_the_longest_stretch():
    t = 1000.0 + np.arange(1000) / 500.0
    assert not out_of_time(t).any()
    odd = t.copy()
    odd[[10, 20, 21]] = np.nan, 1e300, 0.0  # not finite; two neighbours far from the rest
    odd[5] = odd[4]  # the same time twice is not a fault
    assert np.flatnonzero(out_of_time(odd)).tolist() == [10, 20, 21]
    for at, by in ((600, 1e7), (600, 86400.0), (700, -30.0)):  # forward a long way, or back at all
        jump = t.copy()
        jump[at:] += by
        later = np.arange(1000) >= at
        assert np.array_equal(out_of_time(jump), later if at > 500 else ~later)
    pause = t.copy()
    pause[500:] += MAX_GAP_S - 1.0  # a long wait on the ground, still one flight
    assert not out_of_time(pause).any()
    assert len(in_time(odd)) == 997 and in_time(np.array([np.nan])).size == 0


def test_that_a_clock_stepped_by_a_day_reports_the_longest_stretch_with_a_warning(golden, tmp_path):
    """It asked for a 25 GiB matrix before, and a NaN time stopped the report with "arange: cannot compute
    length"."""
    h, s = golden
    bad = s.copy()
    half = len(s) // 3
    bad["t_s"][half:] += 86400.0
    bad["t_s"][10] = np.nan
    rep = report(write_log(tmp_path / "b.pslog", h, bad), tmp_path)
    assert rep["implausible"]["time"] == half
    assert any("times do not fit the log's clock" in w for w in rep["warnings"])
    kept = s["t_s"][half:]
    assert rep["metadata"]["survey_duration_s"] == pytest.approx(kept.max() - kept.min())


def test_that_samples_of_one_instant_get_a_report_and_no_pose_correction(golden, tmp_path):
    h, s = golden
    still = s.copy()
    still["t_s"] = s["t_s"][0]  # a division by zero in the pose correction before
    rep = report(write_log(tmp_path / "b.pslog", h, still), tmp_path)
    assert rep["volume_m3"] > 0 and "does not move" in rep["pose_correction"]["reason"]


def test_that_a_header_sweep_faster_than_a_servo_and_a_mission_id_with_an_escape_still_report(golden, tmp_path):
    h, s = golden
    fast = copy.deepcopy(h)
    fast["servo"]["frequency_hz"] = 1e9  # its period made the pose correction ask for 158 GiB of knots
    fast["mission_id"] = "bay 3\x1b[2J"
    rep = report(write_log(tmp_path / "f.pslog", fast, s), tmp_path)
    assert rep["volume_m3"] > 0 and rep["mission_id"] is None  # an escape never reaches the console or the PDF


def test_that_a_report_into_its_inputs_own_folder_is_refused(golden, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    write_log(run / "samples.pslog", *golden)
    for src in (run, run / "samples.pslog"):
        err = one_line_error(capsys, ["report", str(src), "--out", str(run), "--no-plots", "--force"])
        assert "is the folder of the input" in err
    assert sorted(p.name for p in run.iterdir()) == ["samples.pslog"]


@pytest.mark.parametrize("option", ["--operator", "--site-name", "--aircraft"])
def test_that_a_terminal_escape_or_a_line_break_in_the_surveys_names_is_refused(golden, tmp_path, capsys, option):
    log = write_log(tmp_path / "c.pslog", *golden)
    for bad in ("bob\x1b[31m", "bob\nalice"):
        err = one_line_error(capsys, ["report", str(log), "--out", str(tmp_path / "o"), option, bad])
        assert "printable text on one line" in err


def test_that_servo_angles_of_1e20_rad_are_left_out_counted_and_warned(golden, tmp_path):
    h, s = golden
    clean = report(write_log(tmp_path / "c.pslog", h, s), tmp_path)
    bad = s.copy()
    hit = np.zeros(len(s), bool)
    hit[::3] = True
    bad["servo_rad"][hit] = 1e20
    rep = report(write_log(tmp_path / "b.pslog", h, bad), tmp_path)
    assert rep["implausible"]["servo_angle"] == int((hit & usable(s)).sum()) > 0
    assert any("implausible" in w for w in rep["warnings"])
    # the rest still measures the pile: within a few percent of the clean log, not 13,653 m^3
    assert abs(rep["volume_m3"] - clean["volume_m3"]) / clean["volume_m3"] < 0.05


def test_that_ranges_beyond_the_sensors_reach_and_poses_outside_the_building_are_left_out(golden, tmp_path):
    h, s = golden
    bad = s.copy()
    far, away = np.zeros(len(s), bool), np.zeros(len(s), bool)
    far[1::5] = True
    away[2::5] = True
    bad["range_m"][far] = h["sensor"]["max_range_m"] * 4
    bad["x_m"][away] += 1000.0
    rep = report(write_log(tmp_path / "b.pslog", h, bad), tmp_path)
    assert rep["implausible"]["range"] == int((far & usable(s)).sum()) > 0
    assert rep["implausible"]["pose"] == int((away & usable(s)).sum()) > 0
    assert rep["n_samples_implausible"] == rep["implausible"]["range"] + rep["implausible"]["pose"]


def test_that_a_range_at_the_sensors_max_range_is_plausible(golden, tmp_path):
    h, s = golden
    edge = s.copy()
    at_max = np.flatnonzero(usable(s))[::50]  # a few: the rest still make a surface (else no volume, exit 5)
    edge["range_m"][at_max] = h["sensor"]["max_range_m"]
    rep = report(write_log(tmp_path / "e.pslog", h, edge), tmp_path)
    assert rep["implausible"]["range"] == 0


def test_that_despiking_without_the_waveform_says_it_did_not_run(golden, tmp_path):
    h, s = golden
    h2 = copy.deepcopy(h)
    del h2["servo"]["frequency_hz"]
    rep = report(write_log(tmp_path / "n.pslog", h2, s), tmp_path)
    assert rep["despike"] is False and "servo.frequency_hz" in rep["despike_unavailable"]
    assert any(w.startswith("despiking did not run") for w in rep["warnings"])
    on = report(write_log(tmp_path / "c.pslog", h, s), tmp_path)
    assert on["despike"] is True and on["despike_unavailable"] is None


def test_that_a_grid_too_fine_for_the_memory_bound_is_refused_naming_a_cell_that_fits(golden, tmp_path, capsys):
    log = write_log(tmp_path / "c.pslog", *golden)
    err = one_line_error(capsys, ["report", str(log), "--out", str(tmp_path / "o"), "--cell", "0.01"])
    assert "24,000,000 cells" in err and "--cell 0.015 or more" in err
    with pytest.raises(UserError, match=r"--cell 0\.\d+ or more") as info:
        report(log, tmp_path, cell_m=0.25, max_grid_memory_bytes=2_000_000)
    suggested = float(str(info.value).split("--cell ")[1].split()[0])
    check_grid_memory(Storage(), suggested, 2_000_000)  # the size it names does fit


def test_that_a_bin_grid_beyond_the_memory_bound_is_refused_before_allocating():
    from ground.binning import HeightBinner
    from ground.pointcloud import SensorErrorModel
    with pytest.raises(ValueError, match="more than the 1 MiB allowed"):
        HeightBinner(Storage(), SensorErrorModel(), bin_m=0.05, max_memory_bytes=2**20)


def test_that_a_json_true_is_not_a_sample_rate_for_despiking(golden):
    from ground.despike import SpikeThreshold, why_no_threshold
    h = copy.deepcopy(golden[0])
    h["sensor"]["rate_hz"] = True
    assert SpikeThreshold.from_header(h) is None and "sensor.rate_hz" in why_no_threshold(h)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
@pytest.mark.parametrize("name", ["truth.json", "samples.pslog"])
def test_that_a_fifo_in_a_run_directory_is_refused_not_skipped_or_waited_on(golden, tmp_path, capsys, name):
    run = tmp_path / "run"
    run.mkdir()
    os.mkfifo(run / name)
    if name != "samples.pslog":
        write_log(run / "samples.pslog", *golden)
    err = one_line_error(capsys, ["report", str(run), "--out", str(tmp_path / "o"), "--no-plots"])
    assert "FIFO" in err and name in err


def test_that_a_directory_named_truth_json_is_refused(golden, tmp_path, capsys):
    run = tmp_path / "run"
    (run / "truth.json").mkdir(parents=True)
    write_log(run / "samples.pslog", *golden)
    err = one_line_error(capsys, ["report", str(run), "--out", str(tmp_path / "o"), "--no-plots"])
    assert "truth.json is a directory" in err
