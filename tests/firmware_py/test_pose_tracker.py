"""PoseTracker against the SITL autopilot (MavlinkVehicleServer + KinematicVehicle) over a link with seeded
random latency in simulated time. Everything is stepped in the test loop: 1 ms world steps, the vehicle,
the server and the tracker each once per step; no threads, no sleeps (except the one real-UDP test)."""

from __future__ import annotations

import dataclasses
import heapq
import json
import math
import random
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.clock import MonotonicClock, SimClock
from firmware_py.hal.mavlink_link import ByteStreamLink, PymavlinkLink
from firmware_py.pose_tracker import PoseTracker, PoseTrackerConfig

pytest.importorskip("sitl", reason="the firmware against the simulator (sitl/): not in the payload-only install")
from sitl.mavlink.server import MavlinkVehicleServer
from sitl.mavlink.transport import UdpTransport
from sitl.vehicle.api import FlightMode, NavItem, NavKind
from sitl.vehicle.kinematic_vehicle import KinematicVehicle, wrap_pi

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)

MS = 1_000_000
S = 1_000_000_000
DT_NS = 1 * MS
HOUR_NS = 3_600 * S
COMPANION_OFFSET_NS = 271_828_182_845_904  # companion monotonic time at world time 0: ~3 days, not ms-aligned
QUERY_LAG_NS = 100 * MS  # poses are asked for 100 ms in the past, where both brackets have arrived

ATTITUDE_ID = mavlink.MAVLINK_MSG_ID_ATTITUDE
LOCAL_POSITION_ID = mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED
COMMAND_LONG_ID = mavlink.MAVLINK_MSG_ID_COMMAND_LONG


def msg_id(frame: bytes) -> int:
    """Message id of one MAVLink 2 frame (each transport send is one frame)."""
    return int.from_bytes(frame[7:10], "little")


# ----- a link with latency in simulated time ----------------------------------------------------------

class LatencyLeg:
    """One direction: a frame sent at simulated time t becomes visible at t + a seeded random delay.

    Frames are independent, like UDP datagrams (a later frame may overtake an earlier one). `outlier_p`
    adds a seeded extra delay to some frames; `drop(frame)` loses frames.
    """

    def __init__(self, now_ns: Callable[[], int], seed: int, min_ns: int = 5 * MS, max_ns: int = 30 * MS) -> None:
        self.now_ns, self.rng = now_ns, random.Random(seed)
        self.min_ns, self.max_ns = min_ns, max_ns
        self.outlier_p = 0.0
        self.outlier_extra_ns = (100 * MS, 400 * MS)
        self.drop: Callable[[bytes], bool] | None = None
        self._queue: list[tuple[int, int, bytes]] = []
        self._n = 0
        self.dropped = 0

    def push(self, frame: bytes) -> None:
        if self.drop is not None and self.drop(frame):
            self.dropped += 1
            return
        delay = self.rng.randint(self.min_ns, self.max_ns)
        if self.outlier_p and self.rng.random() < self.outlier_p:
            delay += self.rng.randint(*self.outlier_extra_ns)
        self._n += 1
        heapq.heappush(self._queue, (self.now_ns() + delay, self._n, bytes(frame)))

    def pop_due(self) -> bytes:
        out, now, q = [], self.now_ns(), self._queue
        while q and q[0][0] <= now:
            out.append(heapq.heappop(q)[2])
        return b"".join(out)

    def clear(self) -> None:
        self._queue.clear()


class LatencyEnd:
    """One end of the pipe, with the Transport interface of sitl.mavlink.transport (send / recv / close)."""

    def __init__(self, tx: LatencyLeg, rx: LatencyLeg) -> None:
        self.tx, self.rx = tx, rx

    def send(self, data: bytes) -> None:
        self.tx.push(data)

    def recv(self) -> bytes:
        return self.rx.pop_due()

    def close(self) -> None:
        pass


class JumpClock:
    """Companion clock = world time + offset + jump; unlike SimClock it can be made to jump backwards."""

    def __init__(self, world: World) -> None:
        self.world = world
        self.jump_ns = 0

    def now_ns(self) -> int:
        return self.world.w_ns + COMPANION_OFFSET_NS + self.jump_ns

    def sleep_until_ns(self, t_ns: int) -> None:
        pass  # the world is stepped by the test loop


# ----- the simulated world ----------------------------------------------------------------------------

@dataclass
class Eval:
    """One comparison of PoseTracker.pose_at(t) with the vehicle's true state at t."""

    sync_err_ns: int  # estimated minus true autopilot time of the companion time t
    usable: bool
    along_err_ns: float | None  # position error along the velocity / speed (straight legs)
    yaw_err_ns: float | None  # yaw error / yaw rate (turns)
    cross_m: float | None  # position error across the track


def square_mission(side_m: float = 10.0, laps: int = 3) -> list[NavItem]:
    corners = [(side_m, 0.0), (side_m, side_m), (0.0, side_m), (0.0, 0.0)]
    return [NavItem(NavKind.TAKEOFF, 0.0, 0.0, -5.0)] + [
        NavItem(NavKind.WAYPOINT, n, e, -5.0) for _ in range(laps) for n, e in corners]


class World:
    """Vehicle + SITL MAVLink autopilot <-latency pipe-> ByteStreamLink + PoseTracker, in 1 ms lockstep."""

    def __init__(self, seed: int, timesync_hz: float = 10.0, jumpable: bool = False, fly: bool = True,
                 start: bool = True, stream_hz: float = 50.0) -> None:
        self.w_ns = 0
        now = lambda: self.w_ns  # noqa: E731
        self.up = LatencyLeg(now, 1000 + seed)      # companion -> autopilot
        self.down = LatencyLeg(now, 2000 + seed)    # autopilot -> companion
        self.clock: JumpClock | SimClock = JumpClock(self) if jumpable else SimClock(start_ns=COMPANION_OFFSET_NS)
        payload_end = LatencyEnd(self.up, self.down)
        self.link = ByteStreamLink(payload_end.send, payload_end.recv)
        self.tracker = PoseTracker(self.link, self.clock, timesync_hz=timesync_hz, stream_hz=stream_hz)
        self.evals: list[Eval] = []
        self.boot(fly)
        if start:
            self.tracker.start()

    def boot(self, fly: bool) -> None:
        """(Re)boot the autopilot: a new vehicle whose clock starts at 0 now, and a new server."""
        self.boot_w_ns = self.w_ns
        self.vehicle = KinematicVehicle(dt_s=DT_NS / 1e9, speed_m_s=2.0, altitude_m=5.0)
        self.server = MavlinkVehicleServer(self.vehicle, LatencyEnd(self.down, self.up))
        if fly:
            self.vehicle.set_mode(FlightMode.GUIDED)
            self.vehicle.arm()
            self.vehicle.load_mission(square_mission())
            self.vehicle.start_mission()
        self.history = [self._truth()]  # truth[k] = vehicle state k ms after boot
        self.run_start_same_vel = [0]
        self.run_start_same_yawrate = [0]

    def _truth(self) -> tuple:
        s = self.vehicle.state()
        return s.pos_ned_m, s.vel_ned_m_s, s.yaw_rad, s.yawspeed_rad_s

    def companion_ns(self, w_ns: int) -> int:
        return w_ns + COMPANION_OFFSET_NS + (self.clock.jump_ns if isinstance(self.clock, JumpClock) else 0)

    def step(self) -> None:
        self.w_ns += DT_NS
        if isinstance(self.clock, SimClock):
            self.clock.set_ns(self.companion_ns(self.w_ns))
        self.vehicle.step()
        self.server.update()
        self.tracker.pump()
        truth = self._truth()
        k = len(self.history)
        prev = self.history[-1]
        same_vel = all(abs(a - b) < 1e-9 for a, b in zip(truth[1], prev[1], strict=True))
        self.run_start_same_vel.append(self.run_start_same_vel[-1] if same_vel else k)
        self.run_start_same_yawrate.append(self.run_start_same_yawrate[-1] if truth[3] == prev[3] else k)
        self.history.append(truth)

    def run(self, seconds: float, evaluate_every: int = 0) -> None:
        for k in range(round(seconds * S / DT_NS)):
            self.step()
            if evaluate_every and k % evaluate_every == 0 and self.tracker.timesync.converged:
                self.evaluate()

    def run_until(self, condition: Callable[[], bool], max_seconds: float) -> float:
        """Step until condition() holds; returns the simulated seconds it took (fails after max_seconds)."""
        for k in range(round(max_seconds * S / DT_NS)):
            if condition():
                return k * DT_NS / S
            self.step()
        raise AssertionError(f"condition not met within {max_seconds} s of simulated time")

    def evaluate(self) -> Eval | None:
        """Compare the tracker's pose QUERY_LAG_NS ago with the truth at that instant."""
        w_q = self.w_ns - QUERY_LAG_NS
        k = (w_q - self.boot_w_ns) // DT_NS  # true autopilot time of w_q is k ms after boot
        if k < 60:
            return None
        t_q = self.companion_ns(w_q)
        sync_err = self.tracker.timesync.to_autopilot_ns(t_q) - k * DT_NS
        pose = self.tracker.pose_at(t_q)
        along = yaw_err = cross = None
        if pose.usable:
            pos, vel, yaw, yawrate = self.history[k]
            speed2 = sum(v * v for v in vel)
            if self.run_start_same_vel[k + 60] <= k - 60 and speed2 > 0.25:  # straight leg, +-60 ms
                d = [pose.pos_ned_m[i] - pos[i] for i in range(3)]
                along_s = sum(d[i] * vel[i] for i in range(3)) / speed2
                along = along_s * S
                cross = math.sqrt(sum((d[i] - along_s * vel[i]) ** 2 for i in range(3)))
            if self.run_start_same_yawrate[k + 60] <= k - 60 and abs(yawrate) > 0.1:  # steady turn
                yaw_err = wrap_pi(pose.yaw_rad - yaw) / yawrate * S
        e = Eval(sync_err, pose.usable, along, yaw_err, cross)
        self.evals.append(e)
        return e


def median_abs_ms(values) -> float:
    return statistics.median(abs(v) for v in values) / MS


# ----- the must-show: timing error with 5-30 ms random latency ---------------------------------------

def test_pose_tag_timing_error_is_below_1ms_median_with_5_to_30ms_random_link_latency():
    world = World(seed=1)
    world.run_until(lambda: world.tracker.timesync.converged, max_seconds=5.0)
    world.run(120.0, evaluate_every=10)

    evals = world.evals
    straight = [e.along_err_ns for e in evals if e.along_err_ns is not None]
    turning = [e.yaw_err_ns for e in evals if e.yaw_err_ns is not None]
    assert len(evals) > 11_000 and len(straight) > 3_000 and len(turning) > 3_000  # legs and turns both seen
    assert sum(e.usable for e in evals) / len(evals) > 0.999
    # the clock mapping: estimated vs true autopilot time of the tagged instant
    assert median_abs_ms(e.sync_err_ns for e in evals) <= 1.0
    # the same error as the pose shows it: position along the track / speed, yaw / yaw rate
    assert median_abs_ms(straight) <= 1.0
    assert median_abs_ms(turning) <= 1.0
    assert max(e.cross_m for e in evals if e.cross_m is not None) < 1e-6  # interpolation adds nothing across
    status = world.tracker.status()
    assert status.timesync.resets == 0
    assert status.streams == {"ATTITUDE": "accepted at 50 Hz", "LOCAL_POSITION_NED": "accepted at 50 Hz"}
    assert status.rates_hz["ATTITUDE"] == pytest.approx(50, abs=3)


def test_that_a_pose_is_never_extrapolated_past_the_newest_message_so_a_sample_waits_for_the_next():
    world = World(seed=1)
    world.run_until(lambda: world.tracker.timesync.converged, max_seconds=5.0)
    world.run(1.0)
    newest = world.tracker.buffer.newest_ns
    assert world.tracker.pose_at(newest - 1_000_000).usable  # between two messages: interpolated
    later = world.tracker.pose_at(newest + 1_000_000)  # past the newest: extrapolating would amplify its noise
    assert not later.usable and later.stale and not later.missing


# ----- stream requests ---------------------------------------------------------------------------------

def test_start_requests_both_streams_at_stream_hz_once_each_when_acked():
    world = World(seed=2, fly=False, stream_hz=25.0)  # the SITL's default is 50 Hz
    world.run(3.0)
    assert world.server.stats["rx_by_type"]["COMMAND_LONG"] == 2
    rates = world.tracker.status().rates_hz
    assert rates["ATTITUDE"] == pytest.approx(25, abs=2) and rates["LOCAL_POSITION_NED"] == pytest.approx(25, abs=2)
    assert world.tracker.status().streams["ATTITUDE"] == "accepted at 25 Hz"


def test_a_lost_stream_request_is_retried_until_acked():
    world = World(seed=3, fly=False, start=False)
    lost = []

    def lose_first_three_commands(frame: bytes) -> bool:
        if msg_id(frame) == COMMAND_LONG_ID and len(lost) < 3:
            lost.append(frame)
            return True
        return False

    world.up.drop = lose_first_three_commands
    world.tracker.start()
    world.run(5.0)
    assert len(lost) == 3
    assert world.tracker.status().streams["LOCAL_POSITION_NED"] == "accepted at 50 Hz"
    assert world.tracker.status().streams["ATTITUDE"] == "accepted at 50 Hz"


def test_stream_requests_give_up_after_the_attempt_limit_and_say_so():
    world = World(seed=4, fly=False, start=False)
    world.up.drop = lambda frame: msg_id(frame) == COMMAND_LONG_ID
    world.tracker.start()
    world.run(8.0)
    limit = PoseTrackerConfig().command_attempts
    assert world.tracker.status().streams["ATTITUDE"] == f"no COMMAND_ACK after {limit} attempts"
    assert world.tracker.stats["tx_commands"] == 2 * limit
    assert world.tracker.pose_at(world.clock.now_ns() - QUERY_LAG_NS).usable  # default-rate streams still serve


# ----- faults ------------------------------------------------------------------------------------------

def test_when_local_position_stops_samples_come_back_stale_never_with_an_old_pose():
    world = World(seed=5)
    world.run(20.0, evaluate_every=10)
    assert all(e.usable for e in world.evals[-100:])
    stop_w = world.w_ns
    world.down.drop = lambda frame: msg_id(frame) == LOCAL_POSITION_ID
    world.run(3.0)
    last_pos_ns = world.tracker.buffer._pos_t[-1]
    max_age = world.tracker.config.max_pose_age_ns
    for w in range(stop_w, world.w_ns, 5 * MS):
        t = world.companion_ns(w)
        pose = world.tracker.pose_at(t)
        if t > last_pos_ns + max_age:
            assert pose.stale and math.isnan(pose.pos_ned_m[0])
        elif t <= last_pos_ns:
            assert pose.usable  # inside the data that did arrive
    pose_now = world.tracker.pose_at(world.clock.now_ns())
    assert pose_now.stale and pose_now.age_s > 2.5
    status = world.tracker.status()
    assert not status.pose_ok and status.pose_age_s > 2.5
    assert "LOCAL_POSITION_NED" not in status.rates_hz and status.rates_hz["ATTITUDE"] > 45


def test_without_local_position_the_status_tells_the_operator_about_the_ekf_origin():
    world = World(seed=6, fly=False)
    world.down.drop = lambda frame: msg_id(frame) == LOCAL_POSITION_ID
    world.run(3.0)
    pose = world.tracker.pose_at(world.clock.now_ns() - QUERY_LAG_NS)
    assert pose.missing
    assert "SET_GPS_GLOBAL_ORIGIN" in world.tracker.status().pose_status


def test_before_time_sync_converges_no_pose_is_given_and_the_status_says_why():
    world = World(seed=7, fly=False, start=False)
    world.up.drop = lambda frame: msg_id(frame) == mavlink.MAVLINK_MSG_ID_TIMESYNC
    world.tracker.start()
    world.run(2.0)
    assert world.tracker.pose_at(world.clock.now_ns() - QUERY_LAG_NS).missing
    assert "waiting for TIMESYNC replies" in world.tracker.status().pose_status
    assert world.tracker.stats["pose_dropped_unsynced"] > 150


def test_autopilot_reboot_resets_time_sync_which_reconverges_on_the_new_boot():
    world = World(seed=8, stream_hz=25.0)  # the rebooted autopilot's default would be 50 Hz
    world.run(30.0)
    assert world.tracker.timesync.converged
    flying_down_m = world.vehicle.state().pos_ned_m[2]
    # reboot: 2 s of silence (frames in flight are lost), then a fresh autopilot whose clock starts at 0
    world.up.clear()
    world.down.clear()
    silent_from = world.w_ns
    old_server, world.server = world.server, None
    for _ in range(2000):
        world.w_ns += DT_NS
        world.clock.set_ns(world.companion_ns(world.w_ns))
        world.tracker.pump()
    assert world.tracker.pose_at(world.companion_ns(silent_from + 500 * MS)).stale  # no pose invented
    world.boot(fly=False)
    world.run_until(lambda: world.tracker.timesync.stats["resets"] >= 1, max_seconds=1.0)
    assert world.tracker.pose_at(world.companion_ns(silent_from - 200 * MS)).missing  # old poses were dropped
    assert "reboot" in world.tracker.timesync.last_reset_reason
    took_s = world.run_until(lambda: world.tracker.timesync.converged, max_seconds=5.0)
    assert took_s < 2.0
    world.run(1.0)
    world.evals.clear()
    world.run(60.0, evaluate_every=10)
    assert all(e.usable for e in world.evals)
    assert median_abs_ms(e.sync_err_ns for e in world.evals) <= 1.0
    pose = world.tracker.pose_at(world.clock.now_ns() - QUERY_LAG_NS)
    assert pose.usable and pose.pos_ned_m[2] == pytest.approx(0.0) and flying_down_m < -4.0
    assert world.server.stats["rx_by_type"]["COMMAND_LONG"] >= 2 and old_server is not world.server
    assert world.tracker.status().rates_hz["LOCAL_POSITION_NED"] == pytest.approx(25, abs=2)  # asked for again


@pytest.mark.parametrize("jump_ns", [HOUR_NS, -HOUR_NS])
def test_companion_clock_jump_of_an_hour_resets_time_sync_which_reconverges(jump_ns):
    world = World(seed=9, jumpable=True)
    world.run(20.0)
    assert world.tracker.timesync.converged
    world.clock.jump_ns = jump_ns
    world.run_until(lambda: world.tracker.timesync.stats["resets"] >= 1, max_seconds=1.0)
    reason = world.tracker.timesync.last_reset_reason
    assert "jump" in reason
    world.run_until(lambda: world.tracker.timesync.converged, max_seconds=5.0)
    world.run(1.0)  # the instants queried (100 ms back) are after convergence: earlier poses were dropped
    world.evals.clear()
    world.run(60.0, evaluate_every=10)
    assert all(e.usable for e in world.evals)
    assert median_abs_ms(e.sync_err_ns for e in world.evals) <= 1.0
    assert median_abs_ms(e.along_err_ns for e in world.evals if e.along_err_ns is not None) <= 1.0
    assert world.tracker.timesync.stats["resets"] == 1


def test_latency_outliers_are_rejected_without_resets_or_loss_of_accuracy():
    world = World(seed=10)
    world.up.outlier_p = world.down.outlier_p = 0.05  # 5 % of frames each way stall 100-400 ms
    world.run_until(lambda: world.tracker.timesync.converged, max_seconds=5.0)
    world.run(60.0, evaluate_every=10)
    ts = world.tracker.timesync.stats
    assert ts["rejected_rtt"] > 20
    assert ts["resets"] == 0
    assert median_abs_ms(e.sync_err_ns for e in world.evals) <= 1.0
    assert median_abs_ms(e.along_err_ns for e in world.evals if e.along_err_ns is not None) <= 1.0
    assert world.tracker.buffer.stats["out_of_order"] > 100  # late pose frames were slotted in by time


def test_a_seeded_world_is_deterministic():
    def fingerprint() -> tuple:
        world = World(seed=11)
        world.run(5.0)
        return world.tracker.timesync.offset_ns, world.tracker.pose_at(world.clock.now_ns() - QUERY_LAG_NS)

    assert fingerprint() == fingerprint()


# ----- protocol details, with a scripted link ----------------------------------------------------------

class ScriptedLink:
    """A MavlinkLink whose received messages the test queues, keeping everything the tracker sends."""

    def __init__(self) -> None:
        self.inbox: list = []
        self.sent: list = []
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)

    def send(self, msg) -> None:
        self.sent.append(msg)

    def recv(self) -> list:
        out, self.inbox = self.inbox, []
        return out

    def close(self) -> None:
        pass

    def queue(self, msg, sysid: int = 1, compid: int = 1) -> None:
        """As if received from (sysid, compid): pack and decode so headers are real."""
        sender = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.inbox.append(mavlink.MAVLink(None).decode(bytearray(msg.pack(sender))))


def test_timesync_replies_from_another_system_do_not_touch_the_estimate():
    link, clock = ScriptedLink(), SimClock(start_ns=10 * S)
    tracker = PoseTracker(link, clock)
    tracker.pump()
    ts1 = next(m.ts1 for m in link.sent if m.get_type() == "TIMESYNC")
    link.queue(mavlink.MAVLink_timesync_message(999 * S, ts1), sysid=255, compid=190)  # a GCS answering
    clock.advance_by_ns(10 * MS)
    tracker.pump()
    assert tracker.timesync.offset_ns is None and tracker.stats["rx_not_autopilot"] == 1
    link.queue(mavlink.MAVLink_timesync_message(3 * S, ts1))
    tracker.pump()
    assert tracker.timesync.offset_ns == 3 * S - (10 * S + 5 * MS)


def test_that_an_autopilot_never_heard_is_said_first_naming_the_link_and_for_how_long():
    """Waiting for TIMESYNC replies is only the consequence: the fact to act on is that nothing answers."""
    link, clock = ScriptedLink(), SimClock(start_ns=10 * S)
    tracker = PoseTracker(link, clock, link_name="udpout:127.0.0.1:14999")
    tracker.start()
    for _ in range(120):  # 12 s, nothing received
        clock.advance_by_ns(100 * MS)
        tracker.pump()
    assert tracker.status().pose_status == ("no HEARTBEAT from the autopilot (system 1) on udpout:127.0.0.1:14999 "
                                            "for 12 s: is it connected, is the link's URL right?")
    link.queue(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                 0, 0, mavlink.MAV_STATE_STANDBY, 3))
    tracker.pump()
    assert tracker.status().pose_status.startswith("waiting for TIMESYNC replies from the autopilot (system 1)")


def test_the_autopilots_timesync_request_is_answered_with_our_clock():
    link, clock = ScriptedLink(), SimClock(start_ns=10 * S)
    tracker = PoseTracker(link, clock)
    link.queue(mavlink.MAVLink_timesync_message(0, 77 * S))
    tracker.pump()
    answers = [m for m in link.sent if m.get_type() == "TIMESYNC" and m.tc1 != 0]
    assert [(m.tc1, m.ts1) for m in answers] == [(10 * S, 77 * S)]


def test_heartbeat_goes_out_at_1hz_and_timesync_requests_speed_up_until_converged():
    link, clock = ScriptedLink(), SimClock(start_ns=10 * S)
    tracker = PoseTracker(link, clock, timesync_hz=1.0)
    for _ in range(5000):  # 5 s in 1 ms pumps, no replies: never converges
        tracker.pump()
        clock.advance_by_ns(MS)
    kinds = [m.get_type() for m in link.sent]
    assert kinds.count("HEARTBEAT") == 5
    assert kinds.count("TIMESYNC") == 50  # the 10 Hz convergence rate
    hb = next(m for m in link.sent if m.get_type() == "HEARTBEAT")
    assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER


def test_a_clock_that_goes_back_does_not_stall_the_periodic_messages():
    link, world_clock = ScriptedLink(), [100 * S]

    class BackClock:
        def now_ns(self) -> int:
            return world_clock[0]

        def sleep_until_ns(self, t_ns: int) -> None:
            pass

    tracker = PoseTracker(link, BackClock())
    tracker.pump()
    sent = len(link.sent)
    world_clock[0] -= HOUR_NS
    tracker.pump()
    assert {m.get_type() for m in link.sent[sent:]} >= {"HEARTBEAT", "TIMESYNC"}


def test_command_ack_denied_is_reported_not_retried():
    link, clock = ScriptedLink(), SimClock(start_ns=10 * S)
    tracker = PoseTracker(link, clock)
    tracker.start()
    link.queue(mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_DENIED,
                                                   0, 0, 1, 191))
    tracker.pump()
    assert tracker.status().streams["ATTITUDE"] == "refused: MAV_RESULT_DENIED"
    commands = [m for m in link.sent if m.get_type() == "COMMAND_LONG"]
    assert [int(m.param1) for m in commands] == [ATTITUDE_ID, LOCAL_POSITION_ID]
    assert commands[0].param2 == pytest.approx(20_000)  # us between messages at 50 Hz


@pytest.mark.parametrize("kw,name", [
    ({"target_system": 0}, "target_system"), ({"stream_hz": 0.0}, "stream_hz"),
    ({"timesync_hz": math.nan}, "timesync_hz"), ({"max_pose_age_ns": 0}, "max_pose_age_ns"),
    ({"buffer_capacity": 0}, "buffer_capacity"),
])
def test_bad_tracker_settings_are_refused_naming_the_value(kw, name):
    with pytest.raises(ValueError, match=name):
        PoseTracker(ScriptedLink(), SimClock(), **kw)


# ----- real UDP ---------------------------------------------------------------------------------------

def test_udp_smoke_pose_tracker_on_pymavlink_link_against_the_sitl_autopilot():
    vehicle = KinematicVehicle(dt_s=0.002, speed_m_s=2.0, altitude_m=5.0)
    transport = UdpTransport("udp:127.0.0.1:0")
    server = MavlinkVehicleServer(vehicle, transport)
    link = PymavlinkLink(f"udpout:127.0.0.1:{transport.local_address[1]}")
    clock = MonotonicClock()
    tracker = PoseTracker(link, clock)
    vehicle.set_mode(FlightMode.GUIDED)
    vehicle.arm()
    vehicle.load_mission(square_mission())
    vehicle.start_mission()
    try:
        t0 = time.monotonic()
        tracker.start()
        pose = None
        while time.monotonic() - t0 < 4.0:
            while vehicle.t_s < time.monotonic() - t0:  # the vehicle's clock follows the wall clock
                vehicle.step()
            server.update()
            tracker.pump()
            streams = tracker.status().streams.values()
            if tracker.timesync.converged and all(v.startswith("accepted") for v in streams):
                pose = tracker.pose_at(clock.now_ns() - QUERY_LAG_NS)
                if pose.usable:
                    break
            time.sleep(0.001)
    finally:
        link.close()
        transport.close()
    assert pose is not None and pose.usable
    assert -5.0 <= pose.pos_ned_m[2] <= 0.0  # climbing to 5 m
    assert server.stats["rx_by_type"]["COMMAND_LONG"] >= 2 and server.stats["rx_by_type"]["HEARTBEAT"] >= 1


def test_that_the_status_is_a_frozen_snapshot_and_its_dict_is_plain_json():
    clock = SimClock(start_ns=1_000_000_000)
    tracker = PoseTracker(ByteStreamLink(lambda _d: None, lambda: b""), clock)
    tracker.start()
    status = tracker.status()
    assert not status.pose_ok and status.pose_age_s is None and not status.timesync.converged
    with pytest.raises(dataclasses.FrozenInstanceError):
        status.pose_ok = True
    with pytest.raises(TypeError):
        status.streams["ATTITUDE"] = "accepted"  # read-only, so a later status cannot be confused with it
    d = status.as_dict()
    assert json.loads(json.dumps(d)) == d and d["timesync"]["samples"] == 0 and d["streams"] == dict(status.streams)


def test_that_parameters_are_read_by_name_from_the_autopilot_alone_and_the_unanswered_asked_again_until_the_limit():
    link, clock = ScriptedLink(), SimClock(start_ns=10 * S)
    tracker = PoseTracker(link, clock)
    tracker.request_params(("EK3_SRC1_POSZ", "EK3_SRC1_POSXY"))
    reads = lambda: [m.param_id for m in link.sent if m.get_type() == "PARAM_REQUEST_READ"]  # noqa: E731
    assert reads() == ["EK3_SRC1_POSZ", "EK3_SRC1_POSXY"] and not tracker.params_settled
    link.queue(mavlink.MAVLink_param_value_message(b"EK3_SRC1_POSZ", 2.0, 9, 2, 0), sysid=255, compid=190)  # a GCS
    link.queue(mavlink.MAVLink_param_value_message(b"EK3_SRC1_POSXY", 0.0, 9, 2, 1))
    link.queue(mavlink.MAVLink_param_value_message(b"PS_SPEED_MS", 1.0, 9, 2, 2))  # not asked for: ignored
    tracker.pump()
    assert tracker.params == {"EK3_SRC1_POSXY": 0.0} and tracker.autopilot_heard
    limit, timeout = PoseTrackerConfig().command_attempts, PoseTrackerConfig().command_timeout_ns
    for _ in range(3 * limit):
        clock.advance_by_ns(timeout)
        tracker.pump()
    assert reads().count("EK3_SRC1_POSZ") == limit and reads().count("EK3_SRC1_POSXY") == 1
    assert tracker.params_settled and "EK3_SRC1_POSZ" not in tracker.params  # given up on: the header says nothing


def test_that_a_parameter_answered_settles_the_read_at_once():
    link, clock = ScriptedLink(), SimClock(start_ns=10 * S)
    tracker = PoseTracker(link, clock)
    tracker.request_params(("AHRS_EKF_TYPE",))
    link.queue(mavlink.MAVLink_param_value_message(b"AHRS_EKF_TYPE", 3.0, 9, 1, 0))
    tracker.pump()
    assert tracker.params_settled and tracker.params == {"AHRS_EKF_TYPE": 3.0}
