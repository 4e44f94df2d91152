"""The live sample stream: loopback round trip, malformed datagrams counted, gaps counted, never raising."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from firmware_py.live_stream import (
    HEADER_SIZE,
    MAX_DATAGRAM,
    MAX_RECORDS,
    LiveStreamReceiver,
    LiveStreamSender,
    decode_datagram,
    encode_datagram,
    parse_stream_url,
)
from firmware_py.samplelog import SAMPLE_DTYPE, new_records


def records(n: int, t0: float = 0.0) -> np.ndarray:
    r = new_records(n)
    r["t_s"] = t0 + np.arange(n) * 0.002
    r["range_m"] = 5.0 + np.arange(n) * 0.01
    r["servo_rad"] = np.linspace(-1, 1, n)
    r["sweep_dir"] = 1
    r["flags"] = np.arange(n) % 3
    r["x_m"], r["y_m"], r["z_m"] = 1.0, 2.0, -12.0
    return r


def poll_until(rx: LiveStreamReceiver, n: int, timeout_s: float = 5.0) -> np.ndarray:
    got, deadline = [], time.monotonic() + timeout_s
    while sum(len(g) for g in got) < n and time.monotonic() < deadline:
        got.append(rx.poll())
        time.sleep(0.01)
    return np.concatenate(got) if got else new_records(0)


def test_that_a_full_datagram_stays_under_the_mtu_budget():
    assert HEADER_SIZE + MAX_RECORDS * SAMPLE_DTYPE.itemsize <= MAX_DATAGRAM < 1472  # 1500 - IP - UDP
    assert len(encode_datagram(0, records(20))) == HEADER_SIZE + 20 * SAMPLE_DTYPE.itemsize < 1400


def test_that_records_round_trip_over_loopback_in_batches():
    with LiveStreamReceiver("udp:127.0.0.1:0") as rx:
        tx = LiveStreamSender(f"udp:127.0.0.1:{rx.local_address[1]}", records_per_datagram=20)
        sent = records(45)
        for rec in sent:  # one at a time, as the payload loop appends
            tx.append(rec)
        assert tx.stats["datagrams"] == 2  # 40 sent, 5 waiting for a batch
        tx.flush()
        tx.close()
        got = poll_until(rx, 45)
    assert got.dtype == SAMPLE_DTYPE and got.tobytes() == sent.tobytes()
    assert tx.stats == {"datagrams": 3, "records": 45, "send_errors": 0, "records_dropped": 0}
    assert rx.stats["datagrams"] == 3 and rx.stats["records"] == 45
    assert rx.stats["lost"] == rx.stats["malformed"] == 0


def test_that_sending_with_nobody_listening_never_raises():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()  # a port nobody listens on (ICMP port unreachable on loopback)
    tx = LiveStreamSender(f"udp:127.0.0.1:{port}", records_per_datagram=5)
    for _ in range(20):
        tx.append(records(5))
    tx.close()
    assert tx.seq == 20 and tx.stats["datagrams"] + tx.stats["send_errors"] == 20


class FailingSocket:
    def __init__(self, exc: OSError) -> None:
        self.exc, self.closed = exc, False

    def sendto(self, data, addr):
        raise self.exc

    def close(self):
        self.closed = True


@pytest.mark.parametrize("exc", [BlockingIOError(11, "full"), ConnectionRefusedError(111, "refused"),
                                 OSError(101, "Network is unreachable")])
def test_that_send_failures_are_counted_not_raised(exc):
    sock = FailingSocket(exc)
    tx = LiveStreamSender("udp:127.0.0.1:14600", records_per_datagram=10, sock=sock)
    tx.append(records(25))
    tx.close()
    assert tx.stats == {"datagrams": 0, "records": 0, "send_errors": 3, "records_dropped": 25}
    assert tx.seq == 3 and tx.last_error is not None and sock.closed
    tx.append(records(3))  # after close: still no exception
    tx.flush()


def test_that_malformed_datagrams_are_counted_and_dropped():
    good = encode_datagram(7, records(4))
    bad_crc = bytearray(good)
    bad_crc[-1] ^= 0xFF
    bad_version = bytearray(good)
    bad_version[4] = 9
    rx = LiveStreamReceiver()
    for data in (b"", b"PSLV", good[:HEADER_SIZE - 1], good[:-1], good + b"\x00", b"XXXX" + good[4:],
                 bytes(bad_crc), bytes(bad_version), b"\x00" * 1400):
        assert len(rx.feed(data)) == 0
    assert rx.stats["malformed"] == 9 and rx.stats["datagrams"] == 0 and rx.last_error
    assert len(rx.feed(good)) == 4 and rx.stats["datagrams"] == 1


@pytest.mark.parametrize(("data", "why"), [(b"", "shorter"), (b"XXXX" + bytes(12), "magic")])
def test_that_decode_says_what_is_wrong(data, why):
    with pytest.raises(ValueError, match=why):
        decode_datagram(data)


def test_that_sequence_gaps_late_datagrams_and_restarts_are_counted():
    rx = LiveStreamReceiver()
    one = records(1)
    for seq in (0, 1, 3, 4, 8):  # 2, 5, 6 and 7 lost
        rx.feed(encode_datagram(seq, one))
    assert rx.stats["lost"] == 4 and rx.stats["late"] == 0
    assert len(rx.feed(encode_datagram(6, one))) == 1  # late, but its records still count
    assert rx.stats["late"] == 1 and rx.stats["lost"] == 4
    rx.feed(encode_datagram(0, one))  # the payload restarted
    rx.feed(encode_datagram(1, one))
    assert rx.stats["restarts"] == 1 and rx.stats["lost"] == 4 and rx.expected_seq == 2


def test_that_the_sequence_number_wraps_without_a_gap():
    rx = LiveStreamReceiver()
    rx.feed(encode_datagram(0xFFFFFFFE, records(1)))
    rx.feed(encode_datagram(0xFFFFFFFF, records(1)))
    rx.feed(encode_datagram(0, records(1)))
    rx.feed(encode_datagram(1, records(1)))
    assert rx.stats["lost"] == 0 and rx.stats["datagrams"] == 4


@pytest.mark.parametrize("url", ["udp:host", "tcp:1.2.3.4:5", "udp:1.2.3.4:0", "udp:1.2.3.4:70000", "", None,
                                 "udp::5"])
def test_that_a_bad_stream_url_is_refused_naming_it(url):
    with pytest.raises(ValueError, match="live stream"):
        parse_stream_url(url)


def test_that_ipv6_and_names_are_accepted():
    assert parse_stream_url("udp:[::1]:14600") == ("::1", 14600)
    assert parse_stream_url("udp:ground.local:14600") == ("ground.local", 14600)


def test_that_a_bad_batch_size_or_unresolvable_host_is_refused_at_start():
    with pytest.raises(ValueError, match="records per datagram"):
        LiveStreamSender("udp:127.0.0.1:14600", records_per_datagram=MAX_RECORDS + 1)
    with pytest.raises(ValueError, match="does not resolve"):
        LiveStreamSender("udp:no-such-host.invalid:14600")
