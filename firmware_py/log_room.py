"""Where the sample log goes: checked before anything is opened, and how long its file system's free space lasts.

A payload started flight after flight by a service fills its card with logs (`--out` with `{utc}` in it). Until
now nothing said before a flight that the card was nearly full: the log stopped in the air with "No space left on
device". And a log whose directory could not be written failed only after the pose wait, up to a minute in, and
`--check` did not look at the log at all.

- `check_destination`: the log can be written (its directory exists and is writable; it does not exist yet, or
  `--force`), in `--check` and at start before any hardware is opened.
- `room_s`: how many seconds of samples the free space holds at the sample rate (records and block frames).
- `room_warning`: at start (console and a STATUSTEXT) and in `--check`, when that is less than `--duration`, or,
  without one, less than LOW_ROOM_S.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from firmware_py.core.cli import UserError
from firmware_py.core.samplelog import HEAD_SIZE, SAMPLE_DTYPE

LOW_ROOM_S = 1800.0
"""Without --duration, warn below half an hour of samples: longer than a 450-class quadcopter flies on one battery
(15-20 min), so a whole flight fits with room to spare; a fuller card is worth clearing before the flight."""


def log_bytes_per_s(rate_hz: float, records_per_block: int) -> float:
    """What the log grows by per second: the records and each block's frame (magic, kind, length, CRC)."""
    per_record = SAMPLE_DTYPE.itemsize + HEAD_SIZE / max(records_per_block, 1)
    return per_record * rate_hz


def check_destination(out: Path, force: bool) -> None:
    """UserError (one line) unless the log can be written at out: a file that is not there yet (or force), in a
    directory that exists and that this process may write."""
    out = Path(out)
    if out.is_dir():
        raise UserError(f"cannot write {out}: it is a directory; --out names the sample log file")
    if out.exists() and not force:
        raise UserError(f"{out} already exists; choose another --out or pass --force")
    parent = out.parent
    if not parent.is_dir():
        raise UserError(f"cannot write {out}: directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"cannot write {out}: no permission to create files in {parent}")


def room_s(out: Path, rate_hz: float, records_per_block: int) -> float | None:
    """Seconds of samples the free space of out's file system holds (None: the file system does not say)."""
    try:
        free = shutil.disk_usage(Path(out).parent).free
    except OSError:
        return None
    return free / log_bytes_per_s(rate_hz, records_per_block)


def describe_room(room: float) -> str:
    """'2 h 05 min' or '12 min' or '40 s'."""
    if room >= 3600:
        hours, rest = divmod(int(room), 3600)
        return f"{hours} h {rest // 60:02d} min"
    return f"{int(room // 60)} min" if room >= 60 else f"{room:.0f} s"


def room_warning(room: float | None, duration_s: float | None, rate_hz: float) -> str | None:
    """A warning when the free space holds less than the flight (--duration) or, without one, LOW_ROOM_S."""
    if room is None:
        return None
    need, what = (duration_s, "the --duration") if duration_s else (LOW_ROOM_S, "half an hour")
    if room >= need:
        return None
    return (f"the log's file system has room for {describe_room(room)} of samples at {rate_hz:g} Hz, less than "
            f"{what} ({describe_room(need)}): free some space (old logs?) before the flight, or the log stops when "
            "it is full")
