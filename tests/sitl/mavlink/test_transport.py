"""Byte links: the in-process pipe, UDP, and the transport URLs."""

import socket
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.cli import UserError
from sitl.mavlink.transport import PipeTransport, UdpTransport, make_transport


def test_that_pipe_transports_carry_bytes_both_ways_in_order():
    a, b = PipeTransport.pair()
    a.send(b"one")
    a.send(b"two")
    b.send(b"back")
    assert (b.recv(), b.recv(), a.recv()) == (b"onetwo", b"", b"back")


@pytest.mark.parametrize("url", ["tcp:127.0.0.1:5760", "udp:127.0.0.1", "udp:127.0.0.1:port", "udpout:1.2.3.4:0",
                                 "serial:/dev/ttyS0:57600"])
def test_that_make_transport_refuses_what_it_cannot_open(url):
    with pytest.raises(ValueError):
        make_transport(url)


def test_that_a_port_in_use_names_the_link_it_could_not_open():
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("127.0.0.1", 0))
    try:
        url = f"udp:127.0.0.1:{taken.getsockname()[1]}"
        with pytest.raises(UserError, match=f"cannot open the MAVLink link {url}: Address already in use"):
            make_transport(url)  # a bare "[Errno 98] Address already in use" before
    finally:
        taken.close()


def test_that_a_full_client_table_keeps_its_live_clients_and_refuses_newcomers_until_one_goes_quiet():
    now = [0.0]
    t = UdpTransport("udp:127.0.0.1:0", peer_timeout_s=10.0, max_peers=2, clock=lambda: now[0])
    try:
        a, b, c = ("127.0.0.1", 1001), ("127.0.0.1", 1002), ("127.0.0.1", 1003)
        assert t.add_peer(a) and t.add_peer(b)
        now[0] = 9.0
        assert t.add_peer(b)  # b keeps talking
        assert not t.add_peer(c) and t.peers_refused == 1 and set(t.peers) == {a, b}
        now[0] = 10.5  # a silent for more than the timeout: its slot is free
        assert t.add_peer(c) and set(t.peers) == {b, c}
    finally:
        t.close()


def test_that_recv_passes_only_whole_frame_datagrams_and_learns_only_their_senders():
    t = UdpTransport("udp:127.0.0.1:0")
    good = bytes(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3).pack(mavlink.MAVLink(None, 255, 190)))
    junk, gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM), socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for s in (junk, gcs):
            s.bind(("127.0.0.1", 0))
        junk.sendto(bytes([0xFD, 255, 0, 0, 0, 1, 1, 0, 0, 0]), t.local_address)  # sent first
        gcs.sendto(good, t.local_address)
        got, deadline = b"", time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:  # until the good datagram is delivered
            got = t.recv()
            time.sleep(0.001)
        assert got == good
        assert t.peers == [gcs.getsockname()] and t.datagram_drops == {"truncated": 1}
    finally:
        for s in (junk, gcs):
            s.close()
        t.close()
