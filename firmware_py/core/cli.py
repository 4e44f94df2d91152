"""Command-line plumbing shared by the three programs: one-line errors, distinct exit codes, logging
with -v/-q, no tracebacks.

Lives in firmware_py because every program may import it (the payload runs alone on the drone).

Exit codes (`ExitCode`, documented in the README): 0 ok, 2 usage (a bad option or option value, an
output that exists without --force; argparse's own 2), 3 input (a file the user named is unreadable
or invalid), 4 runtime (the run failed: an output could not be written, a device or port could not
be had, the vehicle did not finish, another process is writing the same folder), 5 no volume (the
report found no usable sample, so it has no volume to give), 130 interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import enum
import logging
import math
import re
import signal
import sys
from collections.abc import Callable, Iterator, Sequence


class ExitCode(enum.IntEnum):
    """What a program's exit status means; defined once, for the three programs and their tests."""

    OK = 0
    USAGE = 2  # argparse's own code for a bad command line, kept
    INPUT = 3
    RUNTIME = 4
    NO_VOLUME = 5
    INTERRUPTED = 130  # 128 + SIGINT, as a shell reports Ctrl-C


EXIT_USAGE = ExitCode.USAGE  # the name older code and tests use


class UserError(Exception):
    """A problem the user must fix, printed as one line; by default with the command line (exit 2).

    Subclasses say which other kind of failure it is. Raising one while handling an OSError says "the
    system refused" (a device, a port, a disk): a runtime failure (exit 4), see `exit_code_of`.
    """

    exit_code: ExitCode = ExitCode.USAGE


class InputError(UserError):
    """A file the user named is unreadable or invalid (exit 3)."""

    exit_code = ExitCode.INPUT


class RunFailure(UserError):
    """The run itself failed (exit 4): an output that cannot be written, a busy folder, a flight not finished."""

    exit_code = ExitCode.RUNTIME


class NoVolumeError(UserError):
    """The report found nothing to build a surface from, so it has no volume to give (exit 5)."""

    exit_code = ExitCode.NO_VOLUME


def one_line(exc: BaseException) -> str:
    """The first line of an exception's message, or its type's name when it has none."""
    return str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__


def exit_code_of(exc: BaseException) -> ExitCode:
    """The exit code a user-facing failure maps to (UserError subclasses carry theirs).

    ValueError is what the configuration dataclasses raise for a bad option value: usage. A bare
    OSError is the system refusing a write, a socket or a device: runtime. A plain UserError raised
    from, or while handling, an OSError describes such a refusal in the user's terms ("cannot listen
    on ...: Address already in use"): runtime too. Input files are read inside `reading_input`,
    whose InputError keeps its 3.
    """
    if isinstance(exc, UserError):
        during = exc.__cause__ if exc.__cause__ is not None else exc.__context__
        if type(exc) is UserError and isinstance(during, OSError):
            return ExitCode.RUNTIME
        return exc.exit_code
    if isinstance(exc, OSError):
        return ExitCode.RUNTIME
    return ExitCode.USAGE


@contextlib.contextmanager
def reading_input(what: str | None = None) -> Iterator[None]:
    """Errors raised inside (reading a file the user named) become InputError: exit 3, one line.

    `what` prefixes the message when the error does not already name the file.
    """
    try:
        yield
    except InputError:
        raise
    except (UserError, ValueError, OSError, UnicodeDecodeError) as exc:
        msg = one_line(exc)
        if what is not None and what.lstrip("-").lower() not in msg.lower():
            msg = f"{what}: {msg}"
        raise InputError(msg) from exc


_NEGATIVE_NUMBERS = re.compile(r"^-\d+$|^-\d*\.\d+$|^-\d*\.?\d*(,[-+]?\d*\.?\d*)+$")
"""argparse's own negative-number pattern, and comma-separated lists of numbers starting with a minus."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a bad option as one line (no usage dump) and exits with 2.

    A value that starts with a minus sign and lists numbers (`--origin -33.9,151.2,30`) is a value, as
    a plain negative number is: argparse alone would take it for an unknown option.
    """

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = _NEGATIVE_NUMBERS


    def error(self, message: str):  # type: ignore[override]
        self.exit(ExitCode.USAGE, f"{self.prog}: error: {message}\n")


def finite_float(text: str) -> float:
    """argparse type: a finite float (NaN and inf are refused with a clear message)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


# ----- logging ------------------------------------------------------------------------------------

def add_verbosity(parser: argparse.ArgumentParser, *, sub: bool = False,
                  quiet_help: str = "only warnings and errors") -> None:
    """-v/--verbose (debug messages too) and -q/--quiet (no progress) on parser.

    On the program's parser and on each subcommand's (sub=True), so `prog -v fly` and `prog fly -v`
    both work: a subcommand's defaults are SUPPRESSed so they do not undo the program-level flag.
    """
    default = argparse.SUPPRESS if sub else False
    parser.add_argument("-v", "--verbose", action="store_true", default=default,
                        help="also print debug messages")
    parser.add_argument("-q", "--quiet", action="store_true", default=default, help=quiet_help)


OUR_PACKAGES = ("firmware_py", "sitl", "ground", "tools")
"""The loggers -v and -q act on (their modules log with `logging.getLogger(__name__)`)."""


class _StderrHandler(logging.StreamHandler):
    """A handler writing to whatever sys.stderr is when a record is emitted (tests swap it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, _value) -> None:
        pass


class _ProgFormatter(logging.Formatter):
    """`PROG: message`, `PROG: warning: message`, `PROG: debug: logger: message`: the programs' one-line form."""

    def __init__(self, prog: str) -> None:
        super().__init__()
        self.prog = prog

    def format(self, record: logging.LogRecord) -> str:
        msg = record.getMessage()
        if record.exc_info and record.levelno >= logging.ERROR:
            msg = f"{msg}: {one_line(record.exc_info[1])}" if record.exc_info[1] is not None else msg
        if record.levelno >= logging.ERROR:
            return f"{self.prog}: error: {msg}"
        if record.levelno >= logging.WARNING:
            return f"{self.prog}: warning: {msg}"
        if record.levelno >= logging.INFO:
            return f"{self.prog}: {msg}"
        return f"{self.prog}: debug: {record.name}: {msg}"


def configure_logging(prog: str, *, verbose: bool = False, quiet: bool = False) -> Callable[[], None]:
    """Route the standard library's logging to stderr in the programs' form; returns the undo.

    Called once per program run (by `run_cli`, which undoes it when the program returns, so `main()`
    called from tests or tools leaves logging as it found it). -q: warnings and errors only; -v: debug.
    Only our packages' loggers follow -v/-q; other libraries' stay at warnings.
    """
    if verbose and quiet:
        raise UserError("-v/--verbose and -q/--quiet exclude each other")
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    root = logging.getLogger()
    ours = [logging.getLogger(p) for p in OUR_PACKAGES]
    before = (root.level, [lg.level for lg in ours])
    handler = _StderrHandler()
    handler.setFormatter(_ProgFormatter(prog))
    root.addHandler(handler)
    if root.level == logging.NOTSET or root.level > logging.WARNING:
        root.setLevel(logging.WARNING)  # other libraries' chatter (matplotlib, trimesh): warnings only
    for lg in ours:
        lg.setLevel(level)

    def undo() -> None:
        root.removeHandler(handler)
        root.setLevel(before[0])
        for lg, lv in zip(ours, before[1], strict=True):
            lg.setLevel(lv)
    return undo


def run_cli(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
            body: Callable[[argparse.Namespace], int]) -> int:
    """Parse argv, set up logging (-v/-q) and run body(args), turning user-facing failures into one line
    on stderr and their `ExitCode`.

    Returns the exit code instead of raising SystemExit, so `main(argv)` is callable from tests.
    """
    prog = parser.prog
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a bad option already reported in one line
        return exc.code if isinstance(exc.code, int) else ExitCode.USAGE
    undo = None
    try:
        undo = configure_logging(prog, verbose=bool(getattr(args, "verbose", False)),
                                 quiet=bool(getattr(args, "quiet", False)))
        return int(body(args))
    except (UserError, ValueError, OSError) as exc:  # OSError: missing file, disk full, permission...
        print(f"{prog}: error: {one_line(exc)}", file=sys.stderr)
        return int(exit_code_of(exc))
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return int(ExitCode.INTERRUPTED)
    finally:
        if undo is not None:
            undo()


@contextlib.contextmanager
def stop_on_signals(stop: Callable[[str], None],
                    signums: Sequence[int] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Route the signals to stop(reason) while inside, restoring the previous handlers after.

    Here (not in a program's cli) so the payload and the ground station's `listen` share it without
    the ground importing the payload program.
    """
    def handler(signum: int, _frame: object) -> None:
        stop(f"signal {signal.Signals(signum).name}")

    previous = {}
    try:
        for s in signums:
            previous[s] = signal.signal(s, handler)
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
