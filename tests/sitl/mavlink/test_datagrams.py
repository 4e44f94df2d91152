"""Each UDP datagram parsed on its own: whole MAVLink frames or nothing, drops counted by reason."""

import os

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.signing import MavlinkSigner, SigningConfig
from sitl.mavlink.datagrams import DatagramParser, Drop

KEY = bytes(range(1, 33))


def frame(msg=None, signer: MavlinkSigner | None = None) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    msg = msg or mavlink.MAVLink_param_request_read_message(1, 1, b"PS_ALT_M", -1)
    if signer is None:
        return bytes(msg.pack(mav))
    signer.attach(mav)
    return signer.pack(msg, mav)


GOOD = frame()
HEARTBEAT = frame(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3))


def corrupt_crc(data: bytes) -> bytes:
    return data[:-1] + bytes([data[-1] ^ 0xFF])


@pytest.mark.parametrize("datagram, reason", [
    (b"", Drop.EMPTY),
    (b"\x00hello world", Drop.NOT_MAVLINK),
    (bytes([0xFD, 255, 0, 0, 0, 1, 1, 0, 0, 0]), Drop.TRUNCATED),  # a header claiming 255 bytes, nothing else
    (GOOD[:6], Drop.TRUNCATED),
    (GOOD[:-3], Drop.TRUNCATED),
    (bytes([0xFD, 9, 0x80]) + GOOD[3:], Drop.BAD_HEADER),
    (corrupt_crc(GOOD), Drop.BAD_FRAME),
    (GOOD + b"junk", Drop.TRAILING),
    (GOOD + corrupt_crc(HEARTBEAT), Drop.BAD_FRAME),
])
def test_that_a_datagram_that_is_not_whole_frames_is_dropped_whole_and_counted(datagram, reason):
    parser = DatagramParser()
    assert parser.parse(datagram) == []
    assert parser.drops == {reason: 1} and parser.dropped == 1


def test_that_a_truncated_datagram_never_holds_back_the_next_one():
    parser = DatagramParser()
    assert parser.parse(bytes([0xFD, 255, 0, 0, 0, 1, 1, 0, 0, 0])) == []
    msgs = parser.parse(GOOD)
    assert [m.get_type() for m in msgs] == ["PARAM_REQUEST_READ"] and msgs[0].param_id == "PS_ALT_M"


def test_that_every_whole_frame_of_a_packed_datagram_is_delivered():
    msgs = DatagramParser().parse(HEARTBEAT + GOOD + HEARTBEAT)
    assert [m.get_type() for m in msgs] == ["HEARTBEAT", "PARAM_REQUEST_READ", "HEARTBEAT"]


def test_that_with_a_signer_only_authenticated_frames_are_delivered():
    ours = MavlinkSigner(SigningConfig(KEY))
    theirs = MavlinkSigner(SigningConfig(KEY))
    parser = DatagramParser(ours)
    assert parser.parse(GOOD) == [] and ours.stats["unsigned"] == 1
    forged = MavlinkSigner(SigningConfig(bytes(range(2, 34))))
    assert parser.parse(frame(signer=forged)) == [] and ours.stats["bad_signature"] == 1
    signed = frame(signer=theirs)
    assert [m.get_type() for m in parser.parse(signed)] == ["PARAM_REQUEST_READ"]
    assert parser.parse(signed) == [] and ours.stats["replayed"] == 1
    assert parser.dropped == 0  # refused frames are counted by the signer, not as malformed datagrams
