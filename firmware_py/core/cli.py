"""Command-line plumbing shared by the three programs: one-line errors, exit code 2, no tracebacks.

Lives in firmware_py because every program may import it (the payload runs alone on the drone).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
from collections.abc import Callable, Iterator, Sequence

EXIT_USAGE = 2


class UserError(Exception):
    """A problem with what the user gave us: printed as one line, exit code 2."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports a bad option as one line (no usage dump) and exits with 2."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")


def finite_float(text: str) -> float:
    """argparse type: a finite float (NaN and inf are refused with a clear message)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text!r}")
    return v


def run_cli(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
            body: Callable[[argparse.Namespace], int]) -> int:
    """Parse argv and run body(args), turning user-facing failures into one line on stderr and exit 2.

    Returns the exit code instead of raising SystemExit, so `main(argv)` is callable from tests.
    """
    prog = parser.prog
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a bad option already reported in one line
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    try:
        return body(args)
    except (UserError, ValueError, OSError) as exc:  # OSError: missing file, disk full, permission...
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130


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
