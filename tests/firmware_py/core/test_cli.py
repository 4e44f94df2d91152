"""The shared command-line conventions: one exit code per kind of failure, logging configured once with -v/-q."""

from __future__ import annotations

import logging

import pytest

from firmware_py.core.cli import (
    ArgumentParser,
    ExitCode,
    InputError,
    NoVolumeError,
    RunFailure,
    UserError,
    add_verbosity,
    exit_code_of,
    reading_input,
    run_cli,
)


def test_that_the_exit_codes_are_distinct_and_keep_argparses_2():
    assert [int(c) for c in ExitCode] == [0, 2, 3, 4, 5, 130]
    assert ExitCode.USAGE == 2


@pytest.mark.parametrize(("exc", "code"), [
    (UserError("bad option"), ExitCode.USAGE),
    (ValueError("seed must be >= 0"), ExitCode.USAGE),
    (InputError("x.pslog: header corrupt"), ExitCode.INPUT),
    (RunFailure("the vehicle did not complete the mission"), ExitCode.RUNTIME),
    (NoVolumeError("no surface"), ExitCode.NO_VOLUME),
    (OSError(28, "No space left on device"), ExitCode.RUNTIME),
])
def test_that_each_kind_of_failure_maps_to_its_code(exc, code):
    assert exit_code_of(exc) == code


def test_that_a_user_error_raised_from_an_os_error_is_a_runtime_failure():
    try:
        try:
            raise ConnectionRefusedError(111, "Connection refused")
        except OSError as cause:
            raise UserError("cannot open I2C bus tcp:127.0.0.1:9: Connection refused") from cause
    except UserError as exc:
        assert exit_code_of(exc) == ExitCode.RUNTIME
    try:
        try:
            raise OSError(98, "Address already in use")
        except OSError as exc:
            raise UserError(f"cannot listen on udp:127.0.0.1:14600: {exc.strerror}") from None
    except UserError as exc:
        assert exit_code_of(exc) == ExitCode.RUNTIME


def test_that_errors_while_reading_an_input_become_input_errors_naming_it():
    with pytest.raises(InputError, match=r"^--stockpile: no triangles$"):
        with reading_input("--stockpile"):
            raise ValueError("no triangles")
    with pytest.raises(InputError, match=r"^stockpile mesh x\.stl not found$"):
        with reading_input("--stockpile"):
            raise ValueError("stockpile mesh x.stl not found")  # already names it: no prefix
    with pytest.raises(InputError):
        with reading_input():
            raise FileNotFoundError(2, "No such file or directory", "x.pslog")


def _program(body):
    ap = ArgumentParser(prog="prog")
    add_verbosity(ap)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    add_verbosity(sub.add_parser("go"), sub=True)
    return lambda argv: run_cli(ap, argv, body)


def _chatty(_args) -> int:
    log = logging.getLogger("sitl.some.module")
    log.debug("detail")
    log.info("progress")
    log.warning("careful")
    return 0


@pytest.mark.parametrize(("argv", "lines"), [
    (["go"], ["prog: progress", "prog: warning: careful"]),
    (["go", "-q"], ["prog: warning: careful"]),
    (["-q", "go"], ["prog: warning: careful"]),
    (["go", "-v"], ["prog: debug: sitl.some.module: detail", "prog: progress", "prog: warning: careful"]),
    (["-v", "go"], ["prog: debug: sitl.some.module: detail", "prog: progress", "prog: warning: careful"]),
])
def test_that_v_shows_debug_and_q_silences_info_at_either_level(capsys, argv, lines):
    assert _program(_chatty)(argv) == 0
    assert capsys.readouterr().err.splitlines() == lines


def test_that_v_and_q_together_are_a_usage_error(capsys):
    assert _program(_chatty)(["go", "-v", "-q"]) == ExitCode.USAGE
    assert capsys.readouterr().err == "prog: error: -v/--verbose and -q/--quiet exclude each other\n"


def test_that_other_libraries_info_stays_quiet(capsys):
    def body(_args) -> int:
        logging.getLogger("matplotlib.font_manager").info("font cache built")
        return 0
    assert _program(body)(["go", "-v"]) == 0
    assert capsys.readouterr().err == ""


def test_that_a_program_run_leaves_logging_as_it_found_it(capsys):
    root, sitl = logging.getLogger(), logging.getLogger("sitl")
    before = (list(root.handlers), root.level, sitl.level)
    prog = _program(_chatty)
    prog(["go", "-v"])
    prog(["go"])
    assert capsys.readouterr().err.count("progress") == 2  # one handler per run, not stacked
    assert (list(root.handlers), root.level, sitl.level) == before
