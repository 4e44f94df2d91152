"""Faults in the networked SITL: the SIM_PS_* parameters on the MAVLink server (in lockstep and over UDP
with pymavlink), the faulted transport, the emulated devices, and `serve --fault`. Short and seeded;
everything is asserted on simulated time, never on the wall clock."""

import json
import math
import threading
import time
from dataclasses import fields

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.frames import StorageFrame
from firmware_py.core.storage import Storage
from firmware_py.hal import I2CError
from sitl.cli import main
from sitl.devices.networked import FaultyTransport, NetworkedDevices, NetworkedFaults
from sitl.faults.injector import FaultSpec
from sitl.faults.params import PARAMS, FaultParams, LiveFaultInjector
from sitl.mavlink.server import MavlinkVehicleServer, run_realtime
from sitl.mavlink.transport import PipeTransport, UdpTransport
from sitl.missions.rectangle import Mission
from sitl.runners.fly import truth_record
from sitl.vehicle.api import FlightMode
from sitl.world.raycast import World
from sitl.world.stockpile import resolve
from tests.sitl.mavlink.lockstep_gcs import GCS_COMP, GCS_SYS, Gcs, survey_mission

LINK_AND_AUTOPILOT = ["SIM_PS_DUP", "SIM_PS_JIT_MS", "SIM_PS_LAT_MS", "SIM_PS_LOSS", "SIM_PS_OUTAGE", "SIM_PS_REBOOT",
                      "SIM_PS_REORDER"]
ATTITUDE = mavlink.MAVLINK_MSG_ID_ATTITUDE


class FaultyGcs(Gcs):
    """test_mavlink_vehicle's lockstep ground station, talking to a server wired as `serve` wires it."""

    def __init__(self, spec: FaultSpec | None = None):
        super().__init__()
        self.faults = NetworkedFaults(spec or FaultSpec(seed=2), self.vehicle, self.server.transport)
        self.server = MavlinkVehicleServer(self.vehicle, self.faults.transport, extra_params=self.faults.params)
        self.faults.bind(self.server)

    def tick(self, step: bool = True) -> None:
        if step:
            self.vehicle.step()
        self.server.update()
        self.faults.step()
        data = self.end.recv()
        msgs = (self.mav.parse_buffer(data) or []) if data else []
        self.pending += [m for m in msgs if m.get_type() != "BAD_DATA"]

    def param_set(self, name: str, value: float):
        self.send(self.mav.param_set_encode(1, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32))


def test_that_the_sim_params_are_arducopter_sized_and_mirror_fault_spec_settings():
    spec_fields = {f.name for f in fields(FaultSpec)}
    for p in PARAMS:
        assert p.name.startswith("SIM_PS_") and len(p.name) <= 16
        assert p.field is None or p.field in spec_fields
        if p.field is not None:  # the table's range is FaultSpec's own
            FaultSpec(**{p.field: p.lo})
            FaultSpec(**{p.field: p.hi})
            with pytest.raises(ValueError):
                FaultSpec(**{p.field: p.hi * 1.01 + 0.01})


# ----- the server's parameter list, in lockstep ------------------------------------------------------

def test_that_the_sim_params_are_listed_and_read_with_the_vehicles_own():
    gcs = FaultyGcs(FaultSpec(seed=2, link_latency_ms=5.0))
    gcs.send(gcs.mav.param_request_list_encode(1, 1))
    values = [m for m in gcs.run(0.2) if m.get_type() == "PARAM_VALUE"]
    names = sorted([*gcs.vehicle.params, *LINK_AND_AUTOPILOT])  # no devices: no device parameters
    assert [m.param_id for m in sorted(values, key=lambda m: m.param_index)] == names
    assert {m.param_count for m in values} == {len(names)}
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"SIM_PS_LAT_MS", -1))
    assert gcs.expect("PARAM_VALUE").param_value == 5.0  # the --fault value
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"", names.index("SIM_PS_LOSS")))
    assert gcs.expect("PARAM_VALUE").param_id == "SIM_PS_LOSS"


@pytest.mark.parametrize(("name", "value", "reason"), [("SIM_PS_LOSS", 101.0, "101 is outside 0..100 %"),
                                                       ("SIM_PS_LAT_MS", math.nan, "nan is outside"),
                                                       ("SIM_PS_REBOOT", 61.0, "61 is outside 0..60 s"),
                                                       ("SIM_PS_OUTAGE", -1.0, "-1 is outside"),
                                                       ("SIM_PS_I2C_NACK", 5.0, "unknown parameter")])
def test_that_a_bad_sim_value_is_refused_with_a_statustext_and_the_old_value_read_back(name, value, reason):
    gcs = FaultyGcs()
    before = gcs.faults.injector.spec
    gcs.param_set(name, value)
    msgs = gcs.run(0.1)
    assert any(m.get_type() == "STATUSTEXT" and reason in m.text for m in msgs), [m.text for m in msgs
                                                                                  if m.get_type() == "STATUSTEXT"]
    echoes = [(m.param_id, m.param_value) for m in msgs if m.get_type() == "PARAM_VALUE"]
    assert echoes == ([] if reason == "unknown parameter" else [(name, 0.0)])
    assert gcs.faults.injector.spec == before and "reboots" not in gcs.server.stats


def test_that_an_outage_is_acknowledged_then_silences_the_link_for_its_seconds():
    gcs = FaultyGcs()
    gcs.param_set("SIM_PS_OUTAGE", 1.0)
    echo = gcs.expect("PARAM_VALUE", within_s=0.05)
    assert (echo.param_id, echo.param_value) == ("SIM_PS_OUTAGE", 1.0)
    gcs.run(0.0)  # what went out at the same instant as the acknowledgement
    assert gcs.run(0.9) == []  # nothing either way (a TIMESYNC request is lost too)
    gcs.send(gcs.mav.timesync_encode(0, 123))
    assert not any(m.get_type() == "TIMESYNC" for m in gcs.run(0.05))
    assert any(m.get_type() == "ATTITUDE" for m in gcs.run(0.2))  # back after 1 s
    gcs.send(gcs.mav.param_request_read_encode(1, 1, b"SIM_PS_OUTAGE", -1))
    assert gcs.expect("PARAM_VALUE").param_value == 0.0
    counters = gcs.faults.transport.down.counters
    assert counters["outage_lost"] > 40 and gcs.faults.transport.up.counters["outage_lost"] == 1


def test_that_added_latency_delays_every_reply_by_at_least_its_milliseconds():
    gcs = FaultyGcs()
    gcs.param_set("SIM_PS_LAT_MS", 200.0)
    gcs.expect("PARAM_VALUE", lambda m: m.param_id == "SIM_PS_LAT_MS")
    t0 = gcs.vehicle.state().t_s
    gcs.send(gcs.mav.timesync_encode(0, 42))
    gcs.expect("TIMESYNC", lambda m: m.ts1 == 42)
    assert gcs.vehicle.state().t_s - t0 >= 0.4 - 1e-9  # 200 ms up, 200 ms down


def test_that_timed_faults_count_from_the_vehicle_entering_auto():
    gcs = FaultyGcs(FaultSpec(seed=2, autopilot_reboot=(0.5, 0.2)))
    gcs.run(1.0)
    assert "reboots" not in gcs.server.stats  # on the ground, disarmed: the fault clock has not started
    assert gcs.upload(survey_mission()) == mavlink.MAV_MISSION_ACCEPTED
    gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
    gcs.set_mode(FlightMode.AUTO)
    t_auto = gcs.faults.injector.survey_t0_ns / 1e9
    gcs.run(0.4)
    assert "reboots" not in gcs.server.stats
    gcs.run(0.2)
    assert gcs.server.stats["reboots"] == 1 and gcs.faults.injector.counters["autopilot_reboots"] == 1
    assert t_auto >= 1.0


# ----- the transport alone ---------------------------------------------------------------------------

def test_that_the_faulty_transport_keeps_order_delays_and_duplicates_on_simulated_time():
    now = [0]
    server_end, client_end = PipeTransport.pair()
    inj = LiveFaultInjector(FaultSpec(seed=1, link_latency_ms=30.0, link_jitter_ms=20.0, link_dup_pct=50.0))
    t = FaultyTransport(server_end, inj, lambda: now[0])
    for k in range(20):
        t.send(bytes([k]))
        now[0] += 1_000_000  # 1 ms a packet
    assert client_end.recv() == b""  # 20 ms in: nothing is due before 30 ms
    now[0] += 60_000_000
    t.flush()
    got = client_end.recv()
    assert sorted(set(got)) == list(range(20)) and list(got) == sorted(got)  # in order, some twice
    assert t.down.counters["duplicated"] > 3 and len(got) == 20 + t.down.counters["duplicated"]
    client_end.send(b"up")
    assert t.recv() == b""  # delayed too (and maybe duplicated)
    now[0] += 60_000_000
    assert t.recv() in (b"up", b"upup")


# ----- the emulated devices ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def world():
    storage = Storage(30, 20, 10)
    return World(storage, resolve("1", storage))


def test_that_device_faults_reach_the_emulated_bus_lidar_and_servo(world):
    gcs = Gcs()  # only for its kinematic vehicle
    devices = NetworkedDevices(gcs.vehicle, world, "tcp:127.0.0.1:0")
    try:
        faults = NetworkedFaults(FaultSpec(seed=5, servo_delay_ms=20.0), gcs.vehicle, PipeTransport(), devices)
        p: FaultParams = faults.params
        assert set(p.names()) == {q.name for q in PARAMS} - {"SIM_PS_REBOOT"}  # not bound to a server
        assert p.get("SIM_PS_SRV_DLY") == 20.0 and devices.servo.delay_ns == 20_000_000

        def nacks(n: int = 400) -> int:
            before = devices.bus.counters["nack"]
            for _ in range(n):
                try:
                    devices.bus.write_read(0x62, bytes([0x01]), 1)
                except I2CError:
                    pass
            return devices.bus.counters["nack"] - before
        assert nacks() == 0
        assert p.set("SIM_PS_I2C_NACK", 50.0) is None  # a setting: read back
        assert 120 < nacks() < 280 and devices.bus.nack_probability == 0.5
        p.set("SIM_PS_I2C_NACK", 0.0)
        assert nacks() == 0

        cal0 = devices.servo.cal
        p.set("SIM_PS_SRV_SLOW", 0.5)
        assert devices.servo.cal.slew_rad_s == pytest.approx(cal0.slew_rad_s * 0.5)
        assert devices.servo.model.cal is devices.servo.cal
        p.set("SIM_PS_SRV_SLOW", 1.0)
        assert devices.servo.cal.slew_rad_s == pytest.approx(cal0.slew_rad_s)  # from the calibration, not compounded
        p.set("SIM_PS_SRV_DLY", 100.0)
        assert devices.servo.delay_ns == 100_000_000
        p.set("SIM_PS_SRV_STK", 1.0)
        assert devices.servo.stuck and p.get("SIM_PS_SRV_STK") == 1.0
        p.set("SIM_PS_SRV_STK", 0.0)
        assert not devices.servo.stuck
        with pytest.raises(ValueError, match="0 or 1"):
            p.set("SIM_PS_SRV_STK", 0.5)

        p.set("SIM_PS_BUSY", 5.0)
        assert devices.lidar.busy and p.get("SIM_PS_BUSY") == 5.0  # the vehicle's clock has not moved
        p.set("SIM_PS_BUSY", 0.0)
        assert not devices.lidar.busy
        assert p.set("SIM_PS_PWRGLT", 1.0) == 1.0  # acknowledged as set, then reads back 0
        assert devices.lidar.counters["power_glitches"] == 1 and p.get("SIM_PS_PWRGLT") == 0.0
        p.set("SIM_PS_GLITCH", 100.0)
        assert {devices.lidar.range_at(0) for _ in range(20)} <= {40.0, 0.01}
        assert faults.injector.counters["lidar_glitches"] == 20
        p.set("SIM_PS_GLITCH", 0.0)
        assert devices.lidar.range_at(0) not in (40.0, 0.01)
        assert "I2C NACKs" in faults.summary()
    finally:
        devices.close()


def test_that_a_stuck_busy_lidar_frees_itself_when_its_seconds_are_up(world):
    gcs = Gcs()
    devices = NetworkedDevices(gcs.vehicle, world, "tcp:127.0.0.1:0")
    try:
        faults = NetworkedFaults(FaultSpec(seed=5), gcs.vehicle, PipeTransport(), devices)
        faults.params.set("SIM_PS_BUSY", 0.5)
        for _ in range(round(0.4 / gcs.vehicle.dt_s)):
            gcs.vehicle.step()
            faults.step()
        assert devices.lidar.busy and 0.0 < faults.params.get("SIM_PS_BUSY") <= 0.11
        for _ in range(round(0.2 / gcs.vehicle.dt_s)):
            gcs.vehicle.step()
            faults.step()
        assert not devices.lidar.busy and faults.params.get("SIM_PS_BUSY") == 0.0
    finally:
        devices.close()


# ----- over UDP, with pymavlink ----------------------------------------------------------------------

class UdpClient:
    """A pymavlink ground station on a real UDP socket; every wait is bounded, none is asserted on."""

    def __init__(self, port: int):
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=GCS_SYS,
                                               source_component=GCS_COMP)
        self.deadline = time.monotonic() + 30.0

    def wait(self, mtype, cond=lambda m: True, seen: list | None = None, timeout_s: float | None = None):
        end = min(self.deadline, time.monotonic() + timeout_s) if timeout_s else self.deadline
        while time.monotonic() < end:
            m = self.conn.recv_match(blocking=True, timeout=0.2)
            if m is None:
                continue
            if seen is not None:
                seen.append(m)
            if m.get_type() in ([mtype] if isinstance(mtype, str) else mtype) and cond(m):
                return m
        if timeout_s:
            return None
        raise AssertionError(f"no {mtype} over UDP")

    def param_set(self, name: str, value: float, seen: list | None = None):
        """PARAM_SET until its PARAM_VALUE comes back (a lossy link may eat either)."""
        for _ in range(40):
            self.conn.mav.param_set_send(1, 1, name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32)
            echo = self.wait("PARAM_VALUE", lambda m: m.param_id == name, seen=seen, timeout_s=0.3)
            if echo is not None:
                return echo
        raise AssertionError(f"no PARAM_VALUE for {name}")

    def interval_us(self, msg_id: int) -> int:
        self.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, 0, msg_id, 0, 0, 0, 0, 0, 0)
        return self.wait("MESSAGE_INTERVAL", lambda m: m.message_id == msg_id).interval_us


def test_that_a_pymavlink_client_lists_sets_and_feels_the_sim_params_over_udp():
    gcs = Gcs()  # its kinematic vehicle
    vehicle, raw = gcs.vehicle, UdpTransport("udp:127.0.0.1:0")
    faults = NetworkedFaults(FaultSpec(seed=7), vehicle, raw)
    server = MavlinkVehicleServer(vehicle, faults.transport, extra_params=faults.params)
    faults.bind(server)
    stop = threading.Event()
    thread = threading.Thread(target=run_realtime, args=(server, vehicle), daemon=True,
                              kwargs={"speedup": 1.0, "duration_s": 600.0, "stop_event": stop, "on_step": faults.step})
    # At 1x the stream rates (per wall-clock second under run_realtime) are per simulated second too.
    thread.start()
    gcs_udp = UdpClient(raw.local_address[1])
    try:
        gcs_udp.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        gcs_udp.wait("HEARTBEAT")
        # the list: the vehicle's parameters and the SIM_PS_* ones, each once, indexed
        gcs_udp.conn.mav.param_request_list_send(1, 1)
        first = gcs_udp.wait("PARAM_VALUE")
        got = {first.param_index: first.param_id}
        while len(got) < first.param_count:
            m = gcs_udp.wait("PARAM_VALUE")
            got[m.param_index] = m.param_id
        assert sorted(got.values()) == sorted([*vehicle.params, *LINK_AND_AUTOPILOT])
        # a bad value: refused, said why, the old value read back
        seen: list = []
        echo = gcs_udp.param_set("SIM_PS_LOSS", 150.0, seen=seen)  # the STATUSTEXT comes just before it
        assert echo.param_value == 0.0 and faults.injector.spec.link_loss_pct == 0.0
        assert any(m.get_type() == "STATUSTEXT" and "SIM_PS_LOSS" in m.text and "150" in m.text for m in seen)
        # 40 % loss both ways: about 60 of the 100 ATTITUDEs of two simulated seconds arrive
        assert gcs_udp.param_set("SIM_PS_LOSS", 40.0).param_value == 40.0
        t1 = gcs_udp.wait("ATTITUDE").time_boot_ms
        stamps = []
        while not stamps or stamps[-1] < t1 + 2000:
            stamps.append(gcs_udp.wait("ATTITUDE").time_boot_ms)
        assert 30 < len(stamps) < 90  # of 100 sent
        assert faults.transport.down.counters["lost"] > 20
        assert gcs_udp.param_set("SIM_PS_LOSS", 0.0).param_value == 0.0
        # a reboot: acknowledged with the value set (MAVProxy checks), silent, then time_boot_ms from 0
        # and the default rates; it reads back 0 then
        gcs_udp.conn.mav.command_long_send(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, ATTITUDE, 200_000,
                                           0, 0, 0, 0, 0)
        assert gcs_udp.interval_us(ATTITUDE) == 200_000
        before = gcs_udp.wait("ATTITUDE").time_boot_ms
        assert gcs_udp.param_set("SIM_PS_REBOOT", 0.5).param_value == 0.5
        after = gcs_udp.wait("ATTITUDE", lambda m: m.time_boot_ms < before)
        assert after.time_boot_ms < 100  # near 0: the first message after the silence
        stamps = [after.time_boot_ms]
        while stamps[-1] < 1000:
            stamps.append(gcs_udp.wait("ATTITUDE").time_boot_ms)
        assert len(stamps) >= 45  # 50 Hz again, counted on the autopilot's clock
        assert gcs_udp.interval_us(ATTITUDE) == 20_000
        gcs_udp.conn.mav.param_request_read_send(1, 1, b"SIM_PS_REBOOT", -1)
        assert gcs_udp.wait("PARAM_VALUE", lambda m: m.param_id == "SIM_PS_REBOOT").param_value == 0.0
        assert server.stats["reboots"] == 1 and faults.injector.counters["autopilot_reboots"] == 1
    finally:
        stop.set()
        thread.join(timeout=5.0)
        gcs_udp.conn.close()
        raw.close()
    assert not thread.is_alive()


# ----- serve --fault ---------------------------------------------------------------------------------

def test_that_serve_injects_link_faults_and_reports_them(tmp_path, capsys):
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--duration", "0.5",
                 "--speedup", "20", "--fault", "link_loss_pct=30", "--seed", "3", "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "faults link_loss_pct (seed 3)" in err
    assert "; faults: MAVLink out " in err and " lost" in err.splitlines()[-1]


def test_that_serve_with_devices_records_its_faults_in_the_truth_it_shares_with_fly(tmp_path, capsys):
    out = tmp_path / "net"
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--devices", "tcp:127.0.0.1:0",
                 "--storage", "30x20x10", "--altitude", "9", "--duration", "0.2", "--fault", "i2c_nack_pct=5",
                 "--fault", "lidar_power_glitch_at_s=3", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "times count from the mission start" in err
    truth = json.loads((out / "truth.json").read_text())
    assert truth["payload"] == "networked" and truth["plant"] == "kinematic"
    assert truth["faults"]["i2c_nack_pct"] == 5.0 and truth["seed"] == 0
    assert {"true_volume_m3", "stockpile", "stockpile_source", "storage", "storage_frame", "mission", "mission_id",
            "software"} <= set(truth)


def test_that_the_truth_record_keeps_fly_keys_in_order():
    storage = Storage(30, 20, 10)
    mission = Mission(storage=storage, p_traj=0.2, altitude_m=9.0)
    rec = truth_record(resolve("1", storage), "1", mission, StorageFrame(), plant="jsbsim", payload="firmware", seed=0,
                       flight_time_s=1.0, energy_j=2.0, payload_kg=0.04, n_samples=3, servo_initial_position=0,
                       waveform="semi-triangular")
    assert list(rec) == ["true_volume_m3", "stockpile", "stockpile_source", "pile_seed", "seed", "storage",
                         "storage_frame", "site", "ekf_origin", "mission", "mission_id", "plant", "payload", "faults",
                         "flight_time_s", "energy_j", "payload_kg", "n_samples", "servo_initial_position", "waveform",
                         "software"]
