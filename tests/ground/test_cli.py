"""pilescan-ground: every bad input is one line, its kind's exit code (`ExitCode`), no traceback; --force, -v/-q,
exit 5 when there is no volume to give."""

import json

import pytest

from firmware_py.core.cli import ExitCode
from firmware_py.core.storage import Storage
from firmware_py.core.version import __version__, software_version
from ground.cli import format_summary, main
from ground.report import ReportOptions, make_report
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)


def test_that_version_prints_the_software_version_and_exits_0(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out
    assert out.strip() == software_version() and __version__ in out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """Pile 1 in the small building at 2 m/s: the command's behaviour, not the survey's size, is what these tests
    read (a quarter of the paper's floor, flown in half the time: each of the many reports the cheaper)."""
    out = tmp_path_factory.mktemp("run")
    fly(FlyConfig(mission=Mission(storage=Storage(30, 20, 10), altitude_m=9.0, p_traj=0.2, speed_m_s=2.0)), out,
        force=True)
    return out


def _one_line_error(capsys, argv, match, expected=ExitCode.USAGE):
    code = main(argv)
    err = capsys.readouterr().err
    assert code == expected, err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert match in err
    return err


def test_that_the_report_command_prints_the_summary(run_dir, tmp_path, capsys):
    assert main(["report", str(run_dir), "--out", str(tmp_path / "r"), "--no-plots"]) == 0
    out = capsys.readouterr().out
    assert "Ve (eq. 8)" in out and "R_a (eq. 9)" in out


def test_that_the_summary_shows_volumes_in_the_chosen_unit_with_cubic_metres_beside(run_dir, tmp_path, capsys):
    assert main(["report", str(run_dir), "--out", str(tmp_path / "r"), "--no-plots", "--volume-units", "yd3"]) == 0
    rows = {line.split("  ")[0]: line for line in capsys.readouterr().out.splitlines()}
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert f"{rep['volume_m3'] / 0.9144**3:,.1f} yd³ ({rep['volume_m3']:,.1f} m³)" in rows["volume"]
    assert "yd³ (" in rows["90 % interval"] and " m³)" in rows["90 % interval"]
    columns = {len(line) - len(line[len(label):].lstrip()) for label, line in rows.items()
               if label in ("volume", "base", "R_a (eq. 9)", "Log SHA-256")}
    assert len(columns) == 1  # every value starts in one column
    # the part of R_a no point saw within the seen radius, said beside it when there is any
    assert (f"{rep['bridged_area_m2']:,.0f} m² of it with no point within 1 m" in rows["R_a (eq. 9)"]) \
        == (rep["bridged_area_m2"] >= 0.5)


def test_that_the_console_shows_a_warning_of_many_clauses_as_its_headline_with_the_rest_under_it():
    rep = {"volume_m3": 1.0, "n_points_used": 1, "n_samples": 1,
           "warnings": ["pose corrected: 0.14 m (0.20 max; over time); the floor 0.5 cm off; the heading 0.26 deg",
                        "a short one; with its reason"]}
    lines = format_summary(rep).splitlines()
    at = lines.index("WARNING: pose corrected: 0.14 m (0.20 max; over time)")
    assert lines[at + 1:at + 4] == ["  - the floor 0.5 cm off", "  - the heading 0.26 deg",
                                    "WARNING: a short one; with its reason"]


def test_that_the_surface_slopes_option_reaches_the_report(run_dir, tmp_path, capsys):
    assert main(["report", str(run_dir), "--out", str(tmp_path / "g"), "--no-plots", "--surface-slopes", "gp"]) == 0
    assert json.loads((tmp_path / "g" / "report.json").read_text())["surface_slopes"] == "gp"
    assert main(["report", str(run_dir), "--out", str(tmp_path / "d"), "--no-plots"]) == 0
    assert json.loads((tmp_path / "d" / "report.json").read_text())["surface_slopes"] == "gp-bridges"
    capsys.readouterr()
    _one_line_error(capsys, ["report", str(run_dir), "--out", str(tmp_path / "x"), "--surface-slopes", "spline"],
                    "--surface-slopes")
    for slopes in ("gp", "curvature"):  # given by name, even curvature: the other fits take no slopes at all
        _one_line_error(capsys, ["report", str(run_dir), "--out", str(tmp_path / "y"), "--surface-slopes", slopes,
                                 "--surface-fit", "linear"], "applies to the local-linear surface fit only")
    by_name = ReportOptions(plots=False, surface_slopes="gp")  # the library's options take the value's name too
    assert make_report(run_dir, tmp_path / "s", by_name)["surface_slopes"] == "gp"


def test_that_the_surface_limit_option_reaches_the_report_and_its_method(run_dir, tmp_path, capsys):
    assert main(["report", str(run_dir), "--out", str(tmp_path / "l"), "--no-plots", "--surface-limit", "linear"]) == 0
    assert json.loads((tmp_path / "l" / "report.json").read_text())["surface_limit"] == "linear"
    assert "planar through the triangle's corners" in (tmp_path / "l" / "report.md").read_text()
    assert main(["report", str(run_dir), "--out", str(tmp_path / "d"), "--no-plots"]) == 0
    assert json.loads((tmp_path / "d" / "report.json").read_text())["surface_limit"] == "clip"
    assert "planar through" not in (tmp_path / "d" / "report.md").read_text()
    capsys.readouterr()
    _one_line_error(capsys, ["report", str(run_dir), "--out", str(tmp_path / "x"), "--surface-limit", "spline"],
                    "--surface-limit")
    for fit in ("cubic", "linear"):  # nothing to limit: given even as the default, it is refused, as --surface-slopes
        _one_line_error(capsys, ["report", str(run_dir), "--out", str(tmp_path / "y"), "--surface-limit", "clip",
                                 "--surface-fit", fit], "applies to the limited cubic fits only")
    assert make_report(run_dir, tmp_path / "s", ReportOptions(plots=False, surface_limit="linear"))["surface_limit"] \
        == "linear"  # the library's options take the value's name too


def test_that_the_ground_options_reach_the_report(run_dir, tmp_path, capsys):
    assert main(["report", str(run_dir), "--out", str(tmp_path / "r"), "--no-plots", "--surface-fit", "linear",
                 "--no-despike", "--no-servo-retiming"]) == 0
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert rep["surface_fit"] == "linear" and rep["despike"] is False
    assert main(["report", str(run_dir), "--out", str(tmp_path / "d"), "--no-plots"]) == 0
    assert json.loads((tmp_path / "d" / "report.json").read_text())["surface_fit"] == "local-linear"
    capsys.readouterr()
    _one_line_error(capsys, ["report", str(run_dir), "--out", str(tmp_path / "x"), "--surface-fit", "spline"],
                    "--surface-fit")


def test_that_the_mount_given_reaches_the_report_in_the_units_it_reports_in(run_dir, tmp_path, capsys):
    """`--mount 1.5 -2 0 0.5`: degrees and percent on the command line, the same figures in report.json's
    self-calibration, marked given, and the console's line says so."""
    assert main(["report", str(run_dir), "--out", str(tmp_path / "r"), "--no-plots", "--mount", "1.5", "-2", "0",
                 "0.5"]) == 0
    cal = json.loads((tmp_path / "r" / "report.json").read_text())["self_calibration"]
    assert cal["given"] is True
    assert cal["servo_offset_deg"]["estimate"] == pytest.approx(1.5)
    assert cal["servo_scale"]["estimate"] == pytest.approx(-0.02)
    assert cal["sweep_yaw_deg"]["estimate"] == pytest.approx(0.5)
    assert [c["applied"] for c in (cal["servo_offset_deg"], cal["servo_scale"], cal["boresight_tilt_deg"],
                                   cal["sweep_yaw_deg"])] == [True, True, False, True]
    assert "the mount as given (--mount) applied" in capsys.readouterr().out


def test_that_bad_inputs_fail_cleanly(run_dir, tmp_path, capsys):
    out = str(tmp_path / "r")
    _one_line_error(capsys, ["report", str(tmp_path / "missing"), "--out", out], "no such run", ExitCode.INPUT)
    empty = tmp_path / "empty"
    empty.mkdir()
    _one_line_error(capsys, ["report", str(empty), "--out", out], "without a samples.pslog", ExitCode.INPUT)
    garbage = tmp_path / "garbage.pslog"
    garbage.write_bytes(b"\x00not a log" * 100)
    _one_line_error(capsys, ["report", str(garbage), "--out", out], "header is missing or corrupt", ExitCode.INPUT)
    _one_line_error(capsys, ["report", str(run_dir), "--out", out, "--truth-volume", "nan"], "finite")
    _one_line_error(capsys, ["report", str(run_dir), "--out", out, "--truth-volume", "-5"], "must be >= 0")
    _one_line_error(capsys, ["report", str(run_dir), "--out", out, "--cell", "0"], "cell size")
    _one_line_error(capsys, ["report", str(run_dir), "--out", out, "--empty-cells", "x"], "invalid choice")
    _one_line_error(capsys, ["report", str(run_dir)], "--out")


def test_that_a_bad_truth_file_is_reported(run_dir, tmp_path, capsys):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "samples.pslog").write_bytes((run_dir / "samples.pslog").read_bytes())
    (bad / "truth.json").write_text("{not json")
    _one_line_error(capsys, ["report", str(bad), "--out", str(tmp_path / "r")], "not valid JSON", ExitCode.INPUT)
    (bad / "truth.json").write_text(json.dumps({"true_volume_m3": "lots"}))
    _one_line_error(capsys, ["report", str(bad), "--out", str(tmp_path / "r")], "must be a finite number",
                    ExitCode.INPUT)
    assert not (tmp_path / "r").exists()  # inputs are read before the output is touched


# ----- exit 5: no volume -----------------------------------------------------------------------------

def _log_file(path, samples) -> str:
    from firmware_py.core.samplelog import encode_block
    from tests.ground.test_report_fuzz import BASE_HEADER
    path.write_bytes(encode_block(b"H", json.dumps(BASE_HEADER).encode()) + encode_block(b"S", samples.tobytes()))
    return str(path)


def test_that_a_log_without_a_usable_sample_exits_5_and_writes_no_report(tmp_path, capsys):
    from firmware_py.core.samplelog import SampleFlags
    from tests.ground.test_report_fuzz import floor_samples
    s = floor_samples()
    s["flags"] = SampleFlags.NO_RETURN  # the LiDAR saw nothing: there is no volume to give, not "0.0 m^3"
    log = _log_file(tmp_path / "blind.pslog", s)
    code = main(["report", log, "--out", str(tmp_path / "r")])
    cap = capsys.readouterr()
    assert code == ExitCode.NO_VOLUME == 5
    assert cap.out == "" and cap.err.count("\n") == 1
    assert "no volume" in cap.err and "400 samples: 400 unusable" in cap.err
    assert not (tmp_path / "r").exists()


def test_that_a_log_with_usable_samples_exits_0(tmp_path, capsys):
    from tests.ground.test_report_fuzz import floor_samples
    log = _log_file(tmp_path / "floor.pslog", floor_samples())
    assert main(["report", log, "--out", str(tmp_path / "r"), "--no-plots"]) == 0
    assert "volume" in capsys.readouterr().out


# ----- --force, atomic reports --------------------------------------------------------------------------

def test_that_report_refuses_to_overwrite_a_report_without_force(run_dir, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["report", str(run_dir), "--out", str(out), "--no-plots", "-q"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    _one_line_error(capsys, ["report", str(run_dir), "--out", str(out), "--no-plots"], "--force")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_that_report_force_replaces_every_old_file(run_dir, tmp_path, capsys):
    out = tmp_path / "r"
    assert main(["report", str(run_dir), "--out", str(out), "-q"]) == 0  # with plots
    assert (out / "coverage.png").is_file()
    coarse = "coarser than the 0.5 m up to which the grid's own error was measured small"
    assert not any(coarse in w for w in json.loads((out / "report.json").read_text())["warnings"])
    assert main(["report", str(run_dir), "--out", str(out), "--no-plots", "--cell", "1.0", "-q", "--force"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["cloud.ply", "piles.csv", "report.html", "report.json",
                                                     "report.md", "report.pdf", "surface.npz"]
    rep = json.loads((out / "report.json").read_text())
    assert rep["cell_size_m"] == 1.0  # no old figure beside it
    assert any(coarse in w for w in rep["warnings"])  # its interval leaves the grid's error out


def test_that_a_report_failing_half_way_leaves_no_new_file_beside_old_ones(run_dir, tmp_path, capsys, monkeypatch):
    import ground.render
    out = tmp_path / "r"
    out.mkdir()
    (out / "notes.txt").write_text("the user's own file")

    def disk_full(*_a, **_k):
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(ground.render, "write_html", disk_full)  # after the cloud, figures, json and markdown
    code = main(["report", str(run_dir), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == ExitCode.RUNTIME and "No space left on device" in err and err.count("\n") == 1
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    code = main(["report", str(run_dir), "--out", str(tmp_path / "fresh"), "--no-plots"])
    assert code == ExitCode.RUNTIME and not (tmp_path / "fresh").exists()


# ----- -v / -q ------------------------------------------------------------------------------------------

def test_that_quiet_prints_nothing_and_the_default_prints_the_summary_and_where(run_dir, tmp_path, capsys):
    assert main(["report", str(run_dir), "--out", str(tmp_path / "a"), "--no-plots", "-q"]) == 0
    assert capsys.readouterr() == ("", "")
    assert main(["report", str(run_dir), "--out", str(tmp_path / "b"), "--no-plots"]) == 0
    cap = capsys.readouterr()
    assert cap.out.startswith("volume ") and cap.err.startswith(f"pilescan-ground: report written to {tmp_path / 'b'}")
    assert main(["-q", "report", str(run_dir), "--out", str(tmp_path / "c"), "--no-plots"]) == 0
    assert capsys.readouterr() == ("", "")


def test_that_the_ground_command_starts_without_scipy_stats_or_signal():
    """scipy.stats (which scipy.signal imports) added a quarter of a second to the command's start-up for two
    functions scipy.special holds; every `pilescan-ground` call paid it."""
    import subprocess
    import sys
    code = "import sys, ground.cli; print(sorted(m for m in ('scipy.stats', 'scipy.signal') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
