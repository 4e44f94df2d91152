"""The payload's UDP MAVLink link under hostile datagrams (real sockets on loopback): each datagram is
parsed on its own, so no datagram can hold back another's frames; only a sender of a valid frame (a
signed one with a key) is answered; per-sender state is bounded; sequence gaps are kept per sender."""

from __future__ import annotations

import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.mavlink_link import MAX_SEQ_STREAMS, ByteStreamLink, MavlinkFramer, PymavlinkLink, heartbeat_msg
from firmware_py.hal.signing import MavlinkSigner, SigningConfig

KEY = bytes(range(1, 33))


def encoder(sys_id: int = 1, comp_id: int = 1) -> mavlink.MAVLink:
    return mavlink.MAVLink(None, srcSystem=sys_id, srcComponent=comp_id)


def frame(mav: mavlink.MAVLink, msg=None, seq: int | None = None) -> bytes:
    if seq is not None:
        mav.seq = seq
    buf = bytes((msg if msg is not None else heartbeat_msg()).pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return buf


def attitude(t_ms: int):
    return mavlink.MAVLink_attitude_message(t_ms, 0.1, 0.2, 0.3, 0.0, 0.0, 0.0)


def truncated_header() -> bytes:
    """A MAVLink 2 header claiming a 255-byte payload of a known message (PARAM_VALUE is 25 bytes: no;
    a message long enough to claim 255): 10 bytes and nothing more."""
    long_id = next(i for i, c in sorted(mavlink.mavlink_map.items()) if c.unpacker.size >= 255)
    return bytes([0xFD, 255, 0, 0, 7, 1, 1]) + long_id.to_bytes(3, "little")


def bad_crc(buf: bytes) -> bytes:
    b = bytearray(buf)
    b[-1] ^= 0xFF
    return bytes(b)


class Udp:
    """A few loopback sockets pointed at a link; closed at the end of the test."""

    def __init__(self) -> None:
        self.socks: list[socket.socket] = []

    def sock(self) -> socket.socket:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        self.socks.append(s)
        return s

    def close(self) -> None:
        for s in self.socks:
            s.close()


@pytest.fixture
def udp():
    u = Udp()
    yield u
    u.close()


def receive(link: PymavlinkLink, datagrams: int, timeout_s: float = 5.0) -> list:
    """Everything the link delivers until it has read `datagrams` datagrams (an observable count)."""
    got, deadline = [], time.monotonic() + timeout_s
    while link.stats["rx_datagrams"] + link.stats["rx_foreign"] < datagrams and time.monotonic() < deadline:
        got += link.recv()
        time.sleep(0.001)
    return got


def test_that_a_truncated_header_from_a_stranger_does_not_hold_back_the_autopilots_next_frame(udp):
    link = PymavlinkLink("udp:127.0.0.1:0")
    stranger, autopilot = udp.sock(), udp.sock()
    try:
        stranger.sendto(truncated_header(), link.local_address)
        autopilot.sendto(frame(encoder(), attitude(42)), link.local_address)
        got = receive(link, 2)
    finally:
        link.close()
    assert [m.get_type() for m in got] == ["ATTITUDE"] and got[0].time_boot_ms == 42
    assert link.stats["rx_truncated"] == 1 and link.stats["rx_bad_bytes"] == 10


def test_that_a_frame_split_over_two_datagrams_is_dropped_not_reassembled_and_the_next_one_is_whole(udp):
    link = PymavlinkLink("udp:127.0.0.1:0")
    autopilot = udp.sock()
    whole = frame(encoder(), attitude(1))
    try:
        autopilot.sendto(whole[:15], link.local_address)
        autopilot.sendto(whole[15:], link.local_address)
        autopilot.sendto(frame(encoder(), attitude(2)), link.local_address)
        got = receive(link, 3)
    finally:
        link.close()
    assert [m.time_boot_ms for m in got] == [2]
    assert link.stats["rx_truncated"] == 1


@pytest.mark.parametrize("junk", [b"\x00" * 40, bytes(range(256)) * 4, b"\xfd", "truncated", "bad_crc"])
def test_that_garbage_truncated_and_bad_crc_datagrams_never_make_their_sender_a_peer(udp, junk):
    link = PymavlinkLink("udp:127.0.0.1:0")
    stranger, autopilot = udp.sock(), udp.sock()
    data = {"truncated": truncated_header(), "bad_crc": bad_crc(frame(encoder()))}.get(junk, junk)
    try:
        stranger.sendto(data, link.local_address)
        autopilot.sendto(frame(encoder()), link.local_address)
        receive(link, 2)
        link.send(heartbeat_msg())
        time.sleep(0)  # loopback delivery is synchronous; the read below waits on the socket anyway
        stranger.settimeout(0.2)
        with pytest.raises(TimeoutError):
            stranger.recv(4096)  # not answered: no reflector
        autopilot.settimeout(5.0)
        assert autopilot.recv(4096)  # the autopilot is
    finally:
        link.close()
    assert link.peers == [autopilot.getsockname()]


def test_that_with_a_key_only_a_correctly_signed_frame_admits_a_peer(udp):
    link = PymavlinkLink("udp:127.0.0.1:0", signing=SigningConfig(KEY))
    unsigned, wrong_key, signed = udp.sock(), udp.sock(), udp.sock()
    good, bad = encoder(), encoder()
    MavlinkSigner(SigningConfig(KEY)).attach(good)
    MavlinkSigner(SigningConfig(bytes(range(2, 34)))).attach(bad)
    try:
        unsigned.sendto(frame(encoder()), link.local_address)
        wrong_key.sendto(frame(bad), link.local_address)
        signed.sendto(frame(good), link.local_address)
        got = receive(link, 3)
    finally:
        link.close()
    assert len(got) == 1 and link.peers == [signed.getsockname()]
    assert link.stats["rx_unsigned"] == 1 and link.stats["rx_bad_signature"] == 1


def test_that_a_full_peer_table_keeps_its_live_peers_and_admits_a_new_one_only_in_place_of_a_silent_one(udp):
    now = [100.0]
    link = PymavlinkLink("udp:127.0.0.1:0", max_peers=2, peer_timeout_s=5.0, clock=lambda: now[0])
    a, b, c = udp.sock(), udp.sock(), udp.sock()
    try:
        a.sendto(frame(encoder()), link.local_address)
        b.sendto(frame(encoder()), link.local_address)
        receive(link, 2)
        c.sendto(frame(encoder()), link.local_address)
        receive(link, 3)
        assert set(link.peers) == {a.getsockname(), b.getsockname()} and link.stats["rx_peers_refused"] == 1
        now[0] += 3.0
        a.sendto(frame(encoder()), link.local_address)  # a stays alive, b goes quiet
        receive(link, 4)
        now[0] += 3.0
        c.sendto(frame(encoder()), link.local_address)
        receive(link, 5)
    finally:
        link.close()
    assert set(link.peers) == {a.getsockname(), c.getsockname()}
    assert link._conn.clients == set(link.peers)  # what mavutil writes to


def test_that_forged_sequence_numbers_from_another_sender_do_not_count_as_the_autopilots_losses(udp):
    """The forger claims the autopilot's system and component and always sends sequence number 200:
    interleaved in one stream, every autopilot frame after it would look like a jump of 56+ frames."""
    link = PymavlinkLink("udp:127.0.0.1:0")
    autopilot, forger = udp.sock(), udp.sock()
    ap, fake = encoder(), encoder()
    try:
        for _ in range(20):
            autopilot.sendto(frame(ap), link.local_address)
            forger.sendto(frame(fake, seq=200), link.local_address)
        got = receive(link, 40)
    finally:
        link.close()
    assert len(got) == 40 and link.stats["rx_seq_lost"] == 0


def test_that_a_udpout_link_takes_datagrams_only_from_where_it_sends(udp):
    autopilot = udp.sock()
    link = PymavlinkLink(f"udpout:127.0.0.1:{autopilot.getsockname()[1]}")
    stranger = udp.sock()
    try:
        autopilot.settimeout(5.0)
        _, our_addr = autopilot.recvfrom(4096)  # our first heartbeat
        stranger.sendto(frame(encoder(), attitude(7)), our_addr)
        autopilot.sendto(frame(encoder(), attitude(8)), our_addr)
        got = receive(link, 2)
    finally:
        link.close()
    assert [m.time_boot_ms for m in got] == [8] and link.stats["rx_foreign"] == 1


# ----- the framer's datagram mode ----------------------------------------------------------------

def test_that_a_datagram_with_several_frames_and_a_cut_tail_gives_the_whole_frames_and_keeps_nothing():
    f = MavlinkFramer()
    mav = encoder()
    frames = [frame(mav, attitude(t)) for t in (1, 2, 3)]
    got = f.feed_datagram(frames[0] + frames[1] + frames[2][:20])
    assert [m.time_boot_ms for m in got] == [1, 2]
    assert f.truncated == 1 and f.bad_bytes == 20
    assert [m.time_boot_ms for m in f.feed_datagram(frames[2])] == [3]


def test_that_sequence_state_is_kept_for_a_bounded_number_of_senders():
    f = MavlinkFramer()
    mav = encoder()
    for port in range(3 * MAX_SEQ_STREAMS):
        f.feed_datagram(frame(mav), ("127.0.0.1", port))
    assert len(f._last_seq) == MAX_SEQ_STREAMS and f.seq_lost == 0


def test_that_a_header_of_an_unknown_message_or_an_impossible_length_costs_one_byte_at_once_on_a_stream():
    """On a serial link too, such a header no longer holds the frames behind it until 267 bytes came."""
    good = frame(encoder(), attitude(5))
    unknown = bytes([0xFD, 255, 0, 0, 1, 1, 1, 0xFF, 0xFF, 0xFF])
    too_long = bytes([0xFD, 200, 0, 0, 1, 1, 1, 30, 0, 0])  # ATTITUDE's payload is 28 bytes
    sent = []
    for head in (unknown, too_long):
        chunks = [head + good]
        link = ByteStreamLink(sent.append, lambda chunks=chunks: chunks.pop() if chunks else b"")
        assert [m.time_boot_ms for m in link.recv()] == [5]
