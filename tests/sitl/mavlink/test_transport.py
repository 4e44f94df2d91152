"""Byte links: the in-process pipe and the transport URLs."""

import pytest

from sitl.mavlink.transport import PipeTransport, make_transport


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
