"""MAVLink signing keys and timestamps, shared by every program that signs or authenticates.

Key file (`load_key`), one of:

- 64 hex digits: the 32-byte secret key itself (e.g. from `openssl rand -hex 32`), upper or lower case;
- one line of passphrase: the key is SHA-256 of its UTF-8 bytes, as MAVProxy's
  `signing setup PASSPHRASE` derives it, so the same passphrase keys MAVProxy, ArduPilot
  (through MAVProxy's SETUP_SIGNING) and us (MAVProxy takes an ASCII passphrase without spaces).
  A passphrase must be at least 8 characters and contain a non-hex character (anything made only
  of hex digits is read as a hex key and must then have exactly 64 of them: a typo'd key is
  refused, not hashed).

Parsing is strict, because a key read wrongly does not fail: it silently becomes another key and
the peers simply stop hearing each other. Accepted: surrounding whitespace and one line ending
(LF or CRLF). Refused, in one line naming the problem: a UTF-8 byte-order mark (an editor's, never
part of a passphrase MAVProxy would see); and a line that is a hex key once decorated with a `0x`
prefix, a trailing `# comment`, or whitespace between the digits (such a line is not a passphrase
anyone meant: taken as one, it would hash to a key no peer has).

Permissions (POSIX, the rules ssh applies to its private keys): the key file must not be readable
or writable by everyone (mode 600 or 640), must not be group-writable, and must belong to us or to
root; its folder must not be group- or world-writable, and no folder above it may be writable by
others unless it has the sticky bit (as /tmp has): whoever can write the folder can swap the key.
Each is REFUSED, not warned about: a key others can read or replace authenticates nothing. An
all-zero key is refused (MAVLink's "signing off").

The same key file keys the payload's MAVLink link, the device bridge and the live sample stream,
so the ground station's `listen` loads it too: that is why it lives with the shared contracts.
"""

from __future__ import annotations

import hashlib
import os
import stat
import string

KEY_SIZE = 32
SIGNING_EPOCH_UNIX_S = 1_420_070_400  # 2015-01-01T00:00:00Z
TIMESTAMP_UNITS_PER_S = 100_000  # 10 us
TIMESTAMP_MAX = (1 << 48) - 1
MIN_PASSPHRASE_LEN = 8
_HEX = frozenset(string.hexdigits)


def key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte key for a passphrase: SHA-256 of its UTF-8 bytes (MAVProxy's `signing setup`)."""
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


_BOM = "\ufeff"
_GROUP_OR_OTHER_WRITE = stat.S_IWGRP | stat.S_IWOTH


def _hex_decoration(line: str) -> str | None:
    """What turns a 64-hex-digit key into something else, if `line` is such a key decorated; else None.

    Only the decorations people actually add: a `0x` prefix, a trailing `# comment`, whitespace
    between digit groups. The digits left after removing them must all be hex (any count: a
    decorated 63-digit key is named as such too, not hashed as a passphrase)."""
    found = []
    body = line
    if "#" in body:
        body = body.split("#", 1)[0]
        found.append("a trailing comment")
    body = body.strip()
    if body[:2].lower() == "0x":
        body = body[2:]
        found.append("a 0x prefix")
    if any(c.isspace() for c in body):
        body = "".join(body.split())
        found.append("whitespace between the digits")
    if not found or not body or not all(c in _HEX for c in body):
        return None
    digits = "" if len(body) == 2 * KEY_SIZE else f" (and {len(body)} hex digits, not {2 * KEY_SIZE})"
    return " and ".join(found) + digits


def parse_key_text(text: str, where: str = "signing key") -> bytes:
    """The key in a key file's text (module docstring); ValueError (one line) if there is none."""
    if text.startswith(_BOM):
        raise ValueError(f"{where} starts with a byte-order mark (BOM, an editor's addition): save it as plain "
                         f"UTF-8 without one")
    lines = [ln.strip() for ln in text.strip().splitlines()]
    if not lines or not lines[0]:
        raise ValueError(f"{where} is empty (put 64 hex digits or a passphrase in it)")
    if len(lines) > 1:
        raise ValueError(f"{where} must hold one line (64 hex digits or a passphrase), found {len(lines)}")
    line = lines[0]
    if all(c in _HEX for c in line):
        if len(line) != 2 * KEY_SIZE:
            raise ValueError(f"{where} holds {len(line)} hex digits; a hex key needs exactly {2 * KEY_SIZE} "
                             f"(a passphrase must contain a non-hex character)")
        key = bytes.fromhex(line)
    else:
        decoration = _hex_decoration(line)
        if decoration is not None:
            raise ValueError(f"{where} holds a hex key with {decoration}: write the {2 * KEY_SIZE} hex digits "
                             f"alone on the line (taken as a passphrase it would be another key)")
        if len(line) < MIN_PASSPHRASE_LEN:
            raise ValueError(f"{where}: passphrase is shorter than {MIN_PASSPHRASE_LEN} characters")
        key = key_from_passphrase(line)
    if not any(key):
        raise ValueError(f"{where} is all zeros (MAVLink's 'signing disabled' key)")
    return key


def _trusted_owner(uid: int) -> bool:
    return uid in (0, os.geteuid())


def check_key_permissions(path: str | os.PathLike[str], st: os.stat_result, where: str) -> None:
    """Refuse (ValueError, one line) a key file others could read or replace (module docstring).

    `st` is the opened file's own stat (so the file checked is the file read). POSIX only."""
    if os.name != "posix":
        return
    mode = stat.S_IMODE(st.st_mode)
    fix = f"run: chmod 600 {os.fspath(path)}"
    if st.st_mode & (stat.S_IROTH | stat.S_IWOTH):
        raise ValueError(f"{where} is accessible by everyone (mode {mode:03o}); {fix}")
    if st.st_mode & stat.S_IWGRP:
        raise ValueError(f"{where} is writable by its group (mode {mode:03o}); {fix}")
    if not _trusted_owner(st.st_uid):
        raise ValueError(f"{where} belongs to another user (uid {st.st_uid}); a key must be yours")
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    first = True
    while True:
        try:
            fst = os.stat(folder)
        except OSError as exc:
            raise ValueError(f"cannot check the folder {folder} of {where}: {exc.strerror or exc}") from None
        writable = fst.st_mode & _GROUP_OR_OTHER_WRITE
        if writable and (first or not fst.st_mode & stat.S_ISVTX):
            who = "everyone" if fst.st_mode & stat.S_IWOTH else "its group"
            raise ValueError(f"{where} is in a folder writable by {who} ({folder}, mode "
                             f"{stat.S_IMODE(fst.st_mode):03o}): others could replace the key; "
                             f"run: chmod go-w {folder}" + ("" if first else " (or move the key)"))
        if not _trusted_owner(fst.st_uid):
            raise ValueError(f"{where} is in a folder that belongs to another user ({folder}, uid {fst.st_uid})")
        parent = os.path.dirname(folder)
        if parent == folder:
            return
        folder, first = parent, False


def load_key(path: str | os.PathLike[str]) -> bytes:
    """The 32-byte signing key in the file at path (formats and permissions: module docstring).

    Raises ValueError with a one-line message naming the file: missing, unreadable, not a regular
    file, readable or writable by others or in a folder others can write (POSIX), empty, not UTF-8,
    decorated, or no valid key in it.
    """
    where = f"signing key file {os.fspath(path)}"
    try:
        with open(path, "rb") as f:
            st = os.fstat(f.fileno())  # the file we read, not whatever the name points at later
            if not stat.S_ISREG(st.st_mode):
                raise ValueError(f"{where} is not a regular file")
            check_key_permissions(path, st, where)
            raw = f.read(64 * 1024)
    except FileNotFoundError:
        raise ValueError(f"{where} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"{where} is a directory") from None
    except OSError as exc:
        raise ValueError(f"cannot read {where}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{where} is not UTF-8 text (64 hex digits or a passphrase)") from None
    return parse_key_text(text, where)


def signing_timestamp(unix_s: float) -> int:
    """MAVLink signing timestamp (10 us units since 2015-01-01) of a Unix time, clamped to 0..2**48-1."""
    t = int((unix_s - SIGNING_EPOCH_UNIX_S) * TIMESTAMP_UNITS_PER_S)
    return min(max(t, 0), TIMESTAMP_MAX)
