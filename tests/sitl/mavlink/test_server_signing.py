"""The SITL autopilot with MAVLink 2 signing: the payload's link and pose tracker with the same key fly
on signed poses; with another key nothing gets through either way (and it is counted); a real
third-party client (pymavlink's mavutil with setup_signing) talks to it over UDP, and an unsigned one
is ignored, not even answered."""

from __future__ import annotations

import time

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.clock import SimClock
from firmware_py.hal.mavlink_link import ByteStreamLink, heartbeat_msg
from firmware_py.hal.signing import SigningConfig
from firmware_py.pose_tracker import PoseTracker
from sitl.mavlink.server import MavlinkVehicleServer
from sitl.mavlink.transport import PipeTransport, UdpTransport
from sitl.vehicle.api import FlightMode, NavItem, NavKind
from sitl.vehicle.kinematic_vehicle import KinematicVehicle

mavutil.set_dialect("ardupilotmega")  # MAVLink 2, whatever imported mavutil first

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(2, 34))
OFFSET_NS = 9_000_000_000  # the companion's clock runs ahead of the autopilot's boot clock
DT_S = 0.002


class LockstepRig:
    """Vehicle + signed SITL autopilot <-pipe-> signed ByteStreamLink + PoseTracker, on one simulated clock."""

    def __init__(self, server_key: bytes | None, payload_key: bytes | None) -> None:
        self.vehicle = KinematicVehicle(dt_s=DT_S, speed_m_s=2.0, altitude_m=5.0)
        server_end, payload_end = PipeTransport.pair()
        self.server = MavlinkVehicleServer(
            self.vehicle, server_end, signing=SigningConfig(server_key) if server_key else None)
        self.link = ByteStreamLink(payload_end.send, payload_end.recv,
                                   signing=SigningConfig(payload_key, link_id=1) if payload_key else None)
        self.clock = SimClock(start_ns=OFFSET_NS)
        self.tracker = PoseTracker(self.link, self.clock)
        self.vehicle.set_mode(FlightMode.GUIDED)
        self.vehicle.arm()
        self.vehicle.load_mission([NavItem(NavKind.TAKEOFF, 0.0, 0.0, -5.0),
                                   NavItem(NavKind.WAYPOINT, 10.0, 0.0, -5.0)])
        self.vehicle.start_mission()
        self.tracker.start()

    def run(self, seconds: float) -> None:
        for _ in range(round(seconds / DT_S)):
            self.vehicle.step()
            self.clock.set_ns(OFFSET_NS + round(self.vehicle.state().t_s * 1e9))
            self.server.update()
            self.tracker.pump()

    def pose(self):
        return self.tracker.pose_at(self.clock.now_ns() - 20_000_000)


def test_with_the_same_key_signed_poses_flow_to_the_pose_tracker():
    rig = LockstepRig(KEY, KEY)
    rig.run(3.0)
    pose = rig.pose()
    assert pose.usable, rig.tracker.status().pose_status
    assert -5.0 <= pose.pos_ned_m[2] < -0.1  # climbing
    link, server = rig.link.stats, rig.server.stats
    assert link["rx_signed"] == link["rx_messages"] > 100
    assert link["rx_unsigned"] == link["rx_bad_signature"] == link["rx_replayed"] == 0
    assert server["rx_signed"] == server["rx_messages"] > 10 and server["rx_by_type"]["COMMAND_LONG"] >= 2
    assert server["rx_unsigned"] == server["rx_bad_signature"] == server["rx_replayed"] == 0


def test_with_different_keys_nothing_is_accepted_and_both_sides_count_it():
    rig = LockstepRig(KEY, OTHER_KEY)
    rig.run(2.0)
    assert not rig.pose().usable
    link, server = rig.link.stats, rig.server.stats
    assert link["rx_messages"] == 0 and link["rx_bad_signature"] > 100
    assert server["rx_messages"] == 0 and server["rx_bad_signature"] > 10
    assert link["rx_bad_frames"] == 0 and server["rx_parse_errors"] == 0  # refused, not taken for noise
    assert server["rx_by_type"]["COMMAND_LONG"] == 0


@pytest.mark.parametrize(("server_key", "payload_key", "refused_by"), [(KEY, None, "server"), (None, KEY, "link")])
def test_a_signed_end_refuses_an_unsigned_peer(server_key, payload_key, refused_by):
    rig = LockstepRig(server_key, payload_key)
    rig.run(1.0)
    assert not rig.pose().usable
    stats = rig.server.stats if refused_by == "server" else rig.link.stats
    assert stats["rx_unsigned"] > 0 and stats["rx_messages"] == 0


def test_the_server_without_a_key_is_as_before():
    rig = LockstepRig(None, None)
    rig.run(3.0)
    assert rig.pose().usable
    assert rig.server.stats["rx_signed"] == 0 and rig.link.stats["rx_signed"] == 0
    assert rig.link.stats["rx_messages"] > 100


def test_a_replayed_command_is_not_run_twice():
    rig = LockstepRig(KEY, KEY)
    rig.run(0.5)
    before = rig.server.stats["rx_by_type"]["COMMAND_LONG"]
    mav = rig.link.mav
    msg = mav.command_long_encode(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                  mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
    frame = rig.link.signer.pack(msg, mav)
    pipe = rig.server.transport
    pipe._peer.send(frame)  # the payload's end of the pipe, as if the link had sent it
    rig.server.update()
    pipe._peer.send(frame)  # and the same bytes again: a replay
    rig.server.update()
    assert rig.server.stats["rx_by_type"]["COMMAND_LONG"] == before + 1
    assert rig.server.stats["rx_replayed"] == 1


# ----- a real third-party client over UDP -----------------------------------------------------------

def _serve(server, vehicle, conn, until, timeout_s: float = 4.0, on_message=None) -> list:
    """Run the autopilot in real time; collect what the mavutil client receives until until(msgs)."""
    got: list = []
    t0 = time.monotonic()
    last_hb = -1.0
    while time.monotonic() - t0 < timeout_s and not until(got):
        now = time.monotonic() - t0
        while vehicle.t_s < now:
            vehicle.step()
        server.update()
        if now - last_hb >= 0.5:
            conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            last_hb = now
        while (m := conn.recv_match(blocking=False)) is not None:
            got.append(m)
            if on_message is not None:
                on_message(m)
        time.sleep(0.002)
    return got


@pytest.fixture
def signed_autopilot():
    vehicle = KinematicVehicle(dt_s=0.01)
    transport = UdpTransport("udp:127.0.0.1:0")
    server = MavlinkVehicleServer(vehicle, transport, signing=SigningConfig(KEY))
    yield vehicle, transport, server
    transport.close()


def test_pymavlink_mavutil_with_setup_signing_talks_to_the_signed_server(signed_autopilot):
    vehicle, transport, server = signed_autopilot
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{transport.local_address[1]}", source_system=255,
                                      source_component=190)
    conn.setup_signing(KEY, sign_outgoing=True, link_id=3)
    asked = []

    def ask(m):
        if m.get_type() == "HEARTBEAT" and not asked:
            conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                       mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
            asked.append(True)

    try:
        got = _serve(server, vehicle, conn, lambda ms: {"AUTOPILOT_VERSION", "ATTITUDE"} <= {m.get_type() for m in ms},
                     on_message=ask)
    finally:
        conn.close()
    kinds = {m.get_type() for m in got}
    assert {"HEARTBEAT", "ATTITUDE", "COMMAND_ACK", "AUTOPILOT_VERSION"} <= kinds
    assert all(m.get_signed() for m in got)  # pymavlink checked every signature we sent
    assert conn.mav.signing.goodsig_count == len(got) and conn.mav.signing.badsig_count == 0
    assert server.stats["rx_signed"] >= 2 and server.stats["rx_by_type"]["COMMAND_LONG"] == 1
    assert server.stats["rx_unsigned"] == server.stats["rx_bad_signature"] == 0


@pytest.mark.parametrize("client_key", [None, OTHER_KEY])
def test_a_client_without_the_key_is_ignored_and_never_answered(signed_autopilot, client_key):
    vehicle, transport, server = signed_autopilot
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{transport.local_address[1]}", source_system=255,
                                      source_component=190)
    if client_key is not None:
        conn.setup_signing(client_key, sign_outgoing=True, link_id=3)
    try:
        for _ in range(3):
            conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        got = _serve(server, vehicle, conn, lambda _ms: False, timeout_s=0.6)
    finally:
        conn.close()
    assert got == []  # not even telemetry: the server never learnt where it is
    assert transport.peers == [] and server.stats["rx_messages"] == 0
    refused = server.stats["rx_unsigned"] if client_key is None else server.stats["rx_bad_signature"]
    assert refused >= 4  # 3 commands and at least one heartbeat
    assert not vehicle.state().armed


def test_a_signed_server_answers_only_the_signed_client_when_both_talk(signed_autopilot):
    vehicle, transport, server = signed_autopilot
    url = f"udpout:127.0.0.1:{transport.local_address[1]}"
    good = mavutil.mavlink_connection(url, source_system=255, source_component=190)
    good.setup_signing(KEY, sign_outgoing=True, link_id=1)
    bad = mavutil.mavlink_connection(url, source_system=254, source_component=190)
    try:
        bad.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        got = _serve(server, vehicle, good, lambda ms: sum(m.get_type() == "ATTITUDE" for m in ms) >= 3)
        assert bad.recv_match(blocking=False) is None
    finally:
        good.close()
        bad.close()
    assert sum(m.get_type() == "ATTITUDE" for m in got) >= 3
    assert len(transport.peers) == 1 and server.stats["rx_unsigned"] >= 1


def test_the_payload_heartbeat_is_signed_on_the_wire():
    a_end, b_end = PipeTransport.pair()
    link = ByteStreamLink(a_end.send, a_end.recv, signing=SigningConfig(KEY, link_id=4))
    link.send(heartbeat_msg())
    frame = b_end.recv()
    assert frame[2] & mavlink.MAVLINK_IFLAG_SIGNED and frame[-13] == 4
    rx = mavlink.MAVLink(None)
    rx.signing.secret_key = KEY
    assert rx.parse_char(frame).get_type() == "HEARTBEAT" and rx.signing.goodsig_count == 1
