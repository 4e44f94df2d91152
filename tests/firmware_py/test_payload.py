"""The payload loop under faults, in lockstep with the SITL: a sensor stuck busy, a burst of NACKs,
the position stream stopping. The loop keeps its 500 Hz, counts what failed, flags what it cannot
vouch for, never tags a sample with an old pose, and recovers when the fault clears."""

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleFlags, SampleLogWriter, read_samplelog
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from firmware_py.drivers.lidarlite import PRESET_FAST_500HZ, LidarLite, LidarLiteConfig, busy_deadline_ns
from firmware_py.drivers.servo import SweepServo
from firmware_py.hal.clock import SimClock
from firmware_py.hal.mavlink_link import ByteStreamLink
from firmware_py.payload import LoopConfig, PayloadLoop
from firmware_py.pose_tracker import PoseTracker

pytest.importorskip("sitl", reason="the firmware against the simulator (sitl/): not in the payload-only install")
from sitl.devices.i2c_sim import SimI2CBus
from sitl.devices.lidarlite_emu import EmulatedLidarLite
from sitl.devices.servo_emu import EmulatedServo
from sitl.runners.lockstep_payload import SimWorld
from sitl.vehicle.api import FlightMode, NavItem, NavKind
from sitl.vehicle.kinematic_vehicle import KinematicVehicle
from sitl.world import stockpile as piles
from sitl.world.raycast import World

OFFSET_NS = 777_000_000_000  # the companion clock runs ahead of the autopilot's boot clock
TICK_NS = 2_000_000
LOCAL_POSITION_NED = 32


def strip_messages(data: bytes, msg_id: int) -> bytes:
    """The MAVLink 2 frames in data, minus those of one message id (a stream the autopilot stopped)."""
    out, i = bytearray(), 0
    while i < len(data):
        assert data[i] == 0xFD, "the SITL server speaks MAVLink 2"
        n = 12 + data[i + 1] + (13 if data[i + 2] & 0x01 else 0)
        if int.from_bytes(data[i + 7:i + 10], "little") != msg_id:
            out += data[i:i + n]
        i += n
    return bytes(out)


class Rig:
    """A kinematic quadcopter flying a rectangle over pile 1 in a 30x20x10 building; the unchanged
    payload parts on one simulated clock with the emulated LiDAR, servo and MAVLink link."""

    def __init__(self, tmp_path):
        storage = Storage(30, 20, 10)
        world = World(storage, piles.resolve("1", storage))
        corners_w = [(8.0, 6.0), (22.0, 6.0), (22.0, 14.0), (8.0, 14.0)]
        nav = [NavItem(NavKind.TAKEOFF, 8.0, -6.0, -9.0)] + [
            NavItem(NavKind.WAYPOINT, x, -y, -9.0) for _ in range(3) for x, y in corners_w]
        vehicle = KinematicVehicle(speed_m_s=1.0, altitude_m=9.0, home_ned_m=(8.0, -6.0, 0.0))
        vehicle.set_mode(FlightMode.GUIDED)
        vehicle.arm()
        vehicle.load_mission(nav)
        vehicle.start_mission()
        self.clock = SimClock(start_ns=OFFSET_NS)
        self.sim = SimWorld(vehicle, world, StorageFrame(), self.clock, OFFSET_NS, (0.0, 0.0, 0.1))
        self.plant = EmulatedServo(self.clock)
        self.sim.servo_angle_at = self.plant.angle_at
        self.bus = SimI2CBus(self.clock)
        self.part = EmulatedLidarLite(self.clock, self.sim.true_range_m)
        self.bus.attach(0x62, self.part)
        self.lidar = LidarLite(self.bus, self.clock, LidarLiteConfig(
            preset=PRESET_FAST_500HZ, busy_timeout_ns=busy_deadline_ns(PRESET_FAST_500HZ, 500.0)))
        self.drop_position_after_ns: int | None = None
        self.drop_position_until_ns: int | None = None

        def wrap(direction, send_at):
            if direction != "down":
                return send_at

            def downlink(t_ns: int, data: bytes) -> None:
                if self.drop_position_after_ns is not None and \
                        self.drop_position_after_ns <= t_ns < (self.drop_position_until_ns or 2**63):
                    data = strip_messages(data, LOCAL_POSITION_NED)
                send_at(t_ns, data)
            return downlink

        self.sim.wrap_links(wrap)
        self.tracker = PoseTracker(ByteStreamLink(self.sim.payload_send, self.sim.payload_recv), self.clock)
        self.tracker.start()
        self.servo = SweepServo(self.plant, named_waveform("semi-triangular"))
        self.t0_ns = self.clock.now_ns()
        while self.clock.now_ns() < self.t0_ns + 3_000_000_000:  # take-off; the time sync converges
            self.clock.sleep_until_ns(self.clock.now_ns() + 10_000_000)
            self.tracker.pump()
        self.log_path = tmp_path / "samples.pslog"

    def run(self, seconds: float, events: list) -> tuple:
        """Run the loop; events are (seconds after the start, action) fired from the loop's hook."""
        start = self.clock.now_ns()
        pending = sorted(events, key=lambda e: e[0])

        def hook() -> bool:
            while pending and self.clock.now_ns() - start >= pending[0][0] * 1e9:
                pending.pop(0)[1]()
            return False

        with SampleLogWriter(self.log_path, {"test": True}, fsync=False) as log:
            loop = PayloadLoop(self.lidar, self.servo, self.tracker, self.clock, log, LoopConfig(), t0_ns=self.t0_ns)
            stats = loop.run(duration_s=seconds, should_stop=hook)  # the seconds sampled, from here
        s = read_samplelog(self.log_path).samples
        return stats, s, (s["t_s"] - start / 1e9)

    def true_position(self, t_s: np.ndarray) -> np.ndarray:
        hist = self.sim.history
        tv = np.array([t for t, _ in hist]) + OFFSET_NS / 1e9
        st = np.array([x[:3] for _, x in hist])
        return np.column_stack([np.interp(t_s, tv, st[:, k]) for k in range(3)])


@pytest.fixture
def rig(tmp_path):
    return Rig(tmp_path)


def _flag(s, f: SampleFlags) -> np.ndarray:
    return (s["flags"] & int(f)) != 0


def test_that_a_sensor_stuck_busy_times_out_is_counted_and_the_loop_keeps_its_rate(rig):
    def stick():
        rig.part.stuck_busy = True

    def unstick():
        rig.part.stuck_busy = False

    stats, s, t = rig.run(5.0, [(2.0, stick), (2.5, unstick)])
    assert rig.lidar.counters().timeouts >= 200  # every reading in the 0.5 s window
    fault = (t > 2.01) & (t < 2.49)
    assert _flag(s[fault], SampleFlags.SENSOR_ERROR).all()
    # The deadline fits in a tick: samples keep coming every 2 ms while the part is stuck ...
    assert np.median(np.diff(s["t_s"][fault])) == pytest.approx(TICK_NS / 1e9, abs=1e-6)
    # ... apart from the driver's resets (every 20 failures, 25 ms each), which are counted.
    assert rig.lidar.counters().resets >= 1
    assert stats.ticks >= 0.9 * 5.0 * 500
    after = t > 2.6
    assert np.mean(_flag(s[after], SampleFlags.SENSOR_ERROR)) < 0.01  # recovered without a restart
    assert np.median(np.diff(s["t_s"][after])) == pytest.approx(TICK_NS / 1e9, abs=1e-6)


def test_that_a_nack_burst_is_counted_flagged_and_recovered_from(rig):
    def burst():
        rig.bus.fault_until_ns = rig.clock.now_ns() + 300_000_000

    stats, s, t = rig.run(4.0, [(1.5, burst)])
    assert rig.lidar.counters().bus_errors >= 100 and rig.bus.counters["nack"] >= 100
    fault = (t > 1.51) & (t < 1.79)
    assert _flag(s[fault], SampleFlags.SENSOR_ERROR).all()
    assert stats.ticks >= 0.95 * 4.0 * 500
    after = t > 1.9
    assert np.mean(_flag(s[after], SampleFlags.SENSOR_ERROR)) < 0.01
    assert np.median(np.diff(s["t_s"])) == pytest.approx(TICK_NS / 1e9, abs=1e-6)


def test_that_samples_are_never_tagged_with_an_old_pose_when_the_position_stream_stops(rig):
    def stop():
        rig.drop_position_after_ns = rig.sim.vehicle_time_ns(rig.clock.now_ns())

    def resume():
        rig.drop_position_until_ns = rig.sim.vehicle_time_ns(rig.clock.now_ns())

    stats, s, t = rig.run(6.0, [(2.0, stop), (4.0, resume)])
    posed = s[(s["flags"] & int(SampleFlags.STALE_POSE | SampleFlags.NO_POSE)) == 0]
    assert len(posed) > 0.5 * len(s)
    # Every sample that carries a pose carries the right one (the vehicle moves at 1 m/s) ...
    err = np.linalg.norm(np.column_stack([posed["x_m"], posed["y_m"], posed["z_m"]])
                         - rig.true_position(posed["t_s"]), axis=1)
    assert err.max() < 0.05
    # ... and while no position came, none did.
    outage = (t > 2.0 + 0.1) & (t < 4.0)
    assert outage.sum() > 500 and _flag(s[outage], SampleFlags.STALE_POSE | SampleFlags.NO_POSE).all()
    assert stats.flagged(SampleFlags.STALE_POSE | SampleFlags.NO_POSE) >= outage.sum()
    after = t > 4.3
    assert np.mean(_flag(s[after], SampleFlags.STALE_POSE | SampleFlags.NO_POSE)) < 0.01  # recovered


def test_that_a_stop_waits_for_the_poses_of_the_last_readings_instead_of_flagging_them(rig):
    stats, s, _ = rig.run(2.0, [])
    assert stats.ticks >= 0.95 * 2.0 * 500 and len(s) == stats.ticks  # every reading logged ...
    assert not _flag(s, SampleFlags.STALE_POSE | SampleFlags.NO_POSE).any()  # ... the last ones with a pose too
    err = np.linalg.norm(np.column_stack([s["x_m"], s["y_m"], s["z_m"]]) - rig.true_position(s["t_s"]), axis=1)
    assert err.max() < 0.05
