"""The live sample stream: loopback round trip, malformed datagrams counted, gaps counted, never raising."""

from __future__ import annotations

import socket
import time
from importlib.util import find_spec

import numpy as np
import pytest

from firmware_py.core.keys import signing_timestamp
from firmware_py.core.samplelog import SAMPLE_DTYPE, new_records
from firmware_py.core.stream_format import (
    AUTH_HEADER_SIZE,
    FLAG_AUTH,
    HEADER_SIZE,
    MAX_DATAGRAM,
    MAX_RECORDS,
    TAG_SIZE,
    VERSION,
    VERSION_AUTH,
    StreamAuthError,
    decode_datagram,
    encode_datagram,
    parse_datagram,
    parse_stream_url,
)
from firmware_py.live_stream import LiveStreamSender

GROUND = find_spec("ground") is not None  # False on the payload-only install (Raspberry Pi): those tests skip
if GROUND:
    from ground.live_receiver import LATE_WINDOW_S, LiveStreamReceiver
needs_ground = pytest.mark.skipif(not GROUND, reason="needs the receiver (ground/), not in the payload-only install")


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


@needs_ground
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


@needs_ground
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


@needs_ground
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


@needs_ground
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


# ----- authenticated datagrams (version 2) -----------------------------------------------------------

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(2, 34))


def now_stamp(offset_s: float = 0.0) -> int:
    return signing_timestamp(time.time() + offset_s)


def keyed(seq: int = 0, n: int = 3, *, stamp: int | None = None, sender_id: int = 0, key: bytes = KEY) -> bytes:
    return encode_datagram(seq, records(n), key=key, stamp=now_stamp() if stamp is None else stamp,
                           sender_id=sender_id)


def test_that_an_authenticated_datagram_fits_the_mtu_budget_and_says_who_sent_it_when():
    assert AUTH_HEADER_SIZE + MAX_RECORDS * SAMPLE_DTYPE.itemsize + TAG_SIZE <= MAX_DATAGRAM
    data = encode_datagram(9, records(20), key=KEY, stamp=123_456_789, sender_id=7)
    assert len(data) == AUTH_HEADER_SIZE + 20 * SAMPLE_DTYPE.itemsize + TAG_SIZE < 1400
    assert data[4] == VERSION_AUTH and data[5] == FLAG_AUTH
    d = parse_datagram(data, key=KEY)
    assert (d.seq, d.version, d.stamp, d.sender_id, d.authenticated) == (9, VERSION_AUTH, 123_456_789, 7, True)
    assert d.records.tobytes() == records(20).tobytes()
    assert decode_datagram(data, key=KEY)[0] == 9
    assert encode_datagram(9, records(2))[4] == VERSION  # no key: the version 1 format, unchanged


@needs_ground
def test_that_keyed_records_round_trip_over_loopback_from_an_allowed_peer():
    with LiveStreamReceiver("udp:127.0.0.1:0", key=KEY, allowed_peers=["127.0.0.1"]) as rx:
        tx = LiveStreamSender(f"udp:127.0.0.1:{rx.local_address[1]}", records_per_datagram=20, key=KEY, sender_id=3)
        assert tx.authenticated and rx.authenticated
        sent = records(45)
        for rec in sent:
            tx.append(rec)
        tx.close()
        got = poll_until(rx, 45)
    assert got.tobytes() == sent.tobytes()
    assert tx.stats == {"datagrams": 3, "records": 45, "send_errors": 0, "records_dropped": 0}
    assert rx.stats["datagrams"] == 3 and rx.stats["lost"] == 0
    assert all(rx.stats[k] == 0 for k in ("malformed", "rejected_peer", "unauthenticated", "bad_tag", "replayed"))


@needs_ground
def test_that_a_keyed_receiver_refuses_unauthenticated_datagrams():
    rx = LiveStreamReceiver(key=KEY)
    assert len(rx.feed(encode_datagram(0, records(4)))) == 0
    assert rx.stats["unauthenticated"] == 1 and rx.stats["datagrams"] == 0 and "version 1" in rx.last_error
    with pytest.raises(StreamAuthError) as err:
        parse_datagram(encode_datagram(0, records(1)), key=KEY)
    assert err.value.reason == "unauthenticated"


@needs_ground
@pytest.mark.parametrize("offset", [0, 4, 6, 8, 12, 16, 21, 22, 23, AUTH_HEADER_SIZE + 5, -TAG_SIZE, -1])
def test_that_a_tampered_datagram_fails_its_tag(offset):
    data = bytearray(keyed(n=3))
    data[offset] ^= 0x01
    rx = LiveStreamReceiver(key=KEY)
    assert len(rx.feed(bytes(data))) == 0
    refused = rx.stats["bad_tag"] + rx.stats["malformed"]  # magic/version/flags/count: malformed before the tag
    assert refused == 1 and rx.stats["datagrams"] == 0
    if offset not in (0, 4, 5, 6):
        assert rx.stats["bad_tag"] == 1


@needs_ground
def test_that_a_datagram_tagged_with_another_key_is_refused():
    rx = LiveStreamReceiver(key=KEY)
    assert len(rx.feed(keyed(key=OTHER_KEY))) == 0
    assert rx.stats["bad_tag"] == 1
    with pytest.raises(StreamAuthError) as err:
        parse_datagram(keyed(key=OTHER_KEY), key=KEY)
    assert err.value.reason == "bad_tag"


@needs_ground
def test_that_a_replayed_datagram_is_refused_but_a_reordered_one_is_used_once():
    rx = LiveStreamReceiver(key=KEY)
    t = now_stamp()
    first, second, third = keyed(0, stamp=t), keyed(1, stamp=t + 1000), keyed(2, stamp=t + 2000)
    assert len(rx.feed(first)) == 3 and len(rx.feed(third)) == 3
    assert len(rx.feed(second)) == 3  # late (10 ms behind), never seen: used
    assert rx.stats["late"] == 1
    for again in (first, second, third):
        assert len(rx.feed(again)) == 0
    assert rx.stats["replayed"] == 3 and rx.stats["datagrams"] == 3
    stale = keyed(3, stamp=t + 2000 - round(LATE_WINDOW_S * 100_000) - 1)  # unseen, but beyond the window
    assert len(rx.feed(stale)) == 0 and rx.stats["replayed"] == 4


@needs_ground
def test_that_a_capture_played_back_to_a_restarted_receiver_is_refused():
    old = keyed(stamp=now_stamp(-3600.0))  # recorded an hour ago
    rx = LiveStreamReceiver(key=KEY)
    assert len(rx.feed(old)) == 0 and rx.stats["replayed"] == 1
    assert len(rx.feed(keyed(stamp=now_stamp(-30.0)))) == 3  # half a minute of clock skew is fine
    lenient = LiveStreamReceiver(key=KEY, new_sender_max_age_s=None)
    assert len(lenient.feed(old)) == 3


@needs_ground
def test_that_replay_state_is_kept_per_sender_id_and_a_restarted_sender_is_accepted():
    rx = LiveStreamReceiver(key=KEY)
    t = now_stamp()
    assert len(rx.feed(keyed(0, stamp=t, sender_id=1))) == 3
    assert len(rx.feed(keyed(0, stamp=t, sender_id=2))) == 3  # same stamp, other sender
    assert len(rx.feed(keyed(0, stamp=t, sender_id=1))) == 0
    sock = CaptureSocket()
    for _ in range(2):  # the payload restarts: sequence back to 0, stamps still rising
        tx = LiveStreamSender("udp:127.0.0.1:14600", records_per_datagram=2, key=KEY, sender_id=1, sock=sock)
        tx.append(records(2))
        tx.close()
    assert [len(rx.feed(d)) for d in sock.sent] == [2, 2]
    assert rx.stats["replayed"] == 1 and rx.stats["restarts"] >= 1


def test_that_sender_stamps_strictly_increase_on_a_stopped_clock():
    sock = CaptureSocket()
    tx = LiveStreamSender("udp:127.0.0.1:14600", records_per_datagram=1, key=KEY, sock=sock,
                          stamp_source=lambda: 5_000)
    tx.append(records(4))
    stamps = [parse_datagram(d, key=KEY).stamp for d in sock.sent]
    assert stamps == [5_000, 5_001, 5_002, 5_003]


@needs_ground
def test_that_datagrams_from_peers_not_allowed_are_refused():
    with LiveStreamReceiver("udp:127.0.0.1:0", key=KEY, allowed_peers=[("127.0.0.1", 9)]) as rx:
        tx = LiveStreamSender(f"udp:127.0.0.1:{rx.local_address[1]}", records_per_datagram=5, key=KEY)
        tx.append(records(10))
        tx.close()
        deadline = time.monotonic() + 5.0
        while rx.stats["rejected_peer"] < 2 and time.monotonic() < deadline:
            assert len(rx.poll()) == 0
            time.sleep(0.01)
    assert rx.stats["rejected_peer"] == 2 and rx.stats["datagrams"] == 0
    allowed = LiveStreamReceiver(allowed_peers=["localhost", ("10.0.0.2", 14600)])
    assert len(allowed.feed(encode_datagram(0, records(1)), ("127.0.0.1", 5555))) == 1
    assert len(allowed.feed(encode_datagram(1, records(1)), ("10.0.0.2", 14600))) == 1
    assert len(allowed.feed(encode_datagram(2, records(1)), ("10.0.0.2", 14601))) == 0
    assert len(allowed.feed(encode_datagram(3, records(1)), ("::ffff:10.0.0.2", 14600))) == 1
    assert len(allowed.feed(encode_datagram(4, records(1)))) == 0  # no peer given: refused
    assert allowed.stats["rejected_peer"] == 2


@needs_ground
@pytest.mark.parametrize(("peers", "word"), [
    (("127.0.0.1", 5000), "list"),
    ([("127.0.0.1", 0)], "port"),
    ([("127.0.0.1",)], "host, port"),
    ([""], "non-empty"),
    (["no-such-host.invalid"], "does not resolve"),
])
def test_that_bad_allowed_peers_are_refused_at_start(peers, word):
    with pytest.raises(ValueError, match=word):
        LiveStreamReceiver(allowed_peers=peers)


@needs_ground
def test_that_a_receiver_without_a_key_uses_authenticated_datagrams_unchecked():
    rx = LiveStreamReceiver()
    assert len(rx.feed(keyed())) == 3 and rx.stats["unverified"] == 1


@needs_ground
@pytest.mark.parametrize("key", [b"short", "x" * 32, bytes(31)])
def test_that_a_bad_key_is_refused(key):
    with pytest.raises(ValueError, match="32 bytes"):
        LiveStreamSender("udp:127.0.0.1:14600", key=key)
    with pytest.raises(ValueError, match="32 bytes"):
        LiveStreamReceiver(key=key)


class CaptureSocket:
    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def sendto(self, data, addr):
        self.sent.append(bytes(data))

    def close(self):
        pass
