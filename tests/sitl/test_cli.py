"""pilescan-sitl: every bad input is one line, its kind's exit code (`ExitCode`), no traceback; --force, -v/-q."""

import json
import os
import signal

import pytest

from firmware_py.core.cli import ExitCode
from firmware_py.core.version import __version__, software_version
from sitl.cli import main

USAGE, INPUT, RUNTIME = ExitCode.USAGE, ExitCode.INPUT, ExitCode.RUNTIME


def test_that_version_prints_the_software_version_and_exits_0(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out
    assert out.strip() == software_version() and __version__ in out


def test_that_fly_writes_a_run_with_the_firmware_in_the_loop_by_default(tmp_path, capsys):
    # the small building: the default payload, not the size, is what is tested
    assert main(["fly", "--stockpile", "1", "--p-traj", "25", "--storage", "30x20x10", "--altitude", "9",
                 "--out", str(tmp_path), "--quiet"]) == 0
    assert (tmp_path / "samples.pslog").is_file()
    assert json.loads((tmp_path / "truth.json").read_text())["payload"] == "firmware"


def test_that_the_ideal_plant_defaults_to_the_batch_sampler(tmp_path, capsys):
    assert main(["fly", "--stockpile", "1", "--p-traj", "25", "--plant", "ideal", "--out", str(tmp_path),
                 "--quiet"]) == 0
    assert json.loads((tmp_path / "truth.json").read_text())["payload"] == "batch"


@pytest.mark.parametrize("extra,match", [
    (["--stockpile", "1", "--p-traj", "0"], "P_traj"),
    (["--stockpile", "1", "--p-traj", "50"], "P_traj"),
    (["--stockpile", "1", "--p-traj", "75"], "P_traj"),
    (["--stockpile", "1", "--p-traj", "nan"], "finite"),
    (["--stockpile", "1", "--p-traj", "ten"], "not a number"),
    (["--stockpile", "1", "--p-traj", "20", "--storage", "60x40"], "LxWxH"),
    (["--stockpile", "1", "--p-traj", "20", "--storage", "60x40x10"], "altitude"),
    (["--stockpile", "1", "--p-traj", "20", "--altitude", "5"], "stockpile top"),
    (["--stockpile", "1", "--p-traj", "20", "--speed", "-1"], "speed"),
    (["--stockpile", "1", "--p-traj", "20", "--yaw-rate-max", "inf"], "finite"),
    (["--stockpile", "1", "--p-traj", "20", "--yaw-rate-max", "0.001"], "in [0.5, 360] deg/s"),  # a flight of days
    (["--stockpile", "1", "--p-traj", "20", "--phase", "20"], "0..19"),
    (["--stockpile", "1", "--p-traj", "20", "--turn", "zigzag"], "invalid choice"),
    (["--stockpile", "1", "--p-traj", "20", "--plant", "webots"], "invalid choice"),
    (["--stockpile", "1"], "--p-traj"),
    (["--stockpile", "1", "--p-traj", "20", "--plant", "ideal", "--payload", "firmware"], "jsbsim plant"),
    (["--stockpile", "1", "--p-traj", "20", "--sensor-noise", "gaussian"], "none, datasheet, appendix-a"),
    (["--stockpile", "1", "--p-traj", "20", "--sensor-noise", "Datasheet"], "got 'Datasheet'"),
    (["--stockpile", "1", "--p-traj", "20", "--pose-error", "bogus"], "none, flow, vio"),
    (["--stockpile", "1", "--p-traj", "20", "--pose-error", "flow", "--altitude", "14"], "roof"),
])
def test_that_bad_options_fail_with_one_line_and_exit_2(tmp_path, capsys, monkeypatch, extra, match):
    monkeypatch.chdir(tmp_path)
    code = main(["fly", *extra, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == USAGE
    assert err.count("\n") == 1 and "Traceback" not in err
    assert match in err
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("stockpile,match", [("7", "unknown stockpile"), ("pile.xyz", "unknown stockpile"),
                                             ("missing.stl", "not found")])
def test_that_a_stockpile_that_cannot_be_had_is_an_input_error_3(tmp_path, capsys, monkeypatch, stockpile, match):
    monkeypatch.chdir(tmp_path)
    code = main(["fly", "--stockpile", stockpile, "--p-traj", "20", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == INPUT and err.count("\n") == 1 and match in err
    assert not (tmp_path / "run").exists()


def test_that_a_corrupt_mesh_fails_with_one_line_and_exit_3(tmp_path, capsys):
    bad = tmp_path / "pile.stl"
    bad.write_bytes(b"\x00" * 50)
    code = main(["fly", "--stockpile", str(bad), "--p-traj", "20", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == INPUT and err.count("\n") == 1 and "pile.stl" in err
    assert not (tmp_path / "run").exists()  # a failed fly leaves no folder behind


def test_that_an_out_path_under_a_file_fails_with_one_line_and_exit_4(tmp_path, capsys):
    blocker = tmp_path / "blocker"
    blocker.write_text("x")
    code = main(["fly", "--stockpile", "1", "--p-traj", "20", "--out", str(blocker / "run")])
    err = capsys.readouterr().err
    assert code == RUNTIME and err.count("\n") == 1 and "Traceback" not in err


# ----- serve: link security --------------------------------------------------------------------------

def _key_file(tmp_path, mode: int = 0o600):
    path = tmp_path / "link.key"
    path.write_text(bytes(range(1, 33)).hex() + "\n")
    path.chmod(mode)
    return path


@pytest.mark.parametrize(("extra", "match", "expected"), [
    (["--signing-key", "/nonexistent/link.key"], "does not exist", INPUT),
    (["--allow-unsigned"], "--allow-unsigned needs --signing-key", USAGE),
])
def test_that_a_bad_signing_key_fails_serve_with_one_line_before_anything_starts(tmp_path, capsys, extra, match,
                                                                                  expected):
    out = tmp_path / "serve"
    code = main(["serve", "--vehicle", "kinematic", "--duration", "0.1", "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert code == expected and err.count("\n") == 1 and "Traceback" not in err
    assert match in err and not out.exists()


def test_that_a_world_readable_signing_key_is_refused_by_serve(tmp_path, capsys):
    if os.name != "posix":
        pytest.skip("POSIX permission bits")
    key = _key_file(tmp_path, mode=0o644)
    code = main(["serve", "--vehicle", "kinematic", "--out", str(tmp_path / "serve"), "--signing-key", str(key)])
    err = capsys.readouterr().err
    assert code == INPUT and err.count("\n") == 1 and "chmod 600" in err


def test_that_serve_with_a_signing_key_says_so_and_reports_what_it_refused(tmp_path, capsys):
    handlers = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--duration", "0.2",
                 "--speedup", "20", "--out", str(tmp_path / "serve"), "--signing-key", str(_key_file(tmp_path))])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "MAVLink signing on" in err and "refused 0 unsigned, 0 badly signed and 0 replayed frames" in err
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers  # restored


# ----- plan --force -----------------------------------------------------------------------------------

def test_that_plan_refuses_to_overwrite_without_force_and_replaces_with_it(tmp_path, capsys):
    out = tmp_path / "p.waypoints"
    assert main(["plan", "--p-traj", "20", "--out", str(out)]) == 0
    assert f"plan written to {out}" in capsys.readouterr().out
    first = out.read_text()
    code = main(["plan", "--p-traj", "30", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == USAGE and err.count("\n") == 1 and "--force" in err
    assert out.read_text() == first
    assert main(["plan", "--p-traj", "30", "--out", str(out), "--force", "-q"]) == 0
    assert capsys.readouterr() == ("", "")
    assert out.read_text() != first
    assert [p.name for p in tmp_path.iterdir()] == ["p.waypoints"]  # no temporary left beside it


def test_that_plan_warns_when_the_estimate_it_will_be_flown_on_can_drift_into_a_wall(tmp_path, capsys):
    """A real flight indoors flies on a drifting estimate: the plan a drone engineer exports is checked as `fly`
    checks a simulated one, and still written (a warning, not a refusal: the pilot may fly a better estimate)."""
    near, far = tmp_path / "near.waypoints", tmp_path / "far.waypoints"
    assert main(["plan", "--p-traj", "5", "--pose-error", "flow", "--out", str(near)]) == 0
    err = capsys.readouterr().err
    assert "warning: the legs run 2.00 m from the walls, and a flow estimate can drift" in err and near.exists()
    assert main(["plan", "--p-traj", "20", "--pose-error", "flow", "--out", str(far)]) == 0
    assert "warning" not in capsys.readouterr().err  # 8 m of room
    assert main(["plan", "--p-traj", "5", "--out", str(tmp_path / "truth.waypoints")]) == 0
    assert "warning" not in capsys.readouterr().err  # no estimate named: motion capture, RTK


# ----- -v / -q -------------------------------------------------------------------------------------------

IDEAL = ["fly", "--stockpile", "1", "--p-traj", "25", "--plant", "ideal"]


def test_that_fly_reports_progress_by_default_debug_with_v_and_nothing_with_q(tmp_path, capsys):
    assert main([*IDEAL, "--out", str(tmp_path / "a")]) == 0
    cap = capsys.readouterr()
    assert cap.out.startswith(f"run written to {tmp_path / 'a'}")
    assert "pilescan-sitl: stockpile: paper pile 1" in cap.err and "debug" not in cap.err
    assert main([*IDEAL, "--out", str(tmp_path / "b"), "-v"]) == 0
    assert "pilescan-sitl: debug: sitl.runners.fly: " in capsys.readouterr().err
    assert main(["-q", *IDEAL, "--out", str(tmp_path / "c")]) == 0
    assert capsys.readouterr() == ("", "")
    assert main([*IDEAL, "--out", str(tmp_path / "d"), "-q", "-v"]) == USAGE
    assert not (tmp_path / "d").exists()


def test_that_serve_refuses_an_unknown_sensor_noise_with_one_line_and_exit_2(tmp_path, capsys):
    code = main(["serve", "--sensor-noise", "appendix_a", "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == USAGE and err.count("\n") == 1 and "--sensor-noise" in err and "appendix-a" in err
    assert not (tmp_path / "run").exists()


def test_that_fly_s_help_names_every_fault_the_injector_knows(capsys):
    # the help was written by hand and named 12 of the 24 faults fly accepts
    from dataclasses import fields

    from sitl.faults.injector import FaultSpec
    assert main(["fly", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    missing = [f.name for f in fields(FaultSpec) if f.name != "seed" and f"{f.name}=" not in text]
    assert not missing, missing
