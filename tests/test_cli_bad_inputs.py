"""Every bad input to the three programs (and the reproduction command): exactly one line on stderr in the
program's own `PROG: error: ...` form, its kind's exit code (`ExitCode`: 2 a bad command line, 3 a bad input
file, 4 an output the system refuses), no traceback, nothing started or opened.

The per-program tests (tests/sitl/test_cli.py, tests/ground/test_cli.py, tests/firmware_py/test_cli.py,
tests/tools/test_reproduce.py) cover the options each was written with; this table covers what they miss,
the same way for every program: missing and unknown options, out-of-range and non-finite numbers, malformed
URLs, missing / unreadable / corrupt inputs, unwritable and already-existing outputs. Commands that would start a
server or open hardware are given a bad option, so they fail before they open anything (the payload's MAVLink
link, when it gets that far, points at the discard port).
"""

from __future__ import annotations

import json
import random
import socket
from pathlib import Path

import pytest

from firmware_py import cli as payload_cli
from firmware_py.core.cli import ExitCode
from firmware_py.core.samplelog import encode_block
from ground import cli as ground_cli
from sitl import cli as sitl_cli
from tests.ground.test_report_fuzz import BASE_HEADER, floor_samples
from tools import reproduce

MAINS = {"sitl": sitl_cli.main, "ground": ground_cli.main, "payload": payload_cli.main, "reproduce": reproduce.main}
PROGS = {"sitl": "pilescan-sitl", "ground": "pilescan-ground", "payload": "pilescan-payload",
         "reproduce": "python -m tools.reproduce"}
NOBODY = "udpout:127.0.0.1:9"  # the discard port: no autopilot there
FLY = ["fly", "--stockpile", "1", "--p-traj", "20", "--quiet"]
SERVE = ["serve", "--vehicle", "kinematic", "--duration", "1"]  # if a case ever got through, it would end
PAY = ["--mavlink", NOBODY, "--i2c", "i2c:/dev/i2c-nonexistent-77"]
LISTEN = ["listen", "--duration", "1"]  # if a case ever got through, it would end
LSTREAM = ["--stream", "udp:127.0.0.1:14599"]
INPUT, RUNTIME = ExitCode.INPUT, ExitCode.RUNTIME  # a case without a code is a usage error (2)
REP = ["--cache", "cache", "--rows", "rows.csv", "--quiet", "--experiments", "baseline-ideal", "--piles", "1",
       "--positions", "1"]


def log_bytes(header) -> bytes:
    return encode_block(b"H", json.dumps(header).encode()) + encode_block(b"S", floor_samples().tobytes())


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """Bad (and a few good) input files, by name: {d}/NAME in a case's argv."""
    d = tmp_path_factory.mktemp("inputs")
    rng = random.Random(20)
    (d / "blocker").write_text("a regular file where a directory is needed")
    (d / "adir.pslog").mkdir()
    (d / "adir.stl").mkdir()
    (d / "adir.toml").mkdir()
    (d / "empty.pslog").write_bytes(b"")
    (d / "random.pslog").write_bytes(bytes(rng.randrange(256) for _ in range(4000)))
    (d / "good.pslog").write_bytes(log_bytes(BASE_HEADER))
    (d / "header-only.pslog").write_bytes(encode_block(b"H", json.dumps(BASE_HEADER).encode()))
    (d / "list-header.pslog").write_bytes(encode_block(b"H", b"[1, 2]") + encode_block(b"S", b""))
    (d / "typed-header.pslog").write_bytes(log_bytes({**BASE_HEADER, "sensor": "lidar-lite"}))
    (d / "huge-building.pslog").write_bytes(log_bytes({**BASE_HEADER, "storage": {
        "length_m": 10_000.0, "width_m": 10_000.0, "height_m": 15.0}}))
    (d / "empty.stl").write_bytes(b"")
    (d / "random.stl").write_bytes(bytes(rng.randrange(256) for _ in range(300)))
    (d / "nofacets.stl").write_text("solid pile\nendsolid pile\n")
    (d / "text.obj").write_text("this is not\na mesh\n")
    (d / "oversize.obj").write_text("v 0 0 0\nv 100 0 0\nv 0 100 1\nf 1 2 3\n")  # larger than the building
    (d / "random.toml").write_bytes(bytes(rng.randrange(256) for _ in range(300)))
    (d / "empty.toml").write_text("")
    (d / "typed.toml").write_text('[[experiment]]\nname = 5\n')
    (d / "dup.toml").write_text('[[experiment]]\nname = "a"\n[[experiment]]\nname = "a"\n')
    (d / "noise-2d.toml").write_text('[[experiment]]\nname = "n"\nsensor = "2d"\nnoise_draws = 3\n')
    (d / "open.key").write_text("11" * 32 + "\n")
    (d / "open.key").chmod(0o644)  # readable by everyone: refused
    (d / "short.key").write_text("abc123\n")
    (d / "short.key").chmod(0o600)
    (d / "list.json").write_text("[1, 2]")
    (d / "layout.json").write_text('{"record_dtype": [["t_s", "<f8"]]}')
    run = d / "old-run"
    run.mkdir()
    (run / "samples.pslog").write_bytes(b"yesterday's survey")
    (d / "old.pslog").write_bytes(b"yesterday's survey")
    return d


CASES = [
    # ----- pilescan-sitl: the command line itself
    ("sitl", [], "required: command"),
    ("sitl", ["land"], "invalid choice"),
    ("sitl", ["fly", "--warp", "9", *FLY[1:], "--out", "{t}/run"], "unrecognized arguments"),
    ("sitl", ["fly", "--p-traj", "20", "--out", "{t}/run"], "--stockpile"),
    ("sitl", ["fly", "--stockpile", "1", "--p-traj"], "expected one argument"),
    # ... numbers
    ("sitl", [*FLY, "--speed", "nan", "--out", "{t}/run"], "finite"),
    ("sitl", [*FLY, "--altitude", "inf", "--out", "{t}/run"], "finite"),
    ("sitl", [*FLY, "--servo-rate=-inf", "--out", "{t}/run"], "finite"),
    ("sitl", [*FLY, "--servo-rate", "1e308", "--out", "{t}/run"], "servo rate"),
    ("sitl", [*FLY, "--servo-rate", "0", "--out", "{t}/run"], "servo rate"),
    ("sitl", [*FLY, "--payload-mass", "3", "--out", "{t}/run"], "payload mass"),
    ("sitl", [*FLY, "--latency-ms", "5", "1", "--out", "{t}/run"], "latency"),
    ("sitl", [*FLY, "--latency-ms", "1", "--out", "{t}/run"], "expected 2 arguments"),
    ("sitl", [*FLY, "--seed", "-1", "--out", "{t}/run"], "seed"),
    ("sitl", [*FLY, "--seed", "1.5", "--out", "{t}/run"], "invalid int"),
    ("sitl", [*FLY, "--phase", "-1", "--out", "{t}/run"], "0..19"),
    ("sitl", [*FLY, "--storage", "1e999x40x15", "--out", "{t}/run"], "storage length"),
    ("sitl", [*FLY, "--storage", "60x40x15x3", "--out", "{t}/run"], "LxWxH"),
    ("sitl", [*FLY, "--p-traj", "1e-300", "--out", "{t}/run"], "from a wall"),
    # ... inputs
    ("sitl", ["fly", "--stockpile", "{d}/empty.stl", "--p-traj", "20", "--out", "{t}/run"], "empty.stl", INPUT),
    ("sitl", ["fly", "--stockpile", "{d}/random.stl", "--p-traj", "20", "--out", "{t}/run"], "random.stl", INPUT),
    ("sitl", ["fly", "--stockpile", "{d}/nofacets.stl", "--p-traj", "20", "--out", "{t}/run"], "no triangles", INPUT),
    ("sitl", ["fly", "--stockpile", "{d}/adir.stl", "--p-traj", "20", "--out", "{t}/run"], "not found", INPUT),
    ("sitl", ["fly", "--stockpile", "{d}/text.obj", "--p-traj", "20", "--out", "{t}/run"], "text.obj", INPUT),
    ("sitl", ["fly", "--stockpile", "{d}/oversize.obj", "--p-traj", "20", "--out", "{t}/run"], "inside", INPUT),
    # ... outputs
    ("sitl", [*FLY, "--out", ""], "non-empty"),
    ("sitl", [*FLY, "--out", "{d}/old-run"], "--force"),
    ("sitl", ["plan", "--p-traj", "20", "--out", "{d}/blocker/p.waypoints"], "Not a directory", RUNTIME),
    ("sitl", ["plan", "--p-traj", "20", "--out", "{d}/adir.stl"], "a directory"),
    ("sitl", ["plan", "--p-traj", "20", "--out", ""], "directory"),
    ("sitl", ["plan", "--out", "{t}/p.waypoints"], "--p-traj"),
    ("sitl", ["plan", "--p-traj", "nan", "--out", "{t}/p.waypoints"], "finite"),
    ("sitl", ["plan", "--p-traj", "20", "--altitude", "100", "--out", "{t}/p.waypoints"], "altitude"),
    # ... serve: every bad option fails before a socket or a device bridge is opened
    ("sitl", [*SERVE, "--speedup", "nan"], "finite"),
    ("sitl", [*SERVE, "--speedup", "-1", "--out", "{t}/s"], "--speedup"),
    ("sitl", [*SERVE, "--speedup", "2000", "--out", "{t}/s"], "--speedup"),
    ("sitl", ["serve", "--vehicle", "kinematic", "--duration", "0", "--out", "{t}/s"], "--duration"),
    ("sitl", ["serve", "--vehicle", "kinematic", "--duration", "inf", "--out", "{t}/s"], "finite"),
    ("sitl", [*SERVE, "--vehicle", "x"], "invalid choice"),
    ("sitl", [*SERVE, "--mavlink", "udp:localhost:99999", "--out", "{t}/s"], "UDP port"),
    ("sitl", [*SERVE, "--mavlink", "udp::14550", "--out", "{t}/s"], "udp:HOST:PORT"),
    ("sitl", [*SERVE, "--mavlink", "udpout:127.0.0.1:0", "--out", "{t}/s"], "UDP port"),
    ("sitl", [*SERVE, "--mavlink", "serial:/dev/ttyS0", "--out", "{t}/s"], "unsupported transport"),
    ("sitl", [*SERVE, "--devices", "tcp:h", "--out", "{t}/s"], "tcp:HOST:PORT"),
    ("sitl", [*SERVE, "--devices", "udp:127.0.0.1:0", "--out", "{t}/s"], "tcp:HOST:PORT"),
    ("sitl", [*SERVE, "--devices", "tcp:127.0.0.1:0", "--speedup", "2", "--out", "{t}/s"], "--speedup 1"),
    ("sitl", [*SERVE, "--devices", "tcp:127.0.0.1:0", "--stockpile", "{d}/random.stl", "--out", "{t}/s"],
     "random.stl", INPUT),
    ("sitl", [*SERVE, "--mavlink", "udp:127.0.0.1:0", "--out", "{d}/blocker/s"], "Not a directory", RUNTIME),
    ("sitl", [*SERVE, "--p-traj", "70", "--out", "{t}/s"], "P_traj"),
    # ... serve --fault: fly's names, checked, and refused where the payload is another process
    ("sitl", [*SERVE, "--fault", "power_cut_at_s=5", "--out", "{t}/s"], "another process"),
    ("sitl", [*SERVE, "--fault", "clock_jump=5,10", "--out", "{t}/s"], "real clock"),
    ("sitl", [*SERVE, "--fault", "i2c_nack_pct=5", "--out", "{t}/s"], "needs --devices"),
    ("sitl", [*SERVE, "--fault", "servo_stuck_at_s=5", "--out", "{t}/s"], "needs --devices"),
    ("sitl", [*SERVE, "--fault", "warp=1", "--out", "{t}/s"], "NAME one of"),
    ("sitl", [*SERVE, "--fault", "link_loss_pct", "--out", "{t}/s"], "NAME=VALUE"),
    ("sitl", [*SERVE, "--fault", "link_loss_pct=200", "--out", "{t}/s"], "percentage"),
    ("sitl", [*SERVE, "--fault", "link_loss_pct=nan", "--out", "{t}/s"], "percentage"),
    ("sitl", [*SERVE, "--fault", "link_outage=3", "--out", "{t}/s"], "START,DURATION"),
    ("sitl", [*SERVE, "--fault", "autopilot_reboot=5,-1", "--out", "{t}/s"], "autopilot_reboot"),
    ("sitl", [*SERVE, "--fault", "link_latency_ms=x", "--out", "{t}/s"], "not a number"),
    ("sitl", [*SERVE, "--seed", "-1", "--fault", "link_loss_pct=5", "--out", "{t}/s"], "seed"),
    ("sitl", [*SERVE, "--seed", "1.5", "--out", "{t}/s"], "invalid int"),
    # ----- pilescan-ground
    ("ground", [], "required: command"),
    ("ground", ["volume"], "invalid choice"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--plots"], "unrecognized arguments"),
    ("ground", ["report", "--out", "{t}/r"], "RUN_DIR_OR_LOG"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--cell", "inf"], "finite"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--cell", "-1"], "cell size"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--cell", "1e-3"], "cell size"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--cell", "1e9"], "cell size"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--truth-volume", "inf"], "finite"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--truth-volume", "-1"], "must be >= 0"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--max-interval-pct", "0"], "--max-interval-pct"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--baro-walk", "0"], "--baro-walk must be > 0"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--baro-walk", "2"], "at most 1 m/sqrt(s)"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--baro-walk", "nan"], "finite"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--mount", "3", "5", "2"], "expected 4 arguments"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--mount", "25", "0", "0", "0"],
     "--mount: the servo offset must be within +/-20 deg"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--mount", "0", "-40", "0", "0"],
     "--mount: the servo scale must be within +/-30 %"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{t}/r", "--mount", "0", "0", "0", "nan"], "finite"),
    ("ground", ["report", "{d}/empty.pslog", "--out", "{t}/r"], "header is missing or corrupt", INPUT),
    ("ground", ["report", "{d}/random.pslog", "--out", "{t}/r"], "header is missing or corrupt", INPUT),
    ("ground", ["report", "{d}/blocker", "--out", "{t}/r"], "header is missing or corrupt", INPUT),
    ("ground", ["report", "{d}/adir.pslog", "--out", "{t}/r"], "without a samples.pslog", INPUT),
    ("ground", ["report", "{d}/header-only.pslog", "--out", "{t}/r"], "no samples", INPUT),
    ("ground", ["report", "{d}/list-header.pslog", "--out", "{t}/r"], "header is missing or corrupt", INPUT),
    ("ground", ["report", "{d}/typed-header.pslog", "--out", "{t}/r"], "sensor", INPUT),
    ("ground", ["report", "{d}/huge-building.pslog", "--out", "{t}/r"], "larger cell size"),
    ("ground", ["report", "", "--out", "{t}/r"], "non-empty"),
    ("ground", ["report", "{d}/good.pslog", "--out", ""], "non-empty"),
    ("ground", ["report", "{d}/good.pslog", "--out", "{d}/blocker", "--no-plots"], "exists and is not a folder",
     RUNTIME),
    ("ground", ["report", "{d}/good.pslog", "--out", "{d}/blocker/r", "--no-plots"], "blocker", RUNTIME),
    # ... listen: every bad option fails before the socket is bound or the log is created
    ("ground", ["listen"], "--stream"),
    ("ground", [*LISTEN, *LSTREAM, "--warp"], "unrecognized arguments"),
    ("ground", [*LISTEN, "--stream", "tcp:127.0.0.1:14599"], "udp:HOST:PORT"),
    ("ground", [*LISTEN, "--stream", "udp::14599"], "udp:HOST:PORT"),
    ("ground", [*LISTEN, "--stream", "udp:127.0.0.1:0"], "port"),
    ("ground", [*LISTEN, "--stream", "udp:127.0.0.1:70000"], "port"),
    ("ground", [*LISTEN, "--stream", "udp:192.0.2.1:14599"], "cannot listen", RUNTIME),  # not an address of ours
    ("ground", [*LISTEN, *LSTREAM, "--duration", "0"], "> 0"),
    ("ground", [*LISTEN, *LSTREAM, "--duration", "nan"], "finite"),
    ("ground", [*LISTEN, *LSTREAM, "--signing-key", "{d}/missing.key"], "does not exist", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--signing-key", "{d}/open.key"], "chmod 600", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--signing-key", "{d}/short.key"], "hex digits", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--signing-key", "{d}/adir.pslog"], "directory", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--allow-peer", "127.0.0.1:0"], "1-65535"),
    ("ground", [*LISTEN, *LSTREAM, "--allow-peer", ""], "allowed peer"),
    ("ground", [*LISTEN, *LSTREAM, "--allow-peer", "[::1"], "allowed peer"),
    ("ground", [*LISTEN, *LSTREAM, "--out", ""], "non-empty"),
    ("ground", [*LISTEN, *LSTREAM, "--web", "8080"], "--web must look like HOST:PORT"),
    ("ground", [*LISTEN, *LSTREAM, "--web", "127.0.0.1:70000"], "port must be 0-65535"),
    ("ground", [*LISTEN, *LSTREAM, "--web", "192.0.2.1:8080"], "cannot serve the live page", RUNTIME),  # not ours
    ("ground", [*LISTEN, *LSTREAM, "--out", "{d}/old.pslog"], "--force"),
    ("ground", [*LISTEN, *LSTREAM, "--out", "{d}/adir.pslog"], "is a directory"),
    ("ground", [*LISTEN, *LSTREAM, "--out", "{d}/blocker/x.pslog"], "does not exist"),
    ("ground", [*LISTEN, *LSTREAM, "--out", "{t}/no/such/dir/x.pslog"], "does not exist"),
    ("ground", [*LISTEN, *LSTREAM, "--header", "{d}/missing.json"], "cannot read", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--header", "{d}/adir.pslog"], "is a directory, not a regular file", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--header", "{d}/random.pslog"], "neither a sample log", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--header", "{d}/list-header.pslog"], "missing or corrupt", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--header", "{d}/list.json"], "JSON object", INPUT),
    ("ground", [*LISTEN, *LSTREAM, "--header", "{d}/layout.json"], "another layout", INPUT),
    # ----- pilescan-payload
    ("payload", ["--out"], "expected one argument"),
    ("payload", ["--out", "{t}/x.pslog", "--warp"], "unrecognized arguments"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--servo-rate", "inf"], "finite"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--servo-rate", "1e308"], "servo rate"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--duration", "inf"], "finite"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--lever-arm", "0", "0", "nan"], "finite"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--send-origin", "nan", "0", "0"], "finite"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--send-origin", "0", "0", "1e9"], "altitude"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--rate", "1e9"], "rate"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--phase", "-1"], "initial position"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--storage", "nanxnanxnan"], "storage"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", "serial:", "--i2c", "i2c:1"], "serial device path"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", "serial:/dev/ttyS0:10"], "baud"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", "udpout:127.0.0.1:0"], "port"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", "tcp: :5760"], "HOST:PORT"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", ""], "MAVLink URL"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", NOBODY, "--i2c", "i2c:"], "I2C bus URL"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", NOBODY, "--i2c", "i2c:١"], "I2C bus URL"),
    ("payload", ["--out", "{t}/x.pslog", "--mavlink", NOBODY, "--pwm", "pwm:"], "PWM output"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--stream", "udp:10.0.0.2:0"], "port"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--stream", "udp:10.0.0.2:70000"], "port"),
    ("payload", ["--out", "{t}/x.pslog", *PAY, "--mission-id", " "], "mission id"),
    ("payload", ["--out", "", *PAY], "non-empty"),
    ("payload", ["--out", "{d}/old.pslog", *PAY], "--force"),
    ("payload", ["--out", "{d}/adir.pslog", *PAY], "is a directory"),
    ("payload", ["--out", "{d}/blocker/x.pslog", *PAY], "does not exist"),
    ("payload", ["--out", "{t}/no/such/dir/x.pslog", *PAY], "does not exist"),
    # ----- python -m tools.reproduce
    ("reproduce", [*REP, "--warp"], "unrecognized arguments"),
    ("reproduce", [*REP, "--experiments", ""], "unknown experiment"),
    ("reproduce", [*REP, "--experiments", ",,"], "unknown experiment"),
    ("reproduce", [*REP, "--piles", "3"], "invalid choice"),
    ("reproduce", [*REP, "--p-traj", "nan"], "--p-traj"),
    ("reproduce", [*REP, "--p-traj", "x"], "invalid float"),
    ("reproduce", [*REP, "--p-traj"], "expected at least one argument"),
    ("reproduce", [*REP, "--positions", "21"], "servo positions"),
    ("reproduce", [*REP, "--jobs", "-3"], "--jobs"),
    ("reproduce", [*REP, "--config", "{d}/missing.toml"], "missing.toml"),
    ("reproduce", [*REP, "--config", "{d}/adir.toml"], "adir.toml"),
    ("reproduce", [*REP, "--config", "{d}/random.toml"], "random.toml"),
    ("reproduce", [*REP, "--config", "{d}/empty.toml"], "[[experiment]]"),
    ("reproduce", [*REP, "--config", "{d}/typed.toml"], "name"),
    ("reproduce", [*REP, "--config", "{d}/dup.toml"], "unique"),
    ("reproduce", [*REP, "--config", "{d}/noise-2d.toml"], "noise draws"),
    ("reproduce", [*REP, "--cache", "{d}/blocker/cache"], "Not a directory", RUNTIME),
    ("reproduce", [*REP, "--rows", "{d}/blocker/rows.csv"], "blocker", RUNTIME),
    ("reproduce", [*REP, "--rows", "{d}/adir.toml"], "is a directory"),
    ("reproduce", [*REP, "--write", "{d}/blocker/results.md"], "blocker", RUNTIME),
]


def run(capsys, prog: str, argv: list[str]) -> tuple[int, str, str]:
    code = MAINS[prog](argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def check_one_line_error(prog: str, code, err: str, expected: ExitCode = ExitCode.USAGE) -> None:
    assert code == expected, err
    assert err.count("\n") == 1 and err.endswith("\n"), err
    assert "Traceback" not in err
    assert err.startswith(PROGS[prog]) and ": error: " in err, err  # the same form for every program


@pytest.mark.parametrize(("prog", "argv", "words", "expected"), [(*c, ExitCode.USAGE)[:4] for c in CASES],
                         ids=[f"{c[0]}-{i:03d}-{' '.join(c[1])[:50]}" for i, c in enumerate(CASES)])
def test_that_a_bad_input_is_one_line_on_stderr_and_its_kinds_exit_code(inputs, tmp_path, monkeypatch, capsys, prog,
                                                                         argv, words, expected):
    monkeypatch.chdir(tmp_path)  # a bad case must not write into the repository
    argv = [a.format(d=inputs, t=tmp_path) for a in argv]
    code, out, err = run(capsys, prog, argv)
    check_one_line_error(prog, code, err, expected)
    assert out == ""
    assert words.lower() in err.lower()
    written = [p for p in tmp_path.rglob("*") if p.is_file() and p.relative_to(tmp_path).parts[0] != "s"]
    assert written == []


# ----- found by this walk and fixed: hardware and files are touched only after every option is checked ----

def test_that_a_malformed_pwm_url_is_named_before_any_hardware_is_opened(tmp_path, capsys):
    code, _, err = run(capsys, "payload", ["--out", str(tmp_path / "x.pslog"), *PAY, "--pwm", "pwm:sysfs:a:b"])
    check_one_line_error("payload", code, err)
    assert "pwm:sysfs:a:b" in err


@pytest.mark.parametrize("opt", ["--i2c", "--pwm"])
def test_that_an_empty_device_url_is_refused(tmp_path, capsys, opt):
    code, _, err = run(capsys, "payload", ["--out", str(tmp_path / "x.pslog"), "--mavlink", NOBODY, opt, ""])
    check_one_line_error("payload", code, err)
    assert "non-empty" in err


def test_that_listen_refuses_a_port_in_use_before_creating_its_log(tmp_path, capsys):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        code, _, err = run(capsys, "ground", [*LISTEN, "--stream", f"udp:127.0.0.1:{port}",
                                              "--out", str(tmp_path / "x.pslog")])
    check_one_line_error("ground", code, err, RUNTIME)
    assert "in use" in err and not (tmp_path / "x.pslog").exists()


def test_that_serve_refuses_a_bad_mavlink_url_before_writing_anything(tmp_path, capsys):
    code, _, err = run(capsys, "sitl", [*SERVE, "--mavlink", "udp:localhost:99999", "--out", str(tmp_path / "s")])
    check_one_line_error("sitl", code, err)
    assert not (tmp_path / "s").exists()
