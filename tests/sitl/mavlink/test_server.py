"""The server as a whole: framing, TIMESYNC, the tlog, STATUSTEXT chunking, run_realtime, real UDP."""

import os
import random
import threading
import time

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink.server import MavlinkVehicleServer, run_realtime
from sitl.mavlink.streams import TLOG_EPOCH_US
from sitl.mavlink.transport import PipeTransport, UdpTransport
from sitl.vehicle.api import FlightMode
from tests.sitl.mavlink.lockstep_gcs import (
    GCS_COMP,
    GCS_SYS,
    Gcs,
    count,
    fast_vehicle,
    survey_mission,
)


def test_that_timesync_requests_are_answered_with_simulated_nanoseconds_and_the_request_echoed():
    gcs = Gcs()
    gcs.run(1.23)
    gcs.send(gcs.mav.timesync_encode(0, 987_654_321))
    reply = gcs.expect("TIMESYNC")
    assert (reply.tc1, reply.ts1) == (1_230_000_000, 987_654_321)
    gcs.send(gcs.mav.timesync_encode(5, 1))  # a reply to someone else's request: not answered
    assert count(gcs.run(0.1), "TIMESYNC") == 0


def test_that_garbage_and_bit_flipped_frames_never_raise_and_valid_frames_after_them_are_handled():
    gcs = Gcs()
    rng = random.Random(7)
    valid = gcs.mav.param_request_read_encode(1, 1, b"PS_ALT_M", -1).pack(gcs.mav)
    for trial in range(200):
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 400)))
        flipped = bytearray(valid)
        bit = rng.randrange(len(flipped) * 8)
        flipped[bit // 8] ^= 1 << (bit % 8)
        gcs.end.send(junk + bytes(flipped) + bytes([0xFD, 0xFF]))  # ends in a frame header claiming 255 bytes
        if trial % 20 == 0:
            gcs.tick()
    before = gcs.server.stats["rx_by_type"]["PARAM_REQUEST_READ"]
    gcs.end.send(valid + valid)
    gcs.send(gcs.mav.heartbeat_encode(6, 8, 0, 0, 0))
    for _ in range(20):  # enough bytes to complete (and reject) any frame the garbage began
        gcs.send(gcs.mav.heartbeat_encode(6, 8, 0, 0, 0))
    msgs = gcs.run(0.05)
    assert count(msgs, "PARAM_VALUE") >= 2
    assert gcs.server.stats["rx_by_type"]["PARAM_REQUEST_READ"] - before >= 2
    assert gcs.server.stats["rx_parse_errors"] > 0 and gcs.server.stats["rx_bad_bytes"] > 0
    assert gcs.server.stats["handler_errors"] == 0


def test_that_a_frame_with_a_corrupt_length_does_not_swallow_the_frames_after_it():
    gcs = Gcs()
    request = gcs.mav.param_request_read_encode(1, 1, b"PS_ALT_M", -1).pack(gcs.mav)
    broken = bytearray(request)
    broken[1] = 200  # payload length: the parser would wait for 200 bytes
    gcs.end.send(bytes(broken) + request + request * 8)
    assert count(gcs.run(0.0), "PARAM_VALUE") == 9


def test_that_the_tlog_holds_both_directions_with_simulated_timestamps(tmp_path):
    path = tmp_path / "flight.tlog"
    gcs = Gcs(tlog_path=path)
    gcs.run(0.5)
    gcs.send(gcs.mav.param_request_list_encode(1, 1))
    gcs.run(0.5)
    gcs.server.close()
    log = mavutil.mavlink_connection(str(path))
    seen = {}
    while (m := log.recv_match()) is not None:
        seen.setdefault((m.get_srcSystem(), m.get_type()), m._timestamp)
    log.close()
    assert (GCS_SYS, "PARAM_REQUEST_LIST") in seen
    assert (1, "HEARTBEAT") in seen and (1, "PARAM_VALUE") in seen and (1, "ATTITUDE") in seen
    assert seen[(GCS_SYS, "PARAM_REQUEST_LIST")] == pytest.approx(TLOG_EPOCH_US / 1e6 + 0.5)
    assert seen[(1, "HEARTBEAT")] == pytest.approx(TLOG_EPOCH_US / 1e6)


def test_that_two_identical_runs_write_identical_tlogs(tmp_path):
    def flight(path):
        gcs = Gcs(tlog_path=path)
        gcs.upload(survey_mission())
        gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        gcs.command(mavlink.MAV_CMD_MISSION_START)
        gcs.run(5.0)
        gcs.server.close()
        return path.read_bytes()

    first = flight(tmp_path / "a.tlog")
    assert len(first) > 10_000 and first == flight(tmp_path / "b.tlog")


def test_that_long_status_texts_are_sent_in_chunks():
    gcs = Gcs()
    gcs.send(gcs.mav.param_set_encode(1, 1, b"PS_YAW_RATE_DPS", 1e6, mavlink.MAV_PARAM_TYPE_REAL32))
    texts = [m for m in gcs.run(0.05) if m.get_type() == "STATUSTEXT"]
    assert len(texts) >= 2 and len({m.id for m in texts}) == 1 and texts[0].id != 0
    assert [m.chunk_seq for m in texts] == list(range(len(texts)))
    assert "outside" in "".join(m.text for m in texts)


def test_that_run_realtime_paces_simulated_time_at_the_speedup_against_the_wall_clock():
    vehicle = fast_vehicle()
    a, _ = PipeTransport.pair()
    server = MavlinkVehicleServer(vehicle, a)
    wall = [100.0]
    slept = []

    def sleep(dt):
        slept.append(dt)
        wall[0] += dt

    ran = run_realtime(server, vehicle, speedup=4.0, duration_s=2.0, clock=lambda: wall[0], sleep=sleep)
    assert ran == pytest.approx(2.0) and vehicle.state().t_s == pytest.approx(2.0)
    assert wall[0] - 100.0 == pytest.approx(0.5)  # 2 s simulated at 4x
    assert len(slept) == 200


def test_that_run_realtime_stops_when_asked():
    vehicle = fast_vehicle()
    server = MavlinkVehicleServer(vehicle, PipeTransport())
    stop = threading.Event()
    stop.set()
    assert run_realtime(server, vehicle, stop_event=stop) == 0.0
    with pytest.raises(ValueError):
        run_realtime(server, vehicle, speedup=0.0)



def _run_realtime_on_a_fake_wall_clock(server, vehicle, speedup: float, wall_s: float) -> None:
    """run_realtime for wall_s seconds of a wall clock that only its own sleeps advance (no real waiting)."""
    wall = [100.0]

    def sleep(dt):
        wall[0] += dt

    run_realtime(server, vehicle, speedup=speedup, duration_s=wall_s * speedup, clock=lambda: wall[0], sleep=sleep)


def _parse(data: bytes) -> list:
    mav = mavlink.MAVLink(None)
    mav.robust_parsing = True
    return [m for m in mav.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]


@pytest.mark.parametrize("speedup", [0.5, 1.0, 25.0, 200.0])
def test_that_under_run_realtime_a_ground_station_gets_the_stream_rates_per_second_of_its_own_clock(speedup):
    vehicle = fast_vehicle()
    server_end, gcs_end = PipeTransport.pair()
    server = MavlinkVehicleServer(vehicle, server_end)
    _run_realtime_on_a_fake_wall_clock(server, vehicle, speedup, wall_s=2.0)
    msgs = _parse(gcs_end.recv())
    assert count(msgs, "ATTITUDE") == pytest.approx(100, abs=2)  # 50 Hz for 2 s, not 50 Hz x speedup
    assert count(msgs, "LOCAL_POSITION_NED") == pytest.approx(100, abs=2)
    assert count(msgs, "HEARTBEAT") == pytest.approx(2, abs=1)


def test_that_after_run_realtime_the_streams_run_on_simulated_time_again():
    vehicle = fast_vehicle()
    server_end, gcs_end = PipeTransport.pair()
    server = MavlinkVehicleServer(vehicle, server_end)
    _run_realtime_on_a_fake_wall_clock(server, vehicle, 25.0, wall_s=0.2)
    gcs_end.recv()
    for _ in range(round(1.0 / vehicle.dt_s)):
        vehicle.step()
        server.update()
    assert count(_parse(gcs_end.recv()), "ATTITUDE") == pytest.approx(50, abs=1)


# ----- over real UDP ------------------------------------------------------------------------------

def test_that_a_mavutil_client_flies_a_mission_over_udp():
    vehicle = fast_vehicle()
    transport = UdpTransport("udp:127.0.0.1:0")
    server = MavlinkVehicleServer(vehicle, transport)
    stop = threading.Event()
    thread = threading.Thread(target=run_realtime, args=(server, vehicle),
                              kwargs={"speedup": 20.0, "duration_s": 600.0, "stop_event": stop}, daemon=True)
    thread.start()
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{transport.local_address[1]}", source_system=GCS_SYS,
                                      source_component=GCS_COMP)
    deadline = time.monotonic() + 15.0

    def wait(mtype, cond=lambda m: True):
        while time.monotonic() < deadline:
            m = conn.recv_match(type=mtype, blocking=True, timeout=0.5)
            if m is not None and cond(m):
                return m
        raise AssertionError(f"no {mtype} over UDP")

    try:
        conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        hb = wait("HEARTBEAT")
        assert (hb.type, hb.autopilot) == (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
        assert conn.flightmode == "STABILIZE"  # mavutil maps the ArduCopter mode number itself
        mission = survey_mission()
        conn.mav.mission_count_send(1, 1, len(mission))
        while True:
            m = wait(["MISSION_REQUEST_INT", "MISSION_ACK"])
            if m.get_type() == "MISSION_ACK":
                assert m.type == mavlink.MAV_MISSION_ACCEPTED
                break
            conn.mav.send(mission[m.seq])
        conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        assert wait("COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
        conn.mav.set_mode_send(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, FlightMode.AUTO)
        assert wait("COMMAND_ACK").result == mavlink.MAV_RESULT_ACCEPTED
        reached = [wait("MISSION_ITEM_REACHED").seq for _ in range(6)]
        assert reached == [1, 2, 3, 4, 5, 6]
        wait("HEARTBEAT")
        assert conn.flightmode == "AUTO"
    finally:
        stop.set()
        thread.join(timeout=5.0)
        conn.close()
        transport.close()
    assert not thread.is_alive()


def test_that_a_pose_noise_model_perturbs_what_attitude_and_local_position_report_and_nothing_else():
    from dataclasses import replace as _replace

    from sitl.mavlink.server import MavlinkVehicleServer as _Server

    class Fixed:
        def attitude(self):
            return 0.01, -0.02, 0.03

        def position(self):
            return 0.1, -0.2, 0.3

    from sitl.vehicle.api import FlightMode, VehicleState
    s = VehicleState(1.0, (5.0, 6.0, -7.0), (0.0, 0.0, 0.0), 0.1, 0.2, 0.3, 0.0, 0.0, 0.0, True, FlightMode.AUTO,
                     False, 0.0, 16.0)
    server = _Server.__new__(_Server)  # the estimator seam alone: no transport needed
    server.pose_noise = None
    assert server._estimated(s, True) is s
    server.pose_noise = Fixed()
    att, pos = server._estimated(s, True), server._estimated(s, False)
    assert (att.roll_rad, att.pitch_rad, att.yaw_rad) == pytest.approx((0.11, 0.18, 0.33))
    assert att.pos_ned_m == s.pos_ned_m
    assert pos.pos_ned_m == pytest.approx((5.1, 5.8, -6.7)) and pos.roll_rad == s.roll_rad
    assert _replace(pos, pos_ned_m=s.pos_ned_m) == s


def test_that_the_vehicles_pose_error_is_what_attitude_local_and_global_position_report():
    from sitl.mavlink.server import MavlinkVehicleServer as _Server
    from sitl.vehicle.api import FlightMode, VehicleState

    class Drifting:
        pose_error = (0.5, -0.25, 0.75, 0.02)

    s = VehicleState(1.0, (5.0, 6.0, -7.0), (0.0, 0.0, 0.0), 0.1, 0.2, 3.13, 0.0, 0.0, 0.0, True, FlightMode.AUTO,
                     False, 0.0, 16.0)
    server = _Server.__new__(_Server)
    server.pose_noise = None
    server.vehicle = Drifting()
    est = server._estimated(s, False)
    assert est.pos_ned_m == pytest.approx((5.5, 5.75, -6.25))
    assert est.yaw_rad == pytest.approx(3.15 - 2 * 3.141592653589793)  # wrapped
    assert (est.roll_rad, est.pitch_rad) == (s.roll_rad, s.pitch_rad)
    Drifting.pose_error = (0.0, 0.0, 0.0, 0.0)
    assert server._estimated(s, True) is s  # no error: the very state, as before
