"""Bounded, type-checked reads of the files the programs are given.

Every file a user names (a sample log, truth.json, a JSON header, a mesh) is read through here, so a
wrong path cannot hang a program or exhaust its memory, and a hostile JSON cannot crash it:

- only regular files are read: a FIFO would block forever, /dev/zero or /dev/urandom never end;
  the file is opened non-blocking (so opening a FIFO cannot block either) and checked with fstat on
  the open descriptor (no race between the check and the read);
- the size is checked against a limit before anything is read, and at most limit + 1 bytes are
  read (a file growing during the read is refused, not followed);
- JSON is decoded strictly: UTF-8 (a BOM tolerated), no NaN/Infinity, nesting at most
  MAX_JSON_DEPTH levels (counted before decoding, so no RecursionError anywhere later), and
  helpers that type-check values (a JSON ``true`` is not the number 1).

Failures raise `InputError` (a ValueError) with one line naming the file and what is wrong.
Standard library only: `firmware_py.core` is imported by every program, the payload included.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any

from firmware_py.core.numbers import is_finite_number

MAX_JSON_BYTES = 16 * 1024 * 1024
"""Largest JSON file read (truth.json, headers, reports are kilobytes; a mission of 10,000 waypoints
is about a megabyte)."""
MAX_JSON_DEPTH = 64
"""Deepest JSON nesting accepted: the deepest file pilescan writes nests 4 levels."""


class InputError(ValueError):
    """A file given to a program is unusable: one line naming the file and why."""


def read_bounded(path: str | os.PathLike[str], max_bytes: int, what: str = "file") -> bytes:
    """All bytes of a regular file of at most max_bytes.

    Raises:
        InputError: not a regular file (FIFO, device, directory, socket), or larger than max_bytes.
        OSError: missing, unreadable (the caller names it as it likes).
    """
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 0:
        raise ValueError(f"max_bytes must be an int >= 0, got {max_bytes!r}")
    fd = os.open(os.fspath(path), os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{what} {path} is {_kind(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise InputError(f"{what} {path} is {st.st_size:,} bytes, more than the {max_bytes:,} byte limit")
        chunks: list[bytes] = []
        got = 0
        while got <= max_bytes:
            chunk = os.read(fd, min(max_bytes + 1 - got, 1 << 24))
            if not chunk:
                break
            chunks.append(chunk)
            got += len(chunk)
        if got > max_bytes:
            raise InputError(f"{what} {path} grew past the {max_bytes:,} byte limit while being read")
        return b"".join(chunks)
    finally:
        os.close(fd)


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


def json_depth_exceeds(text: str, max_depth: int) -> bool:
    """True when brackets outside strings nest deeper than max_depth (a linear scan, no recursion)."""
    depth = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            if depth > max_depth:
                return True
        elif ch in "]}":
            depth -= 1
    return False


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def parse_json(data: bytes | str, where: str, max_depth: int = MAX_JSON_DEPTH) -> Any:
    """Strict JSON from bytes or text; InputError naming `where` on anything else."""
    if isinstance(data, bytes | bytearray | memoryview):
        try:
            text = bytes(data).decode("utf-8-sig")
        except UnicodeDecodeError as exc:
            raise InputError(f"{where} is not UTF-8 text (byte {exc.start})") from None
    else:
        text = data
    if json_depth_exceeds(text, max_depth):
        raise InputError(f"{where} nests JSON deeper than {max_depth} levels")
    try:
        return json.loads(text, parse_constant=_refuse_constant)
    except RecursionError:  # not reachable after the depth scan; kept so no traceback can leak
        raise InputError(f"{where} nests JSON too deeply") from None
    except ValueError as exc:
        raise InputError(f"{where} is not valid JSON: {str(exc).splitlines()[0]}") from None


def load_json(path: str | os.PathLike[str], what: str = "JSON file", max_bytes: int = MAX_JSON_BYTES,
              max_depth: int = MAX_JSON_DEPTH) -> Any:
    """A JSON file, read bounded (`read_bounded`) and decoded strictly (`parse_json`).

    Raises:
        InputError: not a regular file, too large, not UTF-8, not JSON, too deep.
        OSError: missing or unreadable.
    """
    return parse_json(read_bounded(path, max_bytes, what), f"{what} {Path(path)}", max_depth)


def json_object(value: Any, where: str) -> dict[str, Any]:
    """value, which must be a JSON object."""
    if not isinstance(value, dict):
        raise InputError(f"{where} must be a JSON object, got {_json_type(value)}")
    return value


def json_number(value: Any, where: str, *, minimum: float | None = None, positive: bool = False) -> float:
    """value as a finite float; JSON booleans are refused (True is not 1 m)."""
    kind = "a positive number" if positive else "a finite number"
    if not is_finite_number(value):
        raise InputError(f"{where} must be {kind}, got {_json_type(value)} {value!r}")
    v = float(value)
    if positive and v <= 0:
        raise InputError(f"{where} must be {kind}, got {v:g}")
    if minimum is not None and v < minimum:
        raise InputError(f"{where} must be >= {minimum:g}, got {v:g}")
    return v


def _json_type(value: Any) -> str:
    return {bool: "a boolean", type(None): "null", str: "a string", list: "an array", dict: "an object",
            int: "a number", float: "a number"}.get(type(value), type(value).__name__)
