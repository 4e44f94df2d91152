import math
import random
import time
from importlib.util import find_spec

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.mavlink_link import (
    COMPANION_COMPONENT_ID,
    ByteStreamLink,
    MavlinkFramer,
    PymavlinkLink,
    heartbeat_msg,
    mavutil_device,
    open_mavlink,
    register_mavlink_backend,
    unregister_mavlink_backend,
)
from tests.firmware_py.byte_pipe import BytePipe

SIM = find_spec("sitl") is not None  # False on the payload-only install (Raspberry Pi): those tests skip
if SIM:
    from sitl.mavlink.server import MavlinkVehicleServer
    from sitl.mavlink.transport import UdpTransport
    from sitl.vehicle.kinematic_vehicle import KinematicVehicle

needs_sim = pytest.mark.skipif(not SIM, reason="needs the simulator (sitl/), not in the payload-only install")

AP = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)


def frame(msg, mav=AP) -> bytes:
    buf = bytes(msg.pack(mav))
    mav.seq = (mav.seq + 1) % 256
    return buf


def timesync_frame(n: int, mav=AP) -> bytes:
    return frame(mavlink.MAVLink_timesync_message(n + 1, n), mav)


def link_pair() -> tuple[ByteStreamLink, ByteStreamLink]:
    a_end, b_end = BytePipe.pair()
    return ByteStreamLink(a_end.send, a_end.recv), ByteStreamLink(b_end.send, b_end.recv, source_system=1,
                                                                   source_component=1)


class Feed:
    """recv_bytes for a ByteStreamLink: hands out queued chunks one per call."""

    def __init__(self, *chunks: bytes) -> None:
        self.chunks = list(chunks)
        self.sent: list[bytes] = []

    def recv(self) -> bytes:
        return self.chunks.pop(0) if self.chunks else b""

    def send(self, data: bytes) -> None:
        self.sent.append(data)


# ----- messages and framing --------------------------------------------------------------------------

def test_heartbeat_msg_announces_an_onboard_controller_without_autopilot():
    hb = heartbeat_msg()
    assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER
    assert hb.autopilot == mavlink.MAV_AUTOPILOT_INVALID
    assert hb.system_status == mavlink.MAV_STATE_ACTIVE


def test_byte_stream_links_exchange_mavlink2_messages_with_our_ids_and_sequence():
    companion, autopilot = link_pair()
    companion.send(heartbeat_msg())
    companion.send(mavlink.MAVLink_timesync_message(0, 42))
    got = autopilot.recv()
    assert [m.get_type() for m in got] == ["HEARTBEAT", "TIMESYNC"]
    assert all((m.get_srcSystem(), m.get_srcComponent()) == (1, COMPANION_COMPONENT_ID) for m in got)
    assert [m.get_seq() for m in got] == [0, 1]
    assert got[1].ts1 == 42
    assert got[0].get_msgbuf()[0] == mavlink.PROTOCOL_MARKER_V2
    assert companion.stats["tx_messages"] == 2 and autopilot.stats["rx_messages"] == 2


def test_recv_returns_nothing_and_never_blocks_when_no_bytes_arrived():
    companion, _ = link_pair()
    assert companion.recv() == []


def test_a_frame_split_across_reads_is_reassembled():
    data = timesync_frame(7)
    feed = Feed(*[data[i:i + 1] for i in range(len(data))])
    link = ByteStreamLink(feed.send, feed.recv)
    got = []
    for _ in range(len(data)):
        got += link.recv()
    assert [m.ts1 for m in got] == [7]
    assert link.stats["rx_bad_bytes"] == 0


def test_garbage_between_frames_is_counted_and_the_frames_survive():
    garbage = bytes([0x00, 0x55, 0xAA, 0x13, 0x37])
    feed = Feed(garbage + timesync_frame(1) + garbage + timesync_frame(2))
    link = ByteStreamLink(feed.send, feed.recv)
    assert [m.ts1 for m in link.recv()] == [1, 2]
    assert link.stats["rx_bad_bytes"] == 2 * len(garbage)


def test_a_corrupt_length_byte_costs_one_frame_not_the_frames_after_it():
    bad = bytearray(timesync_frame(1))
    bad[1] = 250  # claims a 250-byte payload: pymavlink's own parser would swallow what follows
    good = b"".join(timesync_frame(n) for n in range(2, 32))
    feed = Feed(bytes(bad) + good)
    link = ByteStreamLink(feed.send, feed.recv)
    assert [m.ts1 for m in link.recv()] == list(range(2, 32))
    assert link.stats["rx_bad_frames"] >= 1


def test_a_frame_with_a_flipped_payload_bit_is_dropped_by_its_crc():
    bad = bytearray(timesync_frame(1))
    bad[12] ^= 0x01
    feed = Feed(bytes(bad) + timesync_frame(2))
    link = ByteStreamLink(feed.send, feed.recv)
    assert [m.ts1 for m in link.recv()] == [2]
    assert link.stats["rx_bad_frames"] >= 1


def test_seeded_noise_with_magic_bytes_never_raises_and_every_valid_frame_is_recovered():
    rng = random.Random(1234)
    stream = bytearray()
    for n in range(200):
        noise = bytes(rng.choice([0xFD, 0xFE, rng.randrange(256)]) for _ in range(rng.randrange(0, 40)))
        stream += noise + timesync_frame(n)
    stream += b"".join(frame(heartbeat_msg()) for _ in range(20))  # resolves a false header at the very end
    chunks, i = [], 0
    while i < len(stream):
        k = rng.randrange(1, 300)
        chunks.append(bytes(stream[i:i + k]))
        i += k
    feed = Feed(*chunks)
    link = ByteStreamLink(feed.send, feed.recv)
    got = []
    for _ in chunks:
        got += link.recv()
    assert [m.ts1 for m in got if m.get_type() == "TIMESYNC"] == list(range(200))
    assert link.stats["rx_bad_bytes"] > 0


def test_frames_of_unknown_message_ids_are_skipped_and_counted():
    unknown = bytearray(timesync_frame(1))
    unknown[7:10] = (0xABCDEF).to_bytes(3, "little")  # no such message in the dialect
    feed = Feed(bytes(unknown) + timesync_frame(2))
    link = ByteStreamLink(feed.send, feed.recv)
    assert [m.ts1 for m in link.recv()] == [2]
    assert link.stats["rx_bad_frames"] >= 1


def test_sequence_gaps_are_counted_as_lost_frames():
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    frames = [timesync_frame(n, mav) for n in range(10)]
    feed = Feed(b"".join(frames[:3] + frames[6:]))  # 3, 4, 5 lost on the wire
    link = ByteStreamLink(feed.send, feed.recv)
    assert len(link.recv()) == 7
    assert link.stats["rx_seq_lost"] == 3


def test_framer_parses_mavlink1_frames_too():
    mav1 = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    data = bytes(heartbeat_msg().pack(mav1, force_mavlink1=True))
    assert data[0] == mavlink.PROTOCOL_MARKER_V1
    assert [m.get_type() for m in MavlinkFramer().feed(data)] == ["HEARTBEAT"]


def test_a_failing_write_is_counted_not_raised():
    def broken(_data: bytes) -> None:
        raise OSError("link down")

    link = ByteStreamLink(broken, lambda: b"")
    link.send(heartbeat_msg())
    assert link.stats["tx_errors"] == 1 and link.stats["tx_messages"] == 0
    assert "link down" in link.last_error


def test_a_closed_link_receives_nothing_and_refuses_to_send():
    closed = []
    companion_end, autopilot_end = BytePipe.pair()
    link = ByteStreamLink(companion_end.send, companion_end.recv, close=lambda: closed.append(True))
    autopilot_end.send(timesync_frame(1))
    link.close()
    assert closed == [True]
    assert link.recv() == []
    with pytest.raises(ValueError, match="closed"):
        link.send(heartbeat_msg())


@pytest.mark.parametrize("field,value", [("source_system", 0), ("source_component", 256)])
def test_bad_source_ids_are_refused_naming_the_value(field, value):
    with pytest.raises(ValueError, match=f"{field}.*{value}"):
        ByteStreamLink(lambda _d: None, lambda: b"", **{field: value})


# ----- URLs and the factory --------------------------------------------------------------------------

@pytest.mark.parametrize("url,device", [
    ("serial:/dev/ttyAMA0:921600", ("/dev/ttyAMA0", 921600)),
    ("serial:/dev/ttyUSB0:57600", ("/dev/ttyUSB0", 57600)),
    ("serial:/dev/serial0", ("/dev/serial0", 921600)),
    ("udp:127.0.0.1:14550", ("udpin:127.0.0.1:14550", 0)),
    ("udpin:0.0.0.0:14550", ("udpin:0.0.0.0:14550", 0)),
    ("udp:127.0.0.1:0", ("udpin:127.0.0.1:0", 0)),
    ("udpout:192.168.1.10:14550", ("udpout:192.168.1.10:14550", 0)),
    ("tcp:localhost:5760", ("tcp:localhost:5760", 0)),
])
def test_our_url_forms_translate_to_mavutil_devices(url, device):
    assert mavutil_device(url) == device


@pytest.mark.parametrize("url", [
    "", "serial", "serial:", "serial::921600", "serial:/dev/ttyAMA0:", "serial:/dev/ttyAMA0:12",
    "udp:14550", "udp:127.0.0.1:", "udp:127.0.0.1:port", "udp:127.0.0.1:70000", "udpout:127.0.0.1:0",
    "udpout::14550", "tcp:host", "bogus:127.0.0.1:14550", "/dev/ttyAMA0",
])
def test_malformed_urls_are_a_clear_value_error(url):
    with pytest.raises(ValueError, match="MAVLink"):
        mavutil_device(url)


class FakeConnection:
    def __init__(self, device, **kwargs):
        self.device, self.kwargs = device, kwargs
        self.written: list[bytes] = []
        self.inbox: list[bytes] = []
        self.closed = False

    def recv(self, n=None):
        if self.inbox:
            item = self.inbox.pop(0)
            if isinstance(item, Exception):
                raise item
            return item
        return ""

    def write(self, buf):
        self.written.append(bytes(buf))
        return len(buf)

    def close(self):
        self.closed = True


def test_a_serial_url_opens_the_device_at_its_baud_with_our_ids():
    opened = []
    link = PymavlinkLink("serial:/dev/ttyAMA0:921600", connect=lambda d, **kw: opened.append(FakeConnection(d, **kw))
                         or opened[-1])
    conn = opened[0]
    assert conn.device == "/dev/ttyAMA0"
    assert conn.kwargs == {"baud": 921600, "source_system": 1, "source_component": 191}
    assert conn.written == []  # nothing is sent unasked on a serial link
    link.close()
    assert conn.closed


def test_a_udpout_link_sends_a_heartbeat_first_so_a_listening_autopilot_learns_our_address():
    opened = []
    PymavlinkLink("udpout:127.0.0.1:14550", connect=lambda d, **kw: opened.append(FakeConnection(d, **kw))
                  or opened[-1])
    conn = opened[0]
    assert conn.device == "udpout:127.0.0.1:14550"
    assert [m.get_type() for m in MavlinkFramer().feed(b"".join(conn.written))] == ["HEARTBEAT"]


def test_pymavlink_link_reads_everything_available_and_counts_io_errors():
    conn = FakeConnection("udpin:127.0.0.1:0")
    link = PymavlinkLink("udp:127.0.0.1:0", connect=lambda d, **kw: conn)
    conn.inbox = [timesync_frame(1), timesync_frame(2) + timesync_frame(3)]
    assert [m.ts1 for m in link.recv()] == [1, 2, 3]
    conn.inbox = [timesync_frame(4), OSError("device unplugged")]
    assert [m.ts1 for m in link.recv()] == [4]
    assert link.stats["io_errors"] == 1 and "unplugged" in link.last_error


def test_open_mavlink_uses_a_registered_backend_for_its_scheme():
    made = []

    def factory(url):
        made.append(url)
        return ByteStreamLink(lambda _d: None, lambda: b"")

    register_mavlink_backend("sitltest", factory)
    try:
        link = open_mavlink("sitltest:lockstep")
    finally:
        unregister_mavlink_backend("sitltest")
    assert made == ["sitltest:lockstep"]
    assert isinstance(link, ByteStreamLink)
    with pytest.raises(ValueError, match="unsupported MAVLink link scheme 'sitltest'"):
        open_mavlink("sitltest:lockstep")


@pytest.mark.parametrize("scheme", ["", "UDP", "udp", "serial", "a b"])
def test_registering_a_bad_or_builtin_scheme_is_refused(scheme):
    with pytest.raises(ValueError, match="scheme"):
        register_mavlink_backend(scheme, lambda url: None)


def test_open_mavlink_rejects_a_malformed_url_before_touching_hardware():
    with pytest.raises(ValueError, match="MAVLink"):
        open_mavlink("serial:")


# ----- real sockets against the SITL autopilot --------------------------------------------------------

def _serve_until(server, vehicle, link, wanted: set[str], timeout_s: float = 4.0) -> dict[str, object]:
    """Step the SITL autopilot in real time and collect the link's messages until all wanted types came."""
    seen: dict[str, object] = {}
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s and not wanted <= seen.keys():
        while vehicle.t_s < time.monotonic() - t0:
            vehicle.step()
        server.update()
        for m in link.recv():
            seen.setdefault(m.get_type(), m)
        if "HEARTBEAT" in seen and "TIMESYNC" not in seen:
            link.send(mavlink.MAVLink_timesync_message(0, 123_456))
        time.sleep(0.002)
    return seen


@needs_sim
def test_udpout_link_talks_to_the_sitl_autopilot_listening_on_udp():
    vehicle = KinematicVehicle(dt_s=0.01)
    transport = UdpTransport("udp:127.0.0.1:0")
    server = MavlinkVehicleServer(vehicle, transport)
    link = PymavlinkLink(f"udpout:127.0.0.1:{transport.local_address[1]}")
    try:
        seen = _serve_until(server, vehicle, link, {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "TIMESYNC"})
    finally:
        link.close()
        transport.close()
    assert {"HEARTBEAT", "ATTITUDE", "LOCAL_POSITION_NED", "TIMESYNC"} <= seen.keys()
    assert seen["HEARTBEAT"].type == mavlink.MAV_TYPE_QUADROTOR
    assert seen["TIMESYNC"].ts1 == 123_456 and seen["TIMESYNC"].tc1 > 0
    assert server.stats["rx_by_type"]["HEARTBEAT"] >= 1  # our first heartbeat taught it where we are
    assert link.stats["rx_bad_frames"] == 0 and math.isfinite(seen["ATTITUDE"].yaw)


@needs_sim
def test_listening_udp_link_hears_an_autopilot_that_sends_to_it():
    vehicle = KinematicVehicle(dt_s=0.01)
    link = PymavlinkLink("udp:127.0.0.1:0")
    transport = UdpTransport(f"udpout:127.0.0.1:{link.local_address[1]}")
    server = MavlinkVehicleServer(vehicle, transport)
    try:
        seen = _serve_until(server, vehicle, link, {"HEARTBEAT", "ATTITUDE", "TIMESYNC"})
    finally:
        link.close()
        transport.close()
    assert {"HEARTBEAT", "ATTITUDE", "TIMESYNC"} <= seen.keys()  # TIMESYNC: our replies reach it too
