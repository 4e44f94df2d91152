"""MAVLink signing keys and timestamps, shared by every program that signs or authenticates.

Key file (`load_key`), one of:

- 64 hex digits: the 32-byte secret key itself (e.g. from `openssl rand -hex 32`);
- one line of passphrase: the key is SHA-256 of its UTF-8 bytes, as MAVProxy's
  `signing setup PASSPHRASE` derives it, so the same passphrase keys MAVProxy, ArduPilot
  (through MAVProxy's SETUP_SIGNING) and us (MAVProxy takes an ASCII passphrase without spaces).
  Surrounding whitespace is ignored. A passphrase must be at least 8 characters and contain a
  non-hex character (anything made only of hex digits is read as a hex key and must then have
  exactly 64 of them: a typo'd key is refused, not hashed).

The file must not be readable or writable by everyone: on POSIX a key file with any "other"
permission bit (`chmod o-rwx`, e.g. mode 600 or 640) is REFUSED, not warned about: a key anybody on
the companion can read authenticates nothing. An all-zero key is refused (MAVLink's "signing off").

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


def parse_key_text(text: str, where: str = "signing key") -> bytes:
    """The key in a key file's text (module docstring); ValueError (one line) if there is none."""
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
        if len(line) < MIN_PASSPHRASE_LEN:
            raise ValueError(f"{where}: passphrase is shorter than {MIN_PASSPHRASE_LEN} characters")
        key = key_from_passphrase(line)
    if not any(key):
        raise ValueError(f"{where} is all zeros (MAVLink's 'signing disabled' key)")
    return key


def load_key(path: str | os.PathLike[str]) -> bytes:
    """The 32-byte signing key in the file at path (formats and permissions: module docstring).

    Raises ValueError with a one-line message naming the file: missing, unreadable, not a regular
    file, readable or writable by everyone (POSIX), empty, not UTF-8, or no valid key in it.
    """
    where = f"signing key file {os.fspath(path)}"
    try:
        with open(path, "rb") as f:
            st = os.fstat(f.fileno())  # the file we read, not whatever the name points at later
            if not stat.S_ISREG(st.st_mode):
                raise ValueError(f"{where} is not a regular file")
            if os.name == "posix" and st.st_mode & (stat.S_IROTH | stat.S_IWOTH):
                raise ValueError(f"{where} is accessible by everyone (mode {stat.S_IMODE(st.st_mode):03o}); "
                                 f"run: chmod 600 {os.fspath(path)}")
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
