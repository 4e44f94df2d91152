"""MAVLink 2 message signing (authentication) for our links, keyed from a file.

Keys are loaded by `firmware_py.core.keys` (formats and permission rules there).

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
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from firmware_py.core.keys import KEY_SIZE, TIMESTAMP_UNITS_PER_S, load_key, signing_timestamp

SIGNATURE_BLOCK_LEN = 13  # link id 1 + timestamp 6 + signature 6
NEW_STREAM_MAX_AGE = 60 * TIMESTAMP_UNITS_PER_S
"""A stream seen for the first time may be at most one minute behind our timestamp (MAVLink spec)."""
_IFLAG_SIGNED = 0x01
_MAGIC_V2 = 0xFD


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
