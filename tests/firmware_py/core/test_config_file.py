"""The configuration file's schema: every key checked, each problem one line naming its key, an unreadable
file refused at once, and what is written reads back."""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path

import pytest

from firmware_py.core.config_file import (
    ARRAYS,
    MAX_CONFIG_BYTES,
    ConfigError,
    ConfigFile,
    Kind,
    Rangefinder,
    ServoSection,
    Turn,
    key_label,
    load_config,
    parse_config,
    schema_keys,
    to_toml,
)
from firmware_py.core.safe_read import InputError
from firmware_py.core.servo_model import ServoCalibration

ROOT = Path(__file__).resolve().parents[3]
EXAMPLE = ROOT / "examples" / "raspberry-pi.toml"


def write(tmp_path: Path, text: str, name: str = "config.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def problems_of(text: str, tmp_path: Path) -> list[str]:
    with pytest.raises(ConfigError) as exc:
        load_config(write(tmp_path, text))
    return [str(exc.value), *exc.value.details]


@pytest.mark.skipif(not EXAMPLE.exists(), reason="the example file is not in this install")
def test_that_the_raspberry_pi_example_validates_and_sets_every_section():
    cfg = load_config(EXAMPLE)
    assert cfg.site.dimensions() == (60.0, 40.0, 15.0)
    assert cfg.payload.rangefinder is Rangefinder.LIDARLITE_V3
    assert cfg.payload.i2c == "i2c:1" and cfg.payload.pwm.startswith("pwm:pca9685:1:")
    assert cfg.payload.servo.calibration().us_per_rad == pytest.approx(1000 / math.pi, rel=1e-4)
    assert cfg.mission.turn is Turn.ONE_STEP and cfg.sitl.sensor_noise is not None


@pytest.mark.skipif(not EXAMPLE.exists(), reason="the example file is not in this install")
def test_that_every_key_of_the_example_is_commented():
    """A comment on the key's line or on the line above it."""
    lines = EXAMPLE.read_text().splitlines()
    for above, line in zip(["", *lines], lines, strict=False):
        if "=" in line and not line.lstrip().startswith("#"):
            assert "#" in line or above.lstrip().startswith("#"), f"uncommented key: {line}"


def test_that_every_keys_documented_example_is_valid():
    """The schema's own examples (the reference page shows them) pass its checks."""
    data: dict = {}
    for key, f in schema_keys():
        *sections, name = key.split(".")
        table = data
        for s in sections:
            table = table.setdefault(s, [{}] if s in ARRAYS else {})
            table = table[0] if isinstance(table, list) else table
        ex = f.metadata["example"]
        table[name] = list(ex) if isinstance(ex, tuple) else ex
    cfg = parse_config(data, "examples")
    assert to_toml(cfg.to_dict())  # and it writes


@pytest.mark.parametrize(("text", "key", "what"), [
    ("[payload]\nrate = 500\n", "[payload] rate", "unknown key (did you mean rate_hz?)"),
    ("[payload]\nrate_hz = \"500\"\n", "[payload] rate_hz", "must be a number, got a string"),
    ("[payload]\nrate_hz = -5\n", "[payload] rate_hz", "must be 1-2000 Hz, got -5"),
    ("[payload]\ni2c = \"/dev/i2c-1\"\n", "[payload] i2c", "must be a URL like SCHEME:"),
    ("[payload]\nstream = \"udp:ground\"\n", "[payload] stream", "live stream URL must look like"),
    ("[mission]\nturn = \"three-step\"\n", "[mission] turn", "must be one of one-step, two-step"),
    ("[site]\nlength_m = 60\nwidth_m = 40\n", "[site] height_m", "missing"),
    ("[payload.servo]\ncenter_us = 2100\n", "[payload.servo] center_us", "min_us < center_us < max_us"),
    ("[payload.servo]\nus_per_rad = 0\n", "[payload.servo] us_per_rad", "not 0"),
    ("[payload]\nlever_arm_m = [0, 0]\n", "[payload] lever_arm_m", "array of 3 numbers [x, y, z]"),
    ("[payload]\nboresight_deg = [50, 0]\n", "[payload] boresight_deg", "tilt must be within -45..45 deg"),
    ("[site]\norigin = [95, 0, 0]\n", "[site] origin", "lat_deg must be within -90..90"),
    ("[payload.sweep]\nphase = 2.5\n", "[payload.sweep] phase", "must be an integer"),
    ("[payload]\nstop_on_disarm = 1\n", "[payload] stop_on_disarm", "must be true or false"),
    ("[payload.sweep]\npeak_rate_rad_s = 8\n[payload.servo]\nslew_rad_s = 5\n", "[payload.sweep] peak_rate_rad_s",
     "faster than the servo can turn"),
    ("site = 3\n", "[site]", "must be a table"),
    ("[playload]\nrate_hz = 5\n", "[playload]", "unknown section (did you mean payload?)"),
    ("[mission]\np_traj_pct = nan\n", "[mission] p_traj_pct", "must be a finite number"),
])
def test_that_each_bad_key_is_one_line_naming_it(tmp_path, text, key, what):
    lines = problems_of(text, tmp_path)
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"{tmp_path / 'config.toml'}: {key}:"), lines[0]
    assert what in lines[0]


def test_that_every_problem_of_a_file_is_reported_at_once(tmp_path):
    lines = problems_of("[payload]\nrate_hz = 0\nfoo = 1\n[mission]\nspeed_m_s = 99\n", tmp_path)
    assert [ln.split(": ")[1] for ln in lines] == ["[payload] rate_hz", "[payload] foo", "[mission] speed_m_s"]


def test_that_the_checks_across_keys_are_reported_with_the_keys_own_problems(tmp_path):
    """A [site] height_m missing came out only once every other problem had been fixed."""
    lines = problems_of("[site]\nlength_m = 60\nwidth_m = 40\n[payload]\nrate_hz = -5\nrat = 3\n"
                        "[payload.sweep]\npeak_rate_rad_s = 8\n[payload.servo]\nslew_rad_s = 5\n"
                        "[mission]\nturn = \"three-step\"\n[[piles]]\nname = \"sand\"\nx_m = 3\n", tmp_path)
    assert [ln.split(": ")[1] for ln in lines] == [
        "[payload] rate_hz", "[payload] rat", "[mission] turn", "[site] height_m", "[payload.sweep] peak_rate_rad_s",
        "[[piles]] #1 y_m"]


def test_that_a_refused_key_is_not_also_called_missing_nor_checked_against_the_others(tmp_path):
    lines = problems_of("[site]\nlength_m = 60\nwidth_m = -40\nheight_m = 15\n"
                        "[payload.servo]\nmin_us = 100\ncenter_us = 1500\n"
                        "[[piles]]\nname = \"sand\"\nx_m = \"12\"\ny_m = 8\n", tmp_path)
    assert [ln.split(": ")[1] for ln in lines] == ["[site] width_m", "[payload.servo] min_us", "[[piles]] #1 x_m"]
    assert "must be 0.5-10000 m, got -40" in lines[0]


def test_that_a_refused_file_still_gives_its_good_keys_for_the_programs_own_checks(tmp_path):
    """The programs check some keys with their own options (a URL's backends): they run on these, in the same
    report."""
    with pytest.raises(ConfigError) as exc:
        load_config(write(tmp_path, "[payload]\nrate_hz = -5\npwm = \"pwm:sysfs:zero:0\"\n[site]\nlength_m = 9\n"))
    good = exc.value.config
    assert good.payload.pwm == "pwm:sysfs:zero:0" and good.payload.rate_hz is None and good.site.length_m == 9.0
    assert good.get("site.dimensions") is None  # not the building: a part of one
    assert exc.value.problems == (str(exc.value), *exc.value.details) and len(exc.value.problems) == 2  # not pwm
    with pytest.raises(ConfigError) as exc:
        load_config(write(tmp_path, "[site\n"))
    assert exc.value.config is None  # not TOML: no key to check


def test_that_a_toml_syntax_error_names_the_line(tmp_path):
    lines = problems_of("[site]\nlength_m = 60\nwidth_m = = 40\n", tmp_path)
    assert len(lines) == 1 and "not valid TOML" in lines[0] and "line 3" in lines[0]


def test_that_an_empty_file_sets_nothing(tmp_path):
    cfg = load_config(write(tmp_path, "# nothing yet\n"))
    assert cfg.to_dict() == {} and cfg.get("payload.rate_hz") is None and cfg.get("site.dimensions") is None


def test_that_relative_paths_are_taken_from_the_files_folder(tmp_path):
    (tmp_path / "rig").mkdir()
    cfg = load_config(write(tmp_path / "rig", "[payload]\nlog = \"logs/a.pslog\"\nsigning_key = \"/etc/k\"\n"))
    assert cfg.payload.log == str(tmp_path / "rig" / "logs" / "a.pslog")
    assert cfg.payload.signing_key == "/etc/k"


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_that_a_fifo_is_refused_at_once_not_waited_on(tmp_path):
    fifo = tmp_path / "config.toml"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="FIFO"):
        load_config(fifo)


def test_that_a_huge_file_is_refused_before_it_is_read(tmp_path):
    p = tmp_path / "config.toml"
    with p.open("wb") as f:
        f.truncate(MAX_CONFIG_BYTES + 1)
    with pytest.raises(InputError, match="byte limit"):
        load_config(p)


def test_that_a_missing_or_binary_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="No such file"):
        load_config(tmp_path / "nope.toml")
    p = tmp_path / "bin.toml"
    p.write_bytes(b"\xff\xfe[site]")
    with pytest.raises(InputError, match="not UTF-8"):
        load_config(p)


def test_that_written_toml_reads_back_the_same(tmp_path):
    cfg = parse_config({"site": {"length_m": 10.5, "width_m": 8, "height_m": 6, "origin": [1.5, -2.25, 3]},
                        "payload": {"log": "a \"quoted\" name.pslog", "stop_on_disarm": False,
                                    "servo": {"lag_s": 0.01}, "sweep": {"phase": 12}},
                        "mission": {"turn": "two-step"}})
    again = parse_config(tomllib.loads(to_toml(cfg.to_dict())))
    assert again.to_dict() == cfg.to_dict()
    assert again.payload.log == 'a "quoted" name.pslog'


def test_that_the_servo_section_overrides_only_what_it_sets():
    cal = ServoSection(center_us=1480.0, lag_s=0.03).calibration()
    assert cal == ServoCalibration(center_us=1480.0, lag_s=0.03)


def test_that_the_schema_knows_its_kinds_and_labels():
    keys = dict(schema_keys())
    assert keys["payload.servo.center_us"].metadata["kind"] is Kind.NUMBER
    assert key_label("payload.servo.center_us") == "[payload.servo] center_us"
    assert key_label("site.dimensions") == "[site] length_m, width_m, height_m"
    with pytest.raises(KeyError):
        ConfigFile().get("payload.nope")


def test_that_the_turn_choices_are_the_missions():
    rect = pytest.importorskip("sitl.missions.rectangle")
    assert tuple(t.value for t in Turn) == rect.TURN_MODES
