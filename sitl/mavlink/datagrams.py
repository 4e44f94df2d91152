"""One UDP datagram, parsed on its own: whole MAVLink frames, or nothing.

A UDP sender writes whole frames per datagram (pymavlink, MAVProxy and ArduPilot all do; a router
may pack several). So a datagram is parsed alone, never joined to another sender's bytes or to the
next datagram: a truncated header, a payload shorter than its header claims, a failed CRC, an
unknown message id or trailing junk drops that datagram whole and is counted by reason. Nothing
carries over, so no datagram can hold back the frames of any later one (a stream framer would
wait for the 255 bytes a 10-byte datagram's header promises, stalling every sender behind it).

With a signer, each whole frame must also pass `MavlinkSigner.verify` (unsigned, forged and
replayed frames are refused and counted there); only the frames it accepts are returned.
"""

from __future__ import annotations

from collections import Counter
from enum import Enum
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.mavlink_link import decode_frame
from firmware_py.hal.signing import MavlinkSigner

_V1, _V2 = mavlink.PROTOCOL_MARKER_V1, mavlink.PROTOCOL_MARKER_V2


class Drop(Enum):
    """Why a datagram was dropped whole."""

    EMPTY = "empty"
    NOT_MAVLINK = "not_mavlink"  # does not start with a MAVLink magic byte (random bytes)
    TRUNCATED = "truncated"  # shorter than the header, or than the frame its header announces
    BAD_HEADER = "bad_header"  # incompatibility flags we do not know
    BAD_FRAME = "bad_frame"  # failed CRC, or a message id outside the dialect
    TRAILING = "trailing"  # bytes after the last whole frame that are not a frame


def frame_length(data: bytes | bytearray, i: int) -> int | Drop:
    """Whole length of the frame whose magic byte is at i, or why it cannot be one."""
    if data[i] == _V1:
        return 6 + data[i + 1] + 2 if len(data) - i >= 2 else Drop.TRUNCATED
    if len(data) - i < 10:
        return Drop.TRUNCATED
    flags = data[i + 2]
    if flags & ~mavlink.MAVLINK_IFLAG_SIGNED:
        return Drop.BAD_HEADER
    return 10 + data[i + 1] + 2 + (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if flags else 0)


class DatagramParser:
    """Parses datagrams one at a time; `drops` counts the datagrams dropped, by `Drop` reason."""

    def __init__(self, signer: MavlinkSigner | None = None) -> None:
        self._mav = mavlink.MAVLink(None)  # decodes only: the signer (if any) checks signatures
        self.signer = signer
        self.drops: Counter[Drop] = Counter()
        self.frames = 0

    @property
    def dropped(self) -> int:
        return sum(self.drops.values())

    def parse(self, data: bytes | bytearray) -> list[Any]:
        """The messages of one datagram ([] if it was dropped, or every frame in it was refused)."""
        frames: list[bytes] = []
        i, n = 0, len(data)
        if n == 0:
            return self._drop(Drop.EMPTY)
        while i < n:
            if data[i] != _V1 and data[i] != _V2:
                return self._drop(Drop.NOT_MAVLINK if i == 0 else Drop.TRAILING)
            total = frame_length(data, i)
            if isinstance(total, Drop):
                return self._drop(total)
            if n - i < total:
                return self._drop(Drop.TRUNCATED)
            frames.append(bytes(data[i:i + total]))
            i += total
        msgs = []
        for frame in frames:
            msg = self._decode(frame)
            if msg is None:
                return self._drop(Drop.BAD_FRAME)
            msgs.append((frame, msg))
        self.frames += len(msgs)
        if self.signer is None:
            return [msg for _frame, msg in msgs]
        return [msg for frame, msg in msgs if self.signer.verify(frame) is None]

    def _decode(self, frame: bytes) -> Any | None:
        return decode_frame(self._mav, frame)

    def _drop(self, reason: Drop) -> list[Any]:
        self.drops[reason] += 1
        return []
