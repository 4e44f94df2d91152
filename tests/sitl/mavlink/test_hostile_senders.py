"""The autopilot peer under hostile and careless senders: nothing stalls, nothing mixes, nothing grows.

Lockstep tests use the in-process pipe (deterministic); the routing tests use real UDP sockets on
loopback and step the server in the test's own thread, waiting on what arrives, never on time.
"""

import logging
import math
import os
import socket
import struct
import time

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink import ftp
from sitl.mavlink.ratelimit import Rate
from sitl.mavlink.server import LinkLimits, MavlinkVehicleServer
from sitl.mavlink.streams import SENSORS_PRESENT
from sitl.mavlink.transport import PipeTransport, UdpTransport
from tests.sitl.mavlink.lockstep_gcs import GCS_COMP, GCS_SYS, Gcs, count, fast_vehicle, survey_mission

TRUNCATED = bytes([0xFD, 255, 0, 0, 0, 7, 1, 0, 0, 0])  # a v2 header claiming 255 bytes, and nothing more


def texts(msgs) -> int:
    """STATUSTEXT messages, a chunked one counted once."""
    return sum(m.get_type() == "STATUSTEXT" and m.chunk_seq == 0 for m in msgs)


# ----- lockstep ---------------------------------------------------------------------------------------

def test_that_a_flood_of_refused_requests_gets_statustext_answers_at_the_rate_limit_only():
    gcs = Gcs()
    burst = int(LinkLimits().statustext.burst)
    for _ in range(5 * burst):
        gcs.send(gcs.mav.param_set_encode(1, 1, b"PS_ALT_M", math.nan, mavlink.MAV_PARAM_TYPE_REAL32))
    msgs = gcs.run(0.0)
    assert count(msgs, "PARAM_VALUE") == 5 * burst  # every refusal still reads the kept value back
    assert texts(msgs) == burst
    assert gcs.server.stats["statustext_dropped"] == 4 * burst
    later = gcs.run(2.0)  # the bucket refills at its rate
    gcs.send(gcs.mav.param_set_encode(1, 1, b"PS_ALT_M", math.nan, mavlink.MAV_PARAM_TYPE_REAL32))
    assert texts(later + gcs.run(0.0)) == 1


def test_that_the_tlog_stops_at_its_cap_with_one_warning(tmp_path, caplog):
    path = tmp_path / "t.tlog"
    vehicle = fast_vehicle()
    server_end, _client = PipeTransport.pair()
    cap = 5_000
    caplog.set_level(logging.WARNING, logger="sitl")
    with MavlinkVehicleServer(vehicle, server_end, tlog_path=path, limits=LinkLimits(tlog_max_bytes=cap)) as server:
        for _ in range(round(3.0 / vehicle.dt_s)):
            vehicle.step()
            server.update()
        assert server.stats["tlog_full"]
    assert 0 < path.stat().st_size <= cap
    warnings = [r.getMessage() for r in caplog.records if "reached its cap" in r.getMessage()]
    assert len(warnings) == 1 and "--tlog-max-mb" in warnings[0]


def test_that_what_one_sender_makes_us_log_is_rate_limited(tmp_path):
    path = tmp_path / "t.tlog"
    gcs = Gcs()
    gcs.server = MavlinkVehicleServer(gcs.vehicle, gcs.server.transport, tlog_path=path,
                                      limits=LinkLimits(tlog_rx=Rate(per_s=10.0, burst=50)))
    for _ in range(1000):
        gcs.send(gcs.mav.param_request_read_encode(1, 1, b"", 0))
    msgs = gcs.run(0.0)
    assert count(msgs, "PARAM_VALUE") == 1000  # every request is answered...
    gcs.server.close()
    assert gcs.server.stats["tlog_frames_skipped"] == 2000 - 50  # ...but only a burst of them is logged
    assert path.stat().st_size < 50 * 60 + 20_000


def test_that_sys_status_reports_healthy_sensors_and_no_fence_breach():
    gcs = Gcs()
    m = gcs.expect("SYS_STATUS")
    assert m.onboard_control_sensors_present == SENSORS_PRESENT
    assert m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_GEOFENCE
    assert m.onboard_control_sensors_health & SENSORS_PRESENT == SENSORS_PRESENT
    assert not m.onboard_control_sensors_enabled & mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS  # disarmed


def test_that_mavlink_ftp_is_refused_at_once_with_a_nak_to_the_asker():
    gcs = Gcs()
    request = struct.pack("<HBBBBBBI", 41, 7, 4, 8, 0, 0, 0, 0) + b"@PARAM/x"  # OpenFileRO, seq 41, session 7
    gcs.send(gcs.mav.file_transfer_protocol_encode(0, 1, 1, list(request.ljust(251, b"\0"))))
    reply = gcs.expect("FILE_TRANSFER_PROTOCOL", within_s=0.0)
    seq, session, opcode, size, req_opcode = struct.unpack("<HBBBB", bytes(reply.payload[:6]))
    assert (seq, session, opcode, size, req_opcode) == (42, 7, ftp.OP_NAK, 1, 4)
    assert reply.payload[12] == ftp.ERR_UNKNOWN_COMMAND
    assert (reply.target_system, reply.target_component) == (GCS_SYS, GCS_COMP)
    nak = struct.pack("<HBBBBBBI", 1, 7, ftp.OP_NAK, 1, 4, 0, 0, 0) + b"\x07"
    gcs.send(gcs.mav.file_transfer_protocol_encode(0, 1, 1, list(nak.ljust(251, b"\0"))))
    assert count(gcs.run(0.1), "FILE_TRANSFER_PROTOCOL") == 0  # a reply is never answered


def test_that_the_operator_is_told_about_arming_modes_and_missions(caplog):
    caplog.set_level(logging.INFO, logger="sitl")
    gcs = Gcs()
    gcs.run(0.1)
    assert gcs.upload(survey_mission()) == mavlink.MAV_MISSION_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    gcs.run(0.1)
    text = "\n".join(r.getMessage() for r in caplog.records)
    assert "mission uploaded: 6 items after home" in text and "vehicle armed" in text


# ----- over UDP: per-sender parsing, admission, replies to the asker ----------------------------------

class Udp:
    """A server on a loopback UDP port, stepped by the test, and raw client sockets."""

    def __init__(self, max_peers: int = 8) -> None:
        self.vehicle = fast_vehicle()
        self.transport = UdpTransport("udp:127.0.0.1:0", max_peers=max_peers)
        self.server = MavlinkVehicleServer(self.vehicle, self.transport)
        self.socks: list[socket.socket] = []

    def client(self, sysid: int) -> tuple[socket.socket, mavlink.MAVLink]:
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        self.socks.append(s)
        return s, mavlink.MAVLink(None, srcSystem=sysid, srcComponent=190)

    def send(self, sock: socket.socket, mav: mavlink.MAVLink, msg) -> None:
        sock.sendto(bytes(msg.pack(mav)), self.transport.local_address)
        mav.seq = (mav.seq + 1) % 256

    def step_until(self, cond, what: str, timeout_s: float = 20.0) -> None:
        """Step the server until cond() (an observable event); fails only if it never happens."""
        deadline = time.monotonic() + timeout_s
        while not cond():
            assert time.monotonic() < deadline, f"never: {what}"
            self.vehicle.step()
            self.server.update()
            time.sleep(0.0005)

    def close(self) -> None:
        for s in self.socks:
            s.close()
        self.transport.close()


def received(sock: socket.socket, into: list) -> list:
    """Drain sock into `into` (decoded messages); returns it."""
    mav = mavlink.MAVLink(None)
    while True:
        try:
            data = sock.recv(65535)
        except BlockingIOError:
            return into
        into.extend(mav.parse_buffer(data) or [])


def test_that_random_bytes_never_make_a_sender_a_client():
    udp = Udp()
    try:
        junk, _ = udp.client(7)
        for k in range(50):
            junk.sendto(os.urandom(1 + k) if k % 2 else TRUNCATED, udp.transport.local_address)
        udp.step_until(lambda: udp.server.stats["rx_datagrams_dropped"] == 50, "all 50 junk datagrams dropped")
        assert udp.transport.peers == [] and udp.server.stats["rx_messages"] == 0
        assert received(junk, []) == []
    finally:
        udp.close()


def test_that_a_truncated_header_from_one_sender_does_not_hold_back_another_senders_request():
    udp = Udp()
    try:
        junk, _ = udp.client(7)
        gcs, mav = udp.client(GCS_SYS)
        junk.sendto(TRUNCATED, udp.transport.local_address)
        udp.send(gcs, mav, mav.param_request_read_encode(1, 1, b"PS_ALT_M", -1))
        got: list = []
        udp.step_until(lambda: any(m.get_type() == "PARAM_VALUE" for m in received(gcs, got)), "the reply")
        assert udp.server.stats["rx_drops"] == {"truncated": 1}
        assert udp.transport.peers == [gcs.getsockname()]
    finally:
        udp.close()


def test_that_replies_to_one_client_never_reach_another():
    udp = Udp()
    try:
        good, gmav = udp.client(GCS_SYS)
        bad, bmav = udp.client(66)
        udp.send(good, gmav, gmav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
        udp.step_until(lambda: len(udp.transport.peers) == 1, "the ground station is a client")
        for msg in (bmav.command_long_encode(1, 1, 31_000, 0, *[math.nan] * 7),
                    bmav.param_set_encode(1, 1, b"PS_ALT_M", math.nan, mavlink.MAV_PARAM_TYPE_REAL32),
                    bmav.mission_count_encode(1, 1, 65535, 0),
                    bmav.timesync_encode(0, 5)):
            udp.send(bad, bmav, msg)
        theirs: list = []
        want = {"COMMAND_ACK", "PARAM_VALUE", "MISSION_ACK", "TIMESYNC", "STATUSTEXT"}
        udp.step_until(lambda: want <= {m.get_type() for m in received(bad, theirs)}, "the bad sender's replies")
        udp.send(good, gmav, gmav.param_request_read_encode(1, 1, b"PS_SPEED_MS", -1))
        ours: list = []
        udp.step_until(lambda: any(m.get_type() == "PARAM_VALUE" for m in received(good, ours)), "our reply")
        not_telemetry = [m.get_type() for m in ours if m.get_type() not in (
            "HEARTBEAT", "SYS_STATUS", "SYSTEM_TIME", "ATTITUDE", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT",
            "VFR_HUD", "MISSION_CURRENT")]
        assert not_telemetry == ["PARAM_VALUE"]  # only the answer to our own request
        assert [m.param_id for m in ours if m.get_type() == "PARAM_VALUE"] == ["PS_SPEED_MS"]
    finally:
        udp.close()


def test_that_senders_refused_by_a_full_client_table_share_one_statustext_budget():
    udp = Udp(max_peers=1)
    try:
        gcs, gmav = udp.client(GCS_SYS)
        udp.send(gcs, gmav, gmav.heartbeat_encode(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0))
        udp.step_until(lambda: len(udp.transport.peers) == 1, "the ground station is the client")
        burst = int(LinkLimits().statustext.burst)
        strangers = [udp.client(60 + k) for k in range(10)]
        for sock, mav in strangers:
            for _ in range(burst):
                udp.send(sock, mav, mav.param_set_encode(1, 1, b"NO_SUCH", 1.0, mavlink.MAV_PARAM_TYPE_REAL32))
        udp.step_until(lambda: udp.server.stats["rx_by_type"]["PARAM_SET"] == 10 * burst, "every PARAM_SET handled")
        got = [m for sock, _ in strangers for m in received(sock, [])]
        assert texts(got) <= burst  # not 10 x burst: ten source ports get no more than one sender
        assert udp.transport.peers == [gcs.getsockname()] and udp.transport.peers_refused >= 10
    finally:
        udp.close()


def test_that_the_faulted_serve_link_reports_a_full_client_table_too():
    from sitl.devices.networked import FaultyTransport
    from sitl.faults.injector import FaultSpec
    from sitl.faults.params import LiveFaultInjector

    inner = UdpTransport("udp:127.0.0.1:0", max_peers=1)
    try:
        faulty = FaultyTransport(inner, LiveFaultInjector(FaultSpec()), lambda: 0)
        assert faulty.add_peer(("127.0.0.1", 1001)) is True
        assert faulty.add_peer(("127.0.0.1", 1002)) is False  # the server then answers it as a stranger
    finally:
        inner.close()
