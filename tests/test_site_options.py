"""--origin LAT,LON,ALT and --heading DEG on `pilescan-sitl plan | serve | fly` and `pilescan-payload`: a bad
value is one line on stderr and exit 2, before anything is flown, served, opened or written."""

from __future__ import annotations

import pytest

from tests.test_cli_bad_inputs import FLY, NOBODY, SERVE, check_one_line_error, run

PLAN = ["plan", "--p-traj", "20", "--out", "{t}/p.waypoints"]
PAY = ["--mavlink", NOBODY, "--i2c", "i2c:/dev/i2c-nonexistent-77", "--out", "{t}/s.pslog"]
BAD = [  # (option value(s), words the one line must hold)
    (["--origin", "91,0,0"], "latitude"),
    (["--origin=-90,0,0"], "latitude"),
    (["--origin", "0,180.5,0"], "longitude"),
    (["--origin=-33.9,-181,30"], "longitude"),
    (["--origin", "nan,0,0"], "finite"),
    (["--origin", "0,inf,0"], "finite"),
    (["--origin", "0,0,1e6"], "altitude"),
    (["--origin", "1,2"], "LAT,LON,ALT"),
    (["--origin", "1,2,3,4"], "LAT,LON,ALT"),
    (["--origin", "north,2,3"], "latitude is not a number"),
    (["--origin"], "expected one argument"),
    (["--heading", "361"], "+-360"),
    (["--heading=-400"], "+-360"),
    (["--heading", "nan"], "finite"),
    (["--heading", "inf"], "finite"),
    (["--heading", "east"], "not a number"),
]
COMMANDS = {"plan": ("sitl", PLAN), "serve": ("sitl", [*SERVE, "--out", "{t}/s"]),
            "fly": ("sitl", [*FLY, "--out", "{t}/run"]), "payload": ("payload", PAY)}


@pytest.mark.parametrize(("value", "words"), BAD, ids=[" ".join(v) for v, _ in BAD])
@pytest.mark.parametrize("command", list(COMMANDS))
def test_that_a_bad_site_option_is_one_line_and_exit_2_before_anything_happens(tmp_path, monkeypatch, capsys,
                                                                                command, value, words):
    monkeypatch.chdir(tmp_path)
    prog, argv = COMMANDS[command]
    code, out, err = run(capsys, prog, [a.format(t=tmp_path) for a in argv] + value)
    check_one_line_error(prog, code, err)
    assert words.lower() in err.lower() and out == ""
    assert [p for p in tmp_path.rglob("*") if p.is_file()] == []
