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
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import Any

from firmware_py.core.config_file import ConfigError, key_label, load_config
from firmware_py.core.sensor import Rangefinder


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
    details: tuple[str, ...] = ()
    """Further problems, one line each, printed after the message (a configuration file's other bad keys)."""


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

def rangefinder_arg(text: str) -> Rangefinder:
    """argparse type of --rangefinder (the payload's and the SITL's): the Rangefinder named, or its error."""
    try:
        return Rangefinder.named(text.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


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


def config_keys_of(args: argparse.Namespace, applied: list[tuple[str, str, Any]]) -> dict[str, str]:
    """{dest: configuration key} of the options whose value is still the file's (the command line did not
    give them): the very object `apply_config` made the default."""
    return {dest: key for dest, key, value in applied if getattr(args, dest, None) is value}


def parse_with_config(parser: argparse.ArgumentParser, argv: Sequence[str],
                      tables: ConfigTables) -> argparse.Namespace:
    """What `run_cli` parses: the --config file's defaults applied, then argv (SystemExit on a bad option,
    ConfigError / InputError on a bad file); for tests and tools that parse without running."""
    applied = apply_config(parser, argv, tables)
    args = parser.parse_args(list(argv))
    args.config_keys = config_keys_of(args, applied)
    return args


def _print_error(prog: str, exc: BaseException) -> int:
    print(f"{prog}: error: {one_line(exc)}", file=sys.stderr)
    for line in getattr(exc, "details", ()):
        print(f"{prog}: error: {line}", file=sys.stderr)
    return int(exit_code_of(exc))


def run_cli(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
            body: Callable[[argparse.Namespace], int], config: ConfigTables | None = None) -> int:
    """Parse argv, set up logging (-v/-q) and run body(args), turning user-facing failures into one line
    on stderr and their `ExitCode`.

    With `config` (which configuration key sets which option, per subcommand: `apply_config`), a
    `--config FILE` in argv is read first and its keys become the options' defaults; the body then
    finds the file as `args.config_file` (None without one) and which options it set as
    `args.config_keys` ({dest: key}: those the command line did not override).

    Returns the exit code instead of raising SystemExit, so `main(argv)` is callable from tests.
    """
    prog = parser.prog
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        applied = apply_config(parser, argv, config) if config is not None else []
    except (UserError, ValueError, OSError) as exc:
        return _print_error(prog, exc)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a bad option already reported in one line
        return exc.code if isinstance(exc.code, int) else ExitCode.USAGE
    if config is not None:
        args.config_keys = config_keys_of(args, applied)
    undo = None
    try:
        undo = configure_logging(prog, verbose=bool(getattr(args, "verbose", False)),
                                 quiet=bool(getattr(args, "quiet", False)))
        for note in getattr(args, "config_notes", ()):
            logging.getLogger(__name__).warning("%s", note)
        return int(body(args))
    except (UserError, ValueError, OSError) as exc:  # OSError: missing file, disk full, permission...
        return _print_error(prog, exc)
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


# ----- the configuration file (firmware_py.core.config_file) ----------------------------------------

ConfigTables = Mapping[str | None, Mapping[str, str]]
"""Per (sub)command (None: the program's own parser; else the subcommand's name): configuration key
("payload.rate_hz") -> the option it sets ("--rate"). A key may name an option the parser does not have
(yet): the program then says, once, that it does not use it."""

CONFIG_HELP = ("TOML configuration file (docs/configuration.md): the keys it sets become the defaults of the "
               "options they map to; an option given on the command line still wins")


def add_config_option(parser: argparse.ArgumentParser, *, sub: bool = False) -> None:
    """--config FILE on parser (and on each subcommand's, sub=True, so it may come before or after the
    subcommand). The file is read before parsing (`run_cli`); the option is here for --help and so the
    parser accepts it."""
    parser.add_argument("--config", default=argparse.SUPPRESS if sub else None, metavar="FILE", help=CONFIG_HELP)


class _NoExit(Exception):
    pass


class _PreParser(argparse.ArgumentParser):
    def error(self, message: str):  # type: ignore[override]
        raise _NoExit(message)


def config_path_in(argv: Sequence[str]) -> str | None:
    """The --config FILE in argv (the last one), None without one; a malformed --config is left for the
    real parser to report."""
    pre = _PreParser(add_help=False)
    pre.add_argument("--config", default=None)
    try:
        ns, _ = pre.parse_known_args(list(argv))
    except _NoExit:
        return None
    return ns.config


def _subparser(parser: argparse.ArgumentParser, name: str | None) -> argparse.ArgumentParser:
    if name is None:
        return parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and name in action.choices:
            return action.choices[name]
    raise KeyError(f"{parser.prog} has no subcommand {name!r}")


def option_action(parser: argparse.ArgumentParser, option: str) -> argparse.Action | None:
    """The parser's action for an option string ("--rate"), or None."""
    return parser._option_string_actions.get(option)


def _tokens(value: Any, action: argparse.Action) -> list[str]:
    """A typed configuration value as the words one would type after the option."""
    if isinstance(value, enum.Enum):
        value = value.value
    if isinstance(value, tuple | list):
        words = [repr(float(v)) if isinstance(v, float) else str(v) for v in value]
        return words if isinstance(action.nargs, int) or action.nargs in ("+", "*") else [",".join(words)]
    return [repr(value) if isinstance(value, float) else str(value)]


def option_default(action: argparse.Action, value: Any) -> Any:
    """The value parsing the configuration value's words with the option's own type would give.

    Raises:
        ValueError: the option's type or choices refuse it (the message says why).
    """
    if action.nargs == 0:  # store_true / store_false
        if not isinstance(value, bool):
            raise ValueError(f"must be true or false, got {value!r}")
        return value if action.const is True else not value
    convert = action.type if callable(action.type) else (lambda text: text)
    try:
        words = _tokens(value, action)
        out = [convert(w) for w in words]
    except (argparse.ArgumentTypeError, TypeError, ValueError) as exc:
        raise ValueError(one_line(exc)) from None
    for v in out:
        if action.choices is not None and v not in action.choices:
            raise ValueError(f"must be one of {', '.join(map(str, action.choices))}, got {v!r}")
    if isinstance(action.nargs, int) or action.nargs in ("+", "*"):
        if isinstance(action.nargs, int) and len(out) != action.nargs:
            raise ValueError(f"must be {action.nargs} values, got {len(out)}")
        return out
    return out[0]


def _key_where(source: str, key: str) -> str:
    return f"{source}: {key_label(key)}"


def apply_config(parser: argparse.ArgumentParser, argv: Sequence[str],
                 tables: ConfigTables) -> list[tuple[str, str, Any]]:
    """Read the --config FILE named in argv (if any) and make its keys the defaults of the options they
    map to (`ConfigTables`), on the program's parser and its subcommands'. An option the file supplies is
    no longer required. Each (sub)parser also gets `config_file` (the `ConfigFile`, None without one) and
    `config_notes` (keys it does not use for want of the option) as defaults.

    Returns:
        (dest, key, default object) of every option set, so `run_cli` can tell which ones the command
        line left to the file (identity with the default).

    Raises:
        ConfigError: a bad file (every problem, one line each), or a value an option's type refuses
            (naming the key): exit 2. InputError: the file cannot be read (exit 3).
    """
    path = config_path_in(argv)
    for sub in tables:
        _subparser(parser, sub).set_defaults(config_file=None, config_notes=())
    if path is None:
        return []
    problems: list[str] = []
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        if exc.config is None:  # not TOML: no key to check further
            raise
        # the file's own problems, and then the options' checks of the keys that passed: one report of all
        cfg, problems = exc.config, list(exc.problems)
    except (OSError, ValueError) as exc:  # cannot be read at all: an input error (exit 3)
        raise InputError(one_line(exc)) from exc
    applied: list[tuple[str, str, Any]] = []
    for sub, table in tables.items():
        p = _subparser(parser, sub)
        defaults: dict[str, Any] = {}
        notes = []
        for key, option in table.items():
            value = cfg.get(key)
            if value is None:
                continue
            action = option_action(p, option)
            if action is None:
                notes.append(f"{_key_where(path, key)}: not used: {p.prog} has no {option} option")
                continue
            try:
                defaults[action.dest] = option_default(action, value)
            except ValueError as exc:
                problems.append(f"{_key_where(path, key)}: {exc}")
                continue
            action.required = False
            applied.append((action.dest, key, defaults[action.dest]))
        p.set_defaults(**defaults, config_file=cfg, config_notes=tuple(notes))
    if problems:
        raise ConfigError(sorted(set(problems), key=problems.index))
    return applied
