"""MAVLink FTP refused, as by a vehicle built without it: every request is NAKed at once.

Ground stations try FTP first for the parameter list (MAVProxy fetches `@PARAM/param.pck`) and
fall back to PARAM_REQUEST_LIST only when FTP fails; an unanswered request makes them wait for
their timeout (about 10 s for MAVProxy). A NAK carrying ERR_UnknownCommand (the FTP spec's answer
to an operation the server does not implement) makes them fall back at once.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

from sitl.mavlink.outbox import Outbox

HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, padding, offset
OP_ACK, OP_NAK = 128, 129
ERR_UNKNOWN_COMMAND = 7
PAYLOAD_LEN = 251


def nak_payload(request: bytes | bytearray | list[int]) -> list[int] | None:
    """The FILE_TRANSFER_PROTOCOL payload NAKing request; None for a reply (ACK / NAK), which is not answered."""
    raw = bytes(bytearray(request))[:HEADER.size].ljust(HEADER.size, b"\0")
    seq, session, opcode, _size, _req, _burst, _pad, _offset = HEADER.unpack(raw)
    if opcode in (OP_ACK, OP_NAK):
        return None
    head = HEADER.pack((seq + 1) & 0xFFFF, session, OP_NAK, 1, opcode, 0, 0, 0)
    return list(head + bytes([ERR_UNKNOWN_COMMAND]) + bytes(PAYLOAD_LEN - HEADER.size - 1))


class FtpRefusal:
    """Answers FILE_TRANSFER_PROTOCOL requests with a NAK, to the asker."""

    def __init__(self, mav: Any, out: Outbox) -> None:
        self._mav, self._out = mav, out
        self.refused = 0
        self.handlers: dict[str, Callable[[Any], None]] = {"FILE_TRANSFER_PROTOCOL": self._on_ftp}

    def _on_ftp(self, msg: Any) -> None:
        payload = nak_payload(msg.payload)
        if payload is None:
            return
        self.refused += 1
        self._out.reply(self._mav.file_transfer_protocol_encode(0, msg.get_srcSystem(), msg.get_srcComponent(),
                                                                payload))
