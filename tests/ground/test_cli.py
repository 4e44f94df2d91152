"""pilescan-ground: every bad input is one line, its kind's exit code (`ExitCode`), no traceback; --force, -v/-q,
exit 5 when there is no volume to give."""

import json

import pytest

from firmware_py.core.cli import ExitCode
from firmware_py.core.version import __version__, software_version
from ground.cli import main
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly


def test_that_version_prints_the_software_version_and_exits_0(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out
    assert out.strip() == software_version() and __version__ in out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    fly(FlyConfig(mission=Mission(p_traj=0.2)), out, force=True)
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


def test_that_the_ground_options_reach_the_report(run_dir, tmp_path, capsys):
    assert main(["report", str(run_dir), "--out", str(tmp_path / "r"), "--no-plots", "--surface-fit", "linear",
                 "--no-despike", "--no-servo-retiming"]) == 0
    rep = json.loads((tmp_path / "r" / "report.json").read_text())
    assert rep["surface_fit"] == "linear" and rep["despike"] is False
    assert main(["report", str(run_dir), "--out", str(tmp_path / "d"), "--no-plots"]) == 0
    assert json.loads((tmp_path / "d" / "report.json").read_text())["surface_fit"] == "cubic-limited"
    capsys.readouterr()
    _one_line_error(capsys, ["report", str(run_dir), "--out", str(tmp_path / "x"), "--surface-fit", "spline"],
                    "--surface-fit")


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
    _one_line_error(capsys, ["report", str(run_dir), "--out", out, "--truth-volume", "-5"], "must be > 0")
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
    _one_line_error(capsys, ["report", str(bad), "--out", str(tmp_path / "r")], "positive number", ExitCode.INPUT)
    assert not (tmp_path / "r").exists()  # inputs are read before the output is touched
