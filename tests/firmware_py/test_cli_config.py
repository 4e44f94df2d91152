"""`pilescan-payload --config FILE`: the file sets the options, a flag still wins, --check prints what would
run without opening hardware, each bad key is one line naming it (exit 2), and the log header carries
the effective configuration and the boresight."""

from __future__ import annotations

import datetime as dt
import math
import os
import tomllib
from pathlib import Path

import pytest

from firmware_py.cli import CONFIG_OPTIONS, build_parser, config_from_args, expand_log_name, main
from firmware_py.core.cli import ExitCode, parse_with_config
from firmware_py.core.config_file import parse_config
from firmware_py.core.frames import Boresight
from firmware_py.core.header import LogHeader, header_boresight
from firmware_py.core.servo_model import ServoCalibration
from firmware_py.payload_config import DEFAULT_PWM_URL

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "raspberry-pi.toml"
SERVICE = ROOT / "examples" / "pilescan-payload.service"
needs_example = pytest.mark.skipif(not EXAMPLE.exists(), reason="the example file is not in this install")


def write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "config.toml"
    p.write_text(text)
    return p


def payload_config(*argv: str):
    return config_from_args(parse_with_config(build_parser(), list(argv), CONFIG_OPTIONS))


def errors(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ": error: " in ln]


def set_keys(sections: dict, prefix: str = "") -> set[tuple[str, object]]:
    """(dotted key, value) of every key a configuration's sections set ([[piles]] items by number)."""
    out = set()
    for name, value in sections.items():
        if isinstance(value, dict):
            out |= set_keys(value, f"{prefix}{name}.")
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            for i, item in enumerate(value, start=1):
                out |= set_keys(item, f"{prefix}{name}#{i}.")
        else:
            out.add((f"{prefix}{name}", tuple(value) if isinstance(value, list) else value))
    return out


@needs_example
def test_that_check_validates_the_example_and_prints_what_would_run(capsys):
    assert main(["--config", str(EXAMPLE), "--check"]) == 0
    out, err = capsys.readouterr()
    assert errors(err) == []
    printed = tomllib.loads(out)
    assert parse_config(printed).to_dict() == printed  # it is a valid configuration file itself
    assert printed["payload"]["pwm"] == "pwm:pca9685:1:0x40:0"
    assert printed["payload"]["servo"]["slew_rad_s"] == 10.5
    assert printed["payload"]["log"] == "/home/pi/pilescan/survey-{utc}.pslog"  # the template, as the file has it
    assert printed["mission"]["turn"] == "one-step" and printed["sitl"]["sensor_noise"] == "datasheet"


RIG = """\
[site]
length_m = 60
width_m = 40
height_m = 15
name = "North bay"
timezone = "Europe/London"

[payload]
rangefinder = "lidarlite-v3"
uart = "serial:/dev/serial0:115200"
log = "logs/survey-{utc}.pslog"
rate_hz = 400
stop_on_disarm = true
start_on_arm = true

[payload.servo]
slew_rad_s = 10.5

[mission]
p_traj_pct = 20
altitude_m = 12
turn = "two-step"

[sitl]
sensor_noise = "datasheet"
pose_error = "flow"

[survey]
operator = "J. Smith"

[[piles]]
name = "sand"
x_m = 12
y_m = 8
density_kg_m3 = 1600
"""


def test_that_the_configuration_check_prints_reads_back_as_the_same_configuration(tmp_path, capsys):
    """Saved as the rig's file (a service that starts the payload again after each flight), --check's output had the
    start time in place of {utc} (the second flight's log already existed: refused, again and again) and had lost
    [mission] and [sitl]."""
    rig = write(tmp_path, RIG)
    assert main(["--config", str(rig), "--check"]) == 0
    first = capsys.readouterr().out
    saved = tmp_path / "saved.toml"
    saved.write_text(first)
    original, again = parse_config(tomllib.loads(RIG), base_dir=tmp_path), parse_config(tomllib.loads(first))
    assert again.payload.log == str(tmp_path / "logs" / "survey-{utc}.pslog")
    assert set_keys(original.to_dict()) <= set_keys(again.to_dict())  # every key the file sets, as it sets it
    assert {"mission", "sitl", "survey", "piles"} <= set(again.to_dict()) and again.site.name == "North bay"
    assert "# [payload] log: {utc} becomes the start time" in first and "/logs/survey-20" in first  # what it is now
    assert main(["--config", str(saved), "--check"]) == 0  # printed, saved and printed again: the same
    second = capsys.readouterr().out
    assert tomllib.loads(second) == tomllib.loads(first)


def test_that_check_prints_a_command_line_log_path_as_a_file_would_take_it(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["--check", "--out", "survey-{utc}.pslog"]) == 0
    assert tomllib.loads(capsys.readouterr().out)["payload"]["log"] == str(tmp_path / "survey-{utc}.pslog")


@pytest.mark.parametrize(("flags", "named"), [
    (["--lever-arm", "1e9", "0", "0"], "[payload] lever_arm_m"),
    (["--servo-lag-s", "1e9"], "[payload.servo] lag_s"),
    (["--servo-rate", "100"], "faster than the servo can turn"),
])
def test_that_a_flag_a_configuration_file_could_not_hold_is_refused_as_the_file_would_be(capsys, tmp_path, flags,
                                                                                        named):
    """--check printed these as a valid configuration, which then failed to read back, and a flight took them."""
    assert main(["--out", str(tmp_path / "x.pslog"), "--check", *flags]) == ExitCode.USAGE
    err = capsys.readouterr().err
    assert len(errors(err)) == 1 and "the command line: " in err and named in err


@needs_example
def test_that_check_shows_a_flag_over_the_file(capsys):
    assert main(["--config", str(EXAMPLE), "--check", "--rate", "250", "--servo-center-us", "1490"]) == 0
    printed = tomllib.loads(capsys.readouterr().out)
    assert printed["payload"]["rate_hz"] == 250.0 and printed["payload"]["servo"]["center_us"] == 1490.0


@pytest.mark.parametrize(("text", "key"), [
    ("[payload]\nrate_hz = -5\n", "[payload] rate_hz: must be 1-2000 Hz, got -5"),  # out of range
    ("[payload]\nrat_hz = 500\n", "[payload] rat_hz: unknown key"),  # unknown key
    ("[payload]\nlever_arm_m = \"0 0 0.1\"\n", "[payload] lever_arm_m: must be an array of 3 numbers"),  # type
    ("[payload]\npwm = \"pwm:sysfs:zero:0\"\n", "[payload] pwm: "),  # a URL the PWM backends refuse
    ("[payload]\nmavlink = \"udpout:host\"\n", "[payload] mavlink: expected HOST:PORT in MAVLink URL"),  # bad URL
    # a scheme no backend of this process serves: refused by --check as the flight would refuse it
    ("[payload]\nmavlink = \"mqtt:host:1883\"\n", "[payload] mavlink: unsupported MAVLink link scheme 'mqtt'"),
    ("[payload]\ni2c = \"spi:0\"\n", "[payload] i2c: malformed I2C bus URL 'spi:0': unknown scheme 'spi'"),
    ("[payload]\ni2c = \"tcp:sim-host\"\n", "[payload] i2c: malformed device bridge URL"),
    ("[payload.sweep]\nwaveform = \"square\"\n", "[payload.sweep] waveform: must be one of"),  # bad enum
    ("[site]\nlength_m = 60\nwidth_m = 40\n", "[site] height_m: missing"),  # a section missing a value
    ("[payload]\nlidarlite_preset = \"turbo\"\n", "[payload] lidarlite_preset: unknown LIDAR-Lite preset"),
])
def test_that_a_broken_config_is_one_line_naming_the_key_and_exit_2(tmp_path, capsys, text, key):
    path = write(tmp_path, text + "[payload]\nlog = \"x.pslog\"\n" if "[payload]" not in text else text)
    assert main(["--config", str(path), "--check", "--out", str(tmp_path / "x.pslog")]) == ExitCode.USAGE
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"pilescan-payload: error: {path}: {key}"), err


FIVE_PROBLEMS = """\
[site]
length_m = 60
width_m = 40

[payload]
rate_hz = -5
rat = 3
log = "x.pslog"
{pwm}
[mission]
turn = "three-step"

[[piles]]
name = "sand"
"""


def test_that_every_problem_the_schema_finds_is_reported_in_one_go(tmp_path, capsys):
    """Keys that are fine alone but not together ([site] height_m missing, a pile without its point) came out only
    once every other problem had been fixed."""
    path = write(tmp_path, FIVE_PROBLEMS.format(pwm=""))
    assert main(["--config", str(path), "--check"]) == ExitCode.USAGE
    named = [ln.split(f"{path}: ")[1].split(":")[0] for ln in errors(capsys.readouterr().err)]
    assert named == ["[payload] rate_hz", "[payload] rat", "[mission] turn", "[site] height_m", "[[piles]] #1 x_m"]


def test_that_a_url_the_payload_cannot_open_is_reported_with_the_files_other_problems(tmp_path, capsys):
    path = write(tmp_path, FIVE_PROBLEMS.format(pwm='pwm = "pwm:sysfs:zero:0"\n'))
    assert main(["--config", str(path), "--check"]) == ExitCode.USAGE
    named = [ln.split(f"{path}: ")[1].split(":")[0] for ln in errors(capsys.readouterr().err)]
    assert sorted(named) == sorted(["[payload] rate_hz", "[payload] rat", "[mission] turn", "[site] height_m",
                                    "[[piles]] #1 x_m", "[payload] pwm"])


def test_that_a_flag_overrides_the_file_and_the_file_the_default(tmp_path):
    path = write(tmp_path, "[payload]\nrate_hz = 400\nlog = \"a.pslog\"\n[payload.servo]\ncenter_us = 1480\n")
    assert payload_config("--out", "x.pslog").rate_hz == 500.0
    from_file = payload_config("--config", str(path))
    assert from_file.rate_hz == 400.0 and from_file.servo.center_us == 1480.0
    assert Path(from_file.out_path) == tmp_path / "a.pslog"
    flags = payload_config("--config", str(path), "--rate", "300", "--out", "b.pslog", "--servo-center-us", "1510")
    assert (flags.rate_hz, str(flags.out_path), flags.servo.center_us) == (300.0, "b.pslog", 1510.0)


def test_that_the_config_may_come_after_other_options_and_the_last_wins(tmp_path):
    a = write(tmp_path, "[payload]\nrate_hz = 400\n")
    b = tmp_path / "b.toml"
    b.write_text("[payload]\nrate_hz = 200\n")
    assert payload_config("--out", "x", "--config", str(a), "--config", str(b)).rate_hz == 200.0


def test_that_hal_on_the_command_line_overrides_the_files_buses(tmp_path):
    path = write(tmp_path, "[payload]\ni2c = \"i2c:3\"\npwm = \"pwm:sysfs:1:1\"\n")
    assert payload_config("--config", str(path), "--out", "x").pwm_url == "pwm:sysfs:1:1"
    cfg = payload_config("--config", str(path), "--out", "x", "--hal", "sitl:127.0.0.1:5760")
    assert (cfg.i2c_url, cfg.pwm_url) == ("tcp:127.0.0.1:5760", "pwm:tcp:127.0.0.1:5760:0")


def test_that_hal_with_bus_flags_is_still_refused(tmp_path, capsys):
    assert main(["--out", "x", "--hal", "sitl:127.0.0.1:5760", "--i2c", "i2c:1", "--check"]) == ExitCode.USAGE
    assert "give either --hal or those two" in capsys.readouterr().err


def test_that_servo_calibration_flags_set_each_field():
    cfg = payload_config("--out", "x", "--servo-center-us", "1480", "--servo-us-per-rad", "-600",
                         "--servo-min-us", "900", "--servo-max-us", "2100", "--servo-slew-rad-s", "9",
                         "--servo-lag-s", "0.03")
    assert cfg.servo == ServoCalibration(1480.0, -600.0, 900.0, 2100.0, 9.0, 0.03)
    assert payload_config("--out", "x").servo == ServoCalibration()


@pytest.mark.parametrize("argv", [["--servo-min-us", "1600"], ["--servo-us-per-rad", "0"], ["--servo-lag-s", "-1"],
                                  ["--boresight", "50", "0"], ["--boresight", "1"]])
def test_that_a_bad_servo_or_boresight_flag_is_one_line_and_exit_2(capsys, argv):
    assert main(["--out", "x", "--check", *argv]) == ExitCode.USAGE
    assert len(capsys.readouterr().err.splitlines()) == 1


def test_that_the_boresight_flag_is_in_degrees_and_reaches_the_header():
    cfg = payload_config("--out", "x", "--boresight", "2", "-1.5")
    assert cfg.boresight == Boresight(math.radians(2.0), math.radians(-1.5))
    header = cfg.log_header(sweep_t0_s=0.0)
    assert header_boresight(header) == cfg.boresight
    assert LogHeader.from_dict(header).boresight == cfg.boresight
    assert payload_config("--out", "x").log_header()["boresight"] == {"tilt_rad": 0.0, "sweep_yaw_rad": 0.0}


def test_that_the_header_carries_the_effective_configuration(tmp_path):
    path = write(tmp_path, "[site]\nlength_m = 30\nwidth_m = 20\nheight_m = 10\n"
                           "[payload]\nrate_hz = 400\nboresight_deg = [1.5, 0]\n[payload.servo]\nlag_s = 0.03\n")
    cfg = payload_config("--config", str(path), "--out", "x.pslog", "--rate", "250")
    record = cfg.log_header()["config"]
    assert record["file"] == str(path)
    assert record["payload"]["rate_hz"] == 250.0  # the flag, not the file
    assert record["payload"]["boresight_deg"] == [1.5, 0.0]
    assert record["payload"]["servo"]["lag_s"] == 0.03 and record["payload"]["pwm"] == DEFAULT_PWM_URL
    assert record["site"]["length_m"] == 30.0
    again = parse_config({k: v for k, v in record.items() if k != "file"})  # it reads back as a configuration
    assert again.payload.rate_hz == 250.0
    assert payload_config("--out", "x").log_header()["config"]["file"] is None


def test_that_a_missing_out_is_one_line(capsys):
    assert main(["--check"]) == ExitCode.USAGE
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "--out is required" in err


def test_that_utc_in_the_log_name_becomes_the_start_time():
    when = dt.datetime(2026, 11, 24, 23, 53, 1, tzinfo=dt.UTC)
    assert expand_log_name("/logs/survey-{utc}.pslog", when) == "/logs/survey-20261124T235301Z.pslog"
    assert expand_log_name("plain.pslog", when) == "plain.pslog"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_that_a_fifo_config_is_refused_at_once_exit_3(tmp_path, capsys):
    fifo = tmp_path / "config.toml"
    os.mkfifo(fifo)
    assert main(["--config", str(fifo), "--check", "--out", "x"]) == ExitCode.INPUT
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "FIFO" in err


def test_that_a_missing_config_is_one_line_exit_3(tmp_path, capsys):
    assert main(["--config", str(tmp_path / "nope.toml"), "--check", "--out", "x"]) == ExitCode.INPUT
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "No such file" in err


def test_that_check_says_whether_the_log_could_be_written_here_and_how_long_its_room_lasts(tmp_path, capsys):
    """--check looks at the log as the payload would open it: a path it could not write (or would not replace) is
    a warning, as is too little room; a writable one gets its room as a comment, and the output stays TOML."""
    assert main(["--check", "--out", str(tmp_path / "x.pslog")]) == 0
    out, err = capsys.readouterr()
    assert errors(err) == [] and "warning" not in err
    assert "# the log's file system has room for " in out and " of samples at 500 Hz" in out
    assert tomllib.loads(out)["payload"]["log"] == str(tmp_path / "x.pslog")
    (tmp_path / "old.pslog").write_bytes(b"")
    assert main(["--check", "--out", str(tmp_path / "old.pslog")]) == 0
    assert "warning: " in (err := capsys.readouterr().err) and "already exists" in err and "(on this machine)" in err
    assert main(["--check", "--out", str(tmp_path / "missing" / "x.pslog")]) == 0
    assert "directory " in (err := capsys.readouterr().err) and "does not exist (on this machine)" in err


def test_that_start_on_arm_is_a_flag_and_a_key_and_check_shows_it(tmp_path, capsys):
    assert payload_config("--out", "x.pslog", "--start-on-arm").start_on_arm
    assert not payload_config("--out", "x.pslog").start_on_arm
    path = write(tmp_path, "[payload]\nstart_on_arm = true\n")
    assert main(["--config", str(path), "--check", "--out", str(tmp_path / "x.pslog")]) == 0
    assert tomllib.loads(capsys.readouterr().out)["payload"]["start_on_arm"] is True


@pytest.mark.skipif(not (EXAMPLE.exists() and SERVICE.exists()), reason="the example files are not in this install")
def test_that_the_example_service_runs_the_payload_once_a_flight_and_its_command_checks(capsys):
    import configparser
    import shlex
    unit = configparser.ConfigParser(strict=True, interpolation=None)
    unit.read_string(SERVICE.read_text())
    svc = unit["Service"]
    argv = shlex.split(svc["ExecStart"])
    assert Path(argv[0]).is_absolute() and Path(argv[0]).name == "pilescan-payload"  # systemd wants a full path
    assert "--start-on-arm" in argv and "--stop-on-disarm" in argv  # a log per flight, nothing on the ground
    assert svc["Restart"] == "always" and svc["KillSignal"] == "SIGTERM"  # started again after each flight
    assert unit["Unit"]["StartLimitIntervalSec"] == "0" and unit["Install"]["WantedBy"] == "multi-user.target"
    args = argv[1:]
    args[args.index("--config") + 1] = str(EXAMPLE)  # the rig's file, as the README installs it
    assert main([*args, "--check"]) == 0, capsys.readouterr().err
    printed = tomllib.loads(capsys.readouterr().out)
    assert printed["payload"]["start_on_arm"] is True and printed["payload"]["stop_on_disarm"] is True


def test_that_check_writes_the_header_a_flight_would_start_its_log_with_for_listen(tmp_path, capsys):
    # listen needs the building and the sensor's placement before a first flight: the header comes from --check
    # (tests/ground/test_listen.py reads such a file with listen's own load_header; the payload's tests stay
    # within what a payload-only install has)
    import json
    rig = write(tmp_path, "[site]\nlength_m = 60.0\nwidth_m = 40.0\nheight_m = 15.0\n"
                          "[payload]\nlever_arm_m = [0.0, 0.0, 0.1]\n")
    out = tmp_path / "setup.json"
    rc = main(["--config", str(rig), "--out", str(tmp_path / "f.pslog"), "--check", "--write-header", str(out)])
    assert rc == 0
    header = json.loads(out.read_text())
    assert all(k in header for k in ("storage", "storage_frame", "lever_arm_body_m", "sensor"))
    assert header["storage"] == {"length_m": 60.0, "width_m": 40.0, "height_m": 15.0}
    assert header["lever_arm_body_m"] == [0.0, 0.0, 0.1]
    capsys.readouterr()
    assert main(["--config", str(rig), "--out", str(tmp_path / "f.pslog"), "--write-header",
                 str(tmp_path / "x.json")]) == ExitCode.USAGE
    assert "goes with --check" in capsys.readouterr().err and not (tmp_path / "x.json").exists()
