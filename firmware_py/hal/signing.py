"""MAVLink 2 message signing (authentication) for our links, keyed from a file.

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

Signing (MAVLink spec, "Message Signing"): a signed frame carries link id (1 byte), a 48-bit
timestamp (10 us units since 2015-01-01 GMT) and the first 6 bytes of
SHA-256(key + frame up to and including the timestamp). `MavlinkSigner` holds one link's state:

- sending: every frame gets a timestamp strictly greater than the last one we used, and not below
  the wall clock (`signing_timestamp`) nor the newest timestamp we have accepted (the spec's rule,
  which lets a node without a real-time clock catch up with its peers);
- receiving (`verify`): the signature is checked FIRST (constant-time compare), then the
  timestamp against the newest one accepted on that stream (link id, system id, component id):
  not newer is a replay. A stream seen for the first time is refused if its timestamp is more
  than a minute behind our own (a capture replayed to a restarted node). Only an authenticated
  frame updates the stream table, so forged frames cannot push a stream's timestamp into the
  future and lock the real sender out. (pymavlink's own `check_signature` records the timestamp
  before checking the signature; that is why the links verify here, not in pymavlink.)
- `allow_unsigned`: also accept UNSIGNED frames (MAVLink 1, or 2 without the signed flag), for
  mixed setups during a migration; they are counted. Signed frames with a bad signature or a
  replayed timestamp are refused even then. Off by default.

`apply_to_mavlink` sets the same key on a plain pymavlink `MAVLink` (e.g. a `mavutil` connection's
`.mav`), for tools that let pymavlink do the checking.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import stat
import string
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

KEY_SIZE = 32
SIGNATURE_BLOCK_LEN = 13  # link id 1 + timestamp 6 + signature 6
SIGNING_EPOCH_UNIX_S = 1_420_070_400  # 2015-01-01T00:00:00Z
TIMESTAMP_UNITS_PER_S = 100_000  # 10 us
TIMESTAMP_MAX = (1 << 48) - 1
NEW_STREAM_MAX_AGE = 60 * TIMESTAMP_UNITS_PER_S
"""A stream seen for the first time may be at most one minute behind our timestamp (MAVLink spec)."""
MIN_PASSPHRASE_LEN = 8
_IFLAG_SIGNED = 0x01
_MAGIC_V2 = 0xFD
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


@dataclass(frozen=True)
class SigningConfig:
    """A link's signing setup. `key` never appears in repr().

    Attributes:
        key: the 32-byte secret key (`load_key`).
        link_id: our MAVLink link id (0-255), sent in every signature.
        allow_unsigned: also accept unsigned frames (mixed setups); forged or replayed signed frames
            are still refused.
    """

    key: bytes = field(repr=False)
    link_id: int = 0
    allow_unsigned: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.key, bytes | bytearray) or len(self.key) != KEY_SIZE:
            raise ValueError(f"signing key must be {KEY_SIZE} bytes")
        if not any(self.key):
            raise ValueError("signing key is all zeros (MAVLink's 'signing disabled' key)")
        object.__setattr__(self, "key", bytes(self.key))
        if isinstance(self.link_id, bool) or not isinstance(self.link_id, int) or not 0 <= self.link_id <= 255:
            raise ValueError(f"signing link id must be an integer 0-255, got {self.link_id!r}")
        if not isinstance(self.allow_unsigned, bool):
            raise ValueError(f"allow_unsigned must be True or False, got {self.allow_unsigned!r}")

    @classmethod
    def from_file(cls, path: str | os.PathLike[str], link_id: int = 0, allow_unsigned: bool = False) -> SigningConfig:
        return cls(load_key(path), link_id, allow_unsigned)


def signing_timestamp(unix_s: float) -> int:
    """MAVLink signing timestamp (10 us units since 2015-01-01) of a Unix time, clamped to 0..2**48-1."""
    t = int((unix_s - SIGNING_EPOCH_UNIX_S) * TIMESTAMP_UNITS_PER_S)
    return min(max(t, 0), TIMESTAMP_MAX)


def frame_signature(key: bytes, signed_part: bytes | bytearray) -> bytes:
    """The 6-byte MAVLink signature of a frame's bytes up to and including its timestamp."""
    return hashlib.sha256(bytes(key) + bytes(signed_part)).digest()[:6]


REJECT_REASONS = ("unsigned", "bad_signature", "replayed")


class MavlinkSigner:
    """Signing state of one link end, shared by its encoder (`pack`) and its framer (`verify`).

    stats: `signed` (authenticated frames accepted), `unsigned` / `bad_signature` / `replayed`
    (frames refused, by reason), `unsigned_accepted` (unsigned frames let in by allow_unsigned).
    """

    def __init__(self, config: SigningConfig, clock: Callable[[], float] = time.time) -> None:
        if not isinstance(config, SigningConfig):
            raise ValueError(f"signing must be a SigningConfig, got {type(config).__name__}")
        self.config = config
        self._clock = clock
        self._timestamp = 0  # newest timestamp used or accepted
        self._streams: dict[tuple[int, int, int], int] = {}
        self.stats: dict[str, int] = {"signed": 0, "unsigned": 0, "bad_signature": 0, "replayed": 0,
                                      "unsigned_accepted": 0}

    def now(self) -> int:
        """Our current signing timestamp: never decreasing, not behind the wall clock or accepted frames."""
        self._timestamp = max(self._timestamp, signing_timestamp(self._clock()))
        return self._timestamp

    @property
    def streams(self) -> dict[tuple[int, int, int], int]:
        """Newest accepted timestamp per (link id, system id, component id)."""
        return dict(self._streams)

    # ----- sending ------------------------------------------------------------------------------

    def attach(self, mav: Any) -> None:
        """Make a pymavlink MAVLink encoder sign with our key and link id (then use `pack`)."""
        mav.signing.secret_key = self.config.key
        mav.signing.link_id = self.config.link_id
        mav.signing.sign_outgoing = True
        mav.signing.allow_unsigned_callback = None
        mav.signing.timestamp = self.now()

    def pack(self, msg: Any, mav: Any) -> bytes:
        """msg packed and signed by an `attach`ed encoder, with a fresh timestamp (caller bumps mav.seq)."""
        mav.signing.timestamp = max(mav.signing.timestamp, self.now())
        buf = bytes(msg.pack(mav))
        self._timestamp = max(self._timestamp, mav.signing.timestamp - 1)  # pymavlink added 1 after using it
        return buf

    # ----- receiving ----------------------------------------------------------------------------

    def verify(self, frame: bytes | bytearray) -> str | None:
        """None if a CRC-checked whole frame may be delivered, else why not (a REJECT_REASONS entry).

        Counts the outcome in stats. The frame's CRC and length must already have been checked.
        """
        signed = len(frame) >= 12 + SIGNATURE_BLOCK_LEN and frame[0] == _MAGIC_V2 and frame[2] & _IFLAG_SIGNED
        if not signed:
            if self.config.allow_unsigned:
                self.stats["unsigned_accepted"] += 1
                return None
            return self._reject("unsigned")
        expected = frame_signature(self.config.key, frame[:-6])
        if not hmac.compare_digest(expected, bytes(frame[-6:])):
            return self._reject("bad_signature")
        link_id = frame[-13]
        timestamp = int.from_bytes(frame[-12:-6], "little")
        stream = (link_id, frame[5], frame[6])
        last = self._streams.get(stream)
        if last is not None:
            if timestamp <= last:
                return self._reject("replayed")
        elif timestamp + NEW_STREAM_MAX_AGE < self.now():
            return self._reject("replayed")  # a new stream, but older than a minute: a capture played back
        self._streams[stream] = timestamp
        self._timestamp = max(self._timestamp, timestamp)
        self.stats["signed"] += 1
        return None

    def _reject(self, reason: str) -> str:
        self.stats[reason] += 1
        return reason


def apply_to_mavlink(mav: Any, config: SigningConfig, timestamp: int | None = None) -> None:
    """Key a plain pymavlink `MAVLink` (sign outgoing; pymavlink checks incoming), as mavutil's
    `setup_signing` does. With config.allow_unsigned pymavlink accepts unsigned frames, and (its
    callback cannot tell them apart) badly signed ones too.

    Note pymavlink's checker records a stream's timestamp before checking the signature; our links
    use `MavlinkSigner` instead.
    """
    mav.signing.secret_key = config.key
    mav.signing.link_id = config.link_id
    mav.signing.sign_outgoing = True
    mav.signing.allow_unsigned_callback = (lambda _mav, _msg_id: True) if config.allow_unsigned else None
    mav.signing.timestamp = signing_timestamp(time.time()) if timestamp is None else timestamp
