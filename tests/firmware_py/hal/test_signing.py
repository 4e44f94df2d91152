"""MAVLink 2 signing: key files, the signer's timestamps, and the framer refusing unsigned, forged and
replayed frames (counted, never delivered) while signed ones pass."""

from __future__ import annotations

import hashlib
import os
import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.keys import SIGNING_EPOCH_UNIX_S, TIMESTAMP_MAX, key_from_passphrase, load_key, signing_timestamp
from firmware_py.hal.mavlink_link import (
    ByteStreamLink,
    MavlinkFramer,
    PymavlinkLink,
    heartbeat_msg,
    open_mavlink,
    register_mavlink_backend,
    unregister_mavlink_backend,
)
from firmware_py.hal.signing import NEW_STREAM_MAX_AGE, MavlinkSigner, SigningConfig, apply_to_mavlink
from tests.firmware_py.byte_pipe import BytePipe
from tests.firmware_py.core.test_keys import HEX, KEY, key_file, posix_only

OTHER_KEY = bytes(range(2, 34))


class Sender:
    """An autopilot-like sender (system 1, component 1) signing with a key, one frame at a time."""

    def __init__(self, key: bytes = KEY, link_id: int = 0, srcComponent: int = 1, clock=time.time) -> None:
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=srcComponent)
        self.signer = MavlinkSigner(SigningConfig(key, link_id), clock=clock)
        self.signer.attach(self.mav)

    def frame(self, msg=None) -> bytes:
        buf = self.signer.pack(msg if msg is not None else heartbeat_msg(), self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return buf


def unsigned_frame(msg=None, mavlink1: bool = False) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    return bytes((msg if msg is not None else heartbeat_msg()).pack(mav, force_mavlink1=mavlink1))


def fix_crc(frame: bytearray) -> bytearray:
    """Recompute a MAVLink 2 frame's CRC after tampering (what an attacker would do)."""
    n = frame[1]
    msg_id = int.from_bytes(frame[7:10], "little")
    crc = mavlink.x25crc(bytes(frame[1:10 + n]))
    crc.accumulate(bytes([mavlink.mavlink_map[msg_id].crc_extra]))
    frame[10 + n:12 + n] = crc.crc.to_bytes(2, "little")
    return frame


def framer(key: bytes = KEY, allow_unsigned: bool = False) -> MavlinkFramer:
    return MavlinkFramer(signer=MavlinkSigner(SigningConfig(key, allow_unsigned=allow_unsigned)))


# ----- key files ----------------------------------------------------------------------------------

def test_a_hex_key_file_holds_the_32_byte_key(tmp_path):
    assert load_key(key_file(tmp_path, HEX + "\n")) == KEY
    assert load_key(key_file(tmp_path, "  " + HEX.upper() + "  \r\n", name="upper.key")) == KEY


def test_a_passphrase_key_file_gives_its_sha256_as_mavproxy_signing_setup_does(tmp_path):
    phrase = "correct horse battery staple"
    assert load_key(key_file(tmp_path, phrase + "\n")) == hashlib.sha256(phrase.encode()).digest()
    assert key_from_passphrase(phrase) == hashlib.sha256(phrase.encode()).digest()
    assert load_key(key_file(tmp_path, "pässwörd-überall", name="utf8.key")) == key_from_passphrase("pässwörd-überall")


@pytest.mark.parametrize(("content", "word"), [
    ("", "empty"),
    ("\n  \n", "empty"),
    (HEX[:-1], "63 hex digits"),
    (HEX + "00", "66 hex digits"),
    ("deadbeef", "8 hex digits"),
    ("short!", "shorter than 8"),
    ("first line passphrase\nsecond line", "one line"),
    ("00" * 32, "all zeros"),
    (b"\xff\xfe\x00binary", "UTF-8"),
])
def test_bad_key_files_are_refused_in_one_line(tmp_path, content, word):
    path = key_file(tmp_path, content)
    with pytest.raises(ValueError) as err:
        load_key(path)
    msg = str(err.value)
    assert word in msg and str(path) in msg and "\n" not in msg


def test_a_missing_key_file_or_a_directory_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_key(tmp_path / "nope.key")
    with pytest.raises(ValueError, match=r"directory|not a regular file|cannot read"):
        load_key(tmp_path)


@posix_only
@pytest.mark.parametrize("mode", [0o644, 0o604, 0o666, 0o602])
def test_a_key_file_others_can_access_is_refused(tmp_path, mode):
    path = key_file(tmp_path, HEX, mode=mode)
    with pytest.raises(ValueError, match=r"accessible by everyone .*chmod 600"):
        load_key(path)


@posix_only
@pytest.mark.parametrize("mode", [0o600, 0o400, 0o640])
def test_a_key_file_private_to_its_owner_or_group_is_accepted(tmp_path, mode):
    assert load_key(key_file(tmp_path, HEX, mode=mode)) == KEY


@posix_only
@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root reads anything")
def test_an_unreadable_key_file_is_refused_in_one_line(tmp_path):
    with pytest.raises(ValueError, match="cannot read"):
        load_key(key_file(tmp_path, HEX, mode=0o000))


def test_signing_config_checks_its_fields_and_hides_the_key():
    cfg = SigningConfig(KEY, link_id=7)
    assert HEX not in repr(cfg) and str(list(KEY)) not in repr(cfg) and "link_id=7" in repr(cfg)
    for bad in (KEY[:31], b"\x00" * 32, "x" * 32):
        with pytest.raises(ValueError, match="key"):
            SigningConfig(bad)
    for bad in (-1, 256, True, 1.0):
        with pytest.raises(ValueError, match="link id"):
            SigningConfig(KEY, link_id=bad)


# ----- timestamps ---------------------------------------------------------------------------------

def test_signing_timestamps_count_10_us_since_2015_clamped_to_48_bits():
    assert signing_timestamp(SIGNING_EPOCH_UNIX_S) == 0
    assert signing_timestamp(SIGNING_EPOCH_UNIX_S + 1.5) == 150_000
    assert signing_timestamp(0.0) == 0  # a clock before 2015 (no RTC) clamps, never goes negative
    assert signing_timestamp(1e12) == TIMESTAMP_MAX


def test_sent_timestamps_strictly_increase_even_on_a_stopped_clock_and_follow_accepted_frames():
    t = [SIGNING_EPOCH_UNIX_S + 1000.0]
    sender = Sender(clock=lambda: t[0])
    stamps = [int.from_bytes(sender.frame()[-12:-6], "little") for _ in range(5)]
    assert stamps[0] == 100_000_000 and stamps == sorted(set(stamps))  # +1 per frame while the clock stands
    t[0] += 1.0
    assert int.from_bytes(sender.frame()[-12:-6], "little") == 100_100_000  # not behind the clock
    t[0] -= 50.0  # the clock steps back: timestamps do not
    assert int.from_bytes(sender.frame()[-12:-6], "little") == 100_100_001
    # a node without a real-time clock catches up with the newest frame it accepted
    lost = Sender(clock=lambda: 0.0)
    stale = lost.signer.now()
    assert lost.signer.verify(Sender().frame()) is None
    assert lost.signer.now() > stale + 10**12


# ----- the framer ---------------------------------------------------------------------------------

def test_a_validly_signed_frame_is_delivered_and_marked_signed():
    f = framer()
    got = f.feed(Sender(link_id=5).frame())
    assert [m.get_type() for m in got] == ["HEARTBEAT"]
    assert got[0].get_signed() and got[0].get_link_id() == 5
    assert f.signer.stats["signed"] == 1 and f.bad_frames == f.bad_bytes == 0


@pytest.mark.parametrize("mavlink1", [False, True])
def test_unsigned_frames_are_refused_and_counted_not_taken_for_line_noise(mavlink1):
    f = framer()
    sender = Sender()
    got = f.feed(unsigned_frame(mavlink1=mavlink1) + sender.frame() + unsigned_frame(mavlink1=mavlink1))
    assert len(got) == 1 and got[0].get_signed()  # only the signed one, unhurt by its neighbours
    assert f.signer.stats["unsigned"] == 2 and f.signer.stats["signed"] == 1
    assert f.bad_frames == 0 and f.bad_bytes == 0


def test_allow_unsigned_lets_unsigned_frames_in_but_still_refuses_forgeries():
    f = framer(allow_unsigned=True)
    assert len(f.feed(unsigned_frame())) == 1
    assert f.signer.stats["unsigned_accepted"] == 1
    forged = bytearray(Sender().frame())
    forged[-1] ^= 0x01
    assert f.feed(bytes(forged)) == [] and f.signer.stats["bad_signature"] == 1


def test_a_flipped_bit_in_the_signature_is_a_bad_signature():
    f = framer()
    for k in range(1, 7):
        forged = bytearray(Sender().frame())
        forged[-k] ^= 1 << (k % 8)
        assert f.feed(bytes(forged)) == []
    assert f.signer.stats["bad_signature"] == 6 and f.signer.stats["signed"] == 0


def test_a_forged_payload_with_a_recomputed_crc_is_a_bad_signature():
    f = framer()
    forged = bytearray(Sender().frame(mavlink.MAVLink_timesync_message(0, 42)))
    forged[10] ^= 0x01  # tc1's low bit
    assert f.feed(bytes(fix_crc(forged))) == []
    assert f.signer.stats["bad_signature"] == 1 and f.bad_frames == 0


def test_a_forged_payload_without_a_crc_fix_fails_the_crc_first():
    f = framer()
    forged = bytearray(Sender().frame(mavlink.MAVLink_timesync_message(0, 42)))
    forged[10] ^= 0x01
    assert f.feed(bytes(forged)) == []
    assert f.bad_frames >= 1 and f.signer.stats["signed"] == 0


def test_a_frame_signed_with_another_key_is_a_bad_signature():
    f = framer()
    assert f.feed(Sender(key=OTHER_KEY).frame()) == []
    assert f.signer.stats["bad_signature"] == 1


def test_a_forged_link_id_or_timestamp_breaks_the_signature():
    f = framer()
    for offset in (-13, -12, -7):  # link id, timestamp low and high bytes
        forged = bytearray(Sender().frame())
        forged[offset] ^= 0x01
        assert f.feed(bytes(forged)) == []
    assert f.signer.stats["bad_signature"] == 3


def test_a_replayed_frame_is_refused_and_counted():
    f = framer()
    sender = Sender()
    first, second = sender.frame(), sender.frame()
    assert len(f.feed(first)) == 1 and len(f.feed(second)) == 1
    assert f.feed(first) == [] and f.feed(second) == []  # played back
    assert f.signer.stats["replayed"] == 2 and f.signer.stats["signed"] == 2
    assert len(f.feed(sender.frame())) == 1  # the real sender carries on


def test_streams_are_kept_apart_by_link_id_and_component():
    f = framer()
    t = [time.time()]
    a, b = Sender(link_id=0, clock=lambda: t[0]), Sender(link_id=1, clock=lambda: t[0] - 10.0)
    c = Sender(srcComponent=191, clock=lambda: t[0] - 20.0)
    got = f.feed(a.frame() + b.frame() + c.frame() + b.frame())
    assert len(got) == 4 and f.signer.stats["replayed"] == 0  # older timestamps, but other streams
    assert set(f.signer.streams) == {(0, 1, 1), (1, 1, 1), (0, 1, 191)}


def test_a_new_stream_more_than_a_minute_old_is_a_replay():
    f = framer()
    old = Sender(clock=lambda: time.time() - 3600.0).frame()  # captured an hour ago
    assert f.feed(old) == [] and f.signer.stats["replayed"] == 1
    recent = Sender(link_id=2, clock=lambda: time.time() - 30.0).frame()  # within the minute
    assert len(f.feed(recent)) == 1
    assert NEW_STREAM_MAX_AGE == 6_000_000


def test_a_forged_frame_with_a_future_timestamp_cannot_lock_the_real_sender_out():
    f = framer()
    attacker = Sender(key=OTHER_KEY, clock=lambda: time.time() + 86_400.0)
    assert f.feed(attacker.frame()) == []
    assert len(f.feed(Sender().frame())) == 1  # pymavlink's checker would now call this a replay
    assert f.signer.stats == {"signed": 1, "unsigned": 0, "bad_signature": 1, "replayed": 0, "unsigned_accepted": 0}


def test_a_refused_frame_is_skipped_whole_and_a_frame_hidden_in_its_payload_is_never_delivered():
    good = Sender().frame()
    assert len(good) <= 50 and len(framer().feed(good)) == 1  # on its own it would be taken
    carrier = unsigned_frame(mavlink.MAVLink_statustext_message(6, good))  # the signed frame as text
    f = framer()
    assert f.feed(carrier) == []
    assert f.signer.stats["unsigned"] == 1 and f.signer.stats["signed"] == 0
    assert f.bad_frames == 0 and f.bad_bytes == 0


def test_a_frame_failing_its_crc_still_costs_one_byte_with_a_key():
    f = framer()
    got = f.feed(b"\xfd\x05\x00" + Sender().frame())  # a corrupt header claiming 5 bytes, then a real frame
    assert len(got) == 1 and f.bad_frames == 1 and f.bad_bytes == 3


def test_a_framer_refuses_a_decoder_that_checks_signatures_itself():
    mav = mavlink.MAVLink(None)
    apply_to_mavlink(mav, SigningConfig(KEY))
    with pytest.raises(ValueError, match="decoder"):
        MavlinkFramer(mav, signer=MavlinkSigner(SigningConfig(KEY)))


def test_apply_to_mavlink_keys_a_plain_pymavlink_parser_that_accepts_our_frames():
    rx = mavlink.MAVLink(None)
    apply_to_mavlink(rx, SigningConfig(KEY))
    msg = rx.parse_char(Sender().frame())
    assert msg is not None and msg.get_type() == "HEARTBEAT" and rx.signing.goodsig_count == 1


# ----- links --------------------------------------------------------------------------------------

def signed_pair(key_a: bytes = KEY, key_b: bytes = KEY) -> tuple[ByteStreamLink, ByteStreamLink]:
    a_end, b_end = BytePipe.pair()
    return (ByteStreamLink(a_end.send, a_end.recv, signing=SigningConfig(key_a, link_id=1)),
            ByteStreamLink(b_end.send, b_end.recv, source_system=1, source_component=1,
                           signing=SigningConfig(key_b)))


def test_links_with_the_same_key_talk_signed():
    companion, autopilot = signed_pair()
    assert companion.signing_active
    companion.send(heartbeat_msg())
    companion.send(mavlink.MAVLink_timesync_message(0, 42))
    got = autopilot.recv()
    assert [m.get_type() for m in got] == ["HEARTBEAT", "TIMESYNC"] and all(m.get_signed() for m in got)
    assert autopilot.stats["rx_signed"] == 2 and autopilot.stats["rx_messages"] == 2
    autopilot.send(heartbeat_msg())
    assert len(companion.recv()) == 1 and companion.stats["rx_signed"] == 1


def test_links_with_different_keys_hear_nothing_and_count_it_on_both_sides():
    companion, autopilot = signed_pair(KEY, OTHER_KEY)
    for _ in range(3):
        companion.send(heartbeat_msg())
        autopilot.send(heartbeat_msg())
    assert autopilot.recv() == [] and companion.recv() == []
    for link in (companion, autopilot):
        assert link.stats["rx_bad_signature"] == 3 and link.stats["rx_messages"] == 0
        assert link.stats["rx_bad_frames"] == 0 and link.stats["rx_bad_bytes"] == 0


def test_a_signed_link_refuses_an_unsigned_peer_and_an_unsigned_link_is_unchanged():
    a_end, b_end = BytePipe.pair()
    plain = ByteStreamLink(a_end.send, a_end.recv)
    signed = ByteStreamLink(b_end.send, b_end.recv, signing=SigningConfig(KEY))
    assert not plain.signing_active
    plain.send(heartbeat_msg())
    assert signed.recv() == [] and signed.stats["rx_unsigned"] == 1
    signed.send(heartbeat_msg())
    got = plain.recv()  # without a key, signed frames are delivered unchecked, as before
    assert len(got) == 1 and plain.stats["rx_signed"] == 0 and plain.stats["rx_unsigned"] == 0


def test_a_listening_udp_link_only_answers_senders_that_signed_something():
    link = PymavlinkLink("udp:127.0.0.1:0", signing=SigningConfig(KEY))
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    friend = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        addr = link.local_address
        stranger.sendto(unsigned_frame(), addr)
        friend.sendto(Sender().frame(), addr)
        got, deadline = [], time.monotonic() + 3.0
        while link.stats["rx_unsigned"] + link.stats["rx_signed"] < 2 and time.monotonic() < deadline:
            got += link.recv()
            time.sleep(0.005)
        assert len(got) == 1 and link.stats["rx_unsigned"] == 1
        assert {port for _host, port in link._conn.clients} == {friend.getsockname()[1]}
    finally:
        link.close()
        stranger.close()
        friend.close()


def test_open_mavlink_passes_the_key_only_to_backends_that_take_it():
    seen = {}

    def signing_backend(url, signing=None):
        seen["signing"] = signing
        return ByteStreamLink(lambda _d: None, lambda: b"", signing=signing)

    register_mavlink_backend("signtest", signing_backend)
    register_mavlink_backend("plaintest", lambda url: ByteStreamLink(lambda _d: None, lambda: b""))
    try:
        cfg = SigningConfig(KEY)
        assert open_mavlink("signtest:x", signing=cfg).signing_active and seen["signing"] is cfg
        with pytest.raises(ValueError, match="does not support signing"):
            open_mavlink("plaintest:x", signing=cfg)
        assert not open_mavlink("plaintest:x").signing_active
    finally:
        unregister_mavlink_backend("signtest")
        unregister_mavlink_backend("plaintest")
